"""``external:NAME``: score frames rendered by any other code in the same protocol.

``--method external:ernerf --renders PATH`` points at a video (``.mp4``...) or a folder of
images (in the order of the number in their names: ``0.jpg, 1.jpg, ...`` or ``frame_0001.png``,
without a gap).
An optional sidecar JSON beside it (``PATH.json`` for a video, ``PATH/cost.json`` for a
folder) gives cost figures: ``fps``, ``train_hours``, ``device``, ``n_gaussians``,
``model_mb``. Missing figures stay empty; they are never guessed.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from baselines.protocol import EXTERNAL_PREFIX, MethodInfo, register_prefix
from lmgs.errors import InputError

SIDECAR_KEYS = ("fps", "train_hours", "device", "n_gaussians", "model_mb", "notes")


def read_sidecar(path: Path) -> dict:
    path = Path(path)
    side = path / "cost.json" if path.is_dir() else path.with_name(path.name + ".json")
    if not side.exists():
        return {}
    try:
        d = json.loads(side.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{side}: not valid JSON ({exc.msg})") from None
    unknown = sorted(set(d) - set(SIDECAR_KEYS))
    if unknown:
        raise InputError(f"{side}: unknown keys {unknown}; allowed: {', '.join(SIDECAR_KEYS)}")
    for k in ("fps", "train_hours", "n_gaussians", "model_mb"):
        v = d.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0):
            raise InputError(f"{side}: {k!r} must be a non-negative number, got {v!r}")
    for k in ("device", "notes"):
        if d.get(k) is not None and not isinstance(d[k], str):
            raise InputError(f"{side}: {k!r} must be a string, got {d[k]!r}")
    return d


@register_prefix(EXTERNAL_PREFIX)
class ExternalRenders:
    """A method whose frames were rendered elsewhere (e.g. the official ER-NeRF on a GPU).

    ``read_frames`` (a hook the toolkit passes, see :func:`baselines.protocol.create_method`)
    reads the video or folder as uint8 ``[T, H, W, 3]``; a gap in a folder's numbering is an
    :class:`~lmgs.errors.InputError`.
    """

    prerendered = True  # the protocol neither fits nor times it (see protocols.fit_render_score)
    hooks = ("read_frames",)

    def __init__(self, name: str, renders: str | Path | None = None,
                 read_frames: Callable[[Path], np.ndarray] | None = None, **_):
        if not name:
            raise InputError("external method needs a name: --method external:NAME")
        if renders is None:
            raise InputError(f"--method external:{name} needs --renders PATH (a video or a folder of frames)")
        self.name = name
        self.path = Path(renders)
        if not self.path.exists():
            raise InputError(f"{self.path}: renders not found")
        self.sidecar = read_sidecar(self.path)
        self.read_frames = read_frames
        self._frames: np.ndarray | None = None  # read once, by check() or the first render()

    def fit(self, clip, *, seed: int, workdir: Path, progress: bool = True) -> None:
        """Nothing to train: the renders exist already."""

    def check(self, driving, size: tuple[int, int] | None = None) -> None:
        """Read the renders and check them against the protocol's clip (``size``: its frames' height and
        width), so that a protocol refuses bad renders before it writes any record.

        Raises:
            InputError: the renders cannot be read, or their number or size is not the clip's.
        """
        frames = self.render(driving)
        if size is not None and tuple(frames.shape[1:3]) != tuple(size):
            raise InputError(f"{self.path}: frames of {frames.shape[2]}x{frames.shape[1]} px, but the protocol's clip is "
                             f"{size[1]}x{size[0]} px (same split, same frames expected)")

    def render(self, driving) -> np.ndarray:
        if self._frames is None:
            if self.read_frames is None:
                raise InputError(f"external:{self.name}: no frame reader; the toolkit passes one as the "
                                 "'read_frames' hook of create_method")
            self._frames = self.read_frames(self.path)
        frames = self._frames
        n = driving.n_frames
        if len(frames) != n:
            raise InputError(f"{self.path}: {len(frames)} frames, but the protocol's clip has {n} (same split, same frames expected)")
        return frames

    def describe(self) -> MethodInfo:
        return MethodInfo(
            name=f"external:{self.name}",
            display_name=self.name,
            family="external",
            description=f"frames rendered outside this toolkit, read from {self.path}; scored with the same split, frames and metrics",
            config={"renders": str(self.path), "sidecar": self.sidecar},
            config_hash="external",
        )

    def cost(self) -> dict:
        out = {k: self.sidecar.get(k) for k in ("n_gaussians", "model_mb", "device")}
        out["fps"] = self.sidecar.get("fps")
        out["train_seconds"] = None if self.sidecar.get("train_hours") is None else float(self.sidecar["train_hours"]) * 3600
        return out
