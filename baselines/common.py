"""Shared plumbing of the baseline adapters: budgets, hashes, checkpoints, audio, driving inputs.

Every adapter in :mod:`baselines` follows the same pattern as ``baselines.lmgs_method``:
a frozen budget dataclass with named presets (``tiny`` for tests, ``quick`` for the
benchmark), its hash as ``config_hash``, ``workdir/model.pt`` reused when its hash matches,
and the device from :func:`lmgs.device.choose_device`.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from baselines.protocol import MethodInfo
from lmgs.audio import compute_features
from lmgs.config import AudioConfig, config_dict, config_hash, override
from lmgs.device import choose_device
from lmgs.errors import InputError
from lmgs.fileio import atomic_path
from lmgs.landmarks import lift_2d_landmarks
from lmgs.types import DrivingAudio, TrainingClip

CHECKPOINT_VERSION = 1
LOGMEL = AudioConfig()  # the project's audio front end (log-mel, 16 x 80 windows per frame)


BASELINE_PRESETS = ("tiny", "quick")
# Where a method that predicts landmarks from audio (GeneFace, IP_LAP, lmgs) takes their mouth from, on recorded
# footage: the generic lip model fine-tuned on the subject's training split, as their originals read pretrained
# audio-to-landmark models (lmgs's other settings there: baselines.lmgs_method.ON_FOOTAGE). On the bundled
# subjects, the per-subject predictor (the generic model learned the generator's own articulation).
ON_FOOTAGE_SOURCE = "generic-tuned"


def generic_mouth_tag(source: str) -> str | None:
    """A display name's words for a landmark source other than the per-subject predictor (None for ``subject``)."""
    return None if source == "subject" else "generic mouth" + (", tuned" if source == "generic-tuned" else "")


class Budget:
    """Base of the adapters' budgets (frozen dataclasses): each preset of :data:`BASELINE_PRESETS`
    is a classmethod of its name. ``quick`` (the benchmark's) is the defaults; ``tiny`` (tests)
    the defaults changed by the class's :attr:`TINY`."""

    TINY: dict = {}  # not a dataclass field: no annotation in the subclasses

    @classmethod
    def tiny(cls):
        return cls(**cls.TINY)

    @classmethod
    def quick(cls):
        return cls()


def preset_of(cls, name: str, method: str | None = None):
    """``cls.tiny()`` / ``cls.quick()``; a clear error for a preset the baselines do not have."""
    if name not in BASELINE_PRESETS:
        raise InputError(f"--preset {name}: method '{method or cls.__name__}' has no such preset; "
                         f"its presets: {', '.join(BASELINE_PRESETS)}")
    return getattr(cls, name)()


def configured(cls, preset: str, options: dict, method: str):
    """The preset's schedule (``cls.<preset>()``) with ``options`` applied.

    Options name the schedule's fields (``budget_density=0.5``), or come from the CLI's ``--set``
    as ``overrides={"train.budget_density": 0.5}`` (the ``train.`` prefix of lmgs's keys is
    accepted; a ``--set`` value wins over a field given directly). An unknown name is a one-line
    error listing the method's settings.
    """
    budget = preset_of(cls, preset, method)
    changes = {k: v for k, v in options.items() if k != "overrides"}
    for key, value in (options.get("overrides") or {}).items():
        changes[key.removeprefix("train.")] = value
    fields = sorted(f.name for f in dataclasses.fields(budget))
    unknown = sorted(set(changes) - set(fields))
    if unknown:
        raise InputError(f"method '{method}' has no setting {', '.join(repr(k) for k in unknown)}; "
                         f"its settings: {', '.join(fields)}")
    return override(budget, changes, what=f"--set ({method})")


def audio_windows(audio: np.ndarray, n_frames: int) -> torch.Tensor:
    """Log-mel windows ``[T, 16, 80]`` for ``n_frames`` frames (silence-padded, never truncated)."""
    return torch.from_numpy(np.ascontiguousarray(compute_features(audio, 16000, LOGMEL, n_frames=n_frames), np.float32))


def seed_all(seed: int) -> np.random.Generator:
    if not 0 <= int(seed) < 2 ** 32:
        raise InputError(f"seed {seed}: a seed is an integer from 0 to {2 ** 32 - 1}")
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


def to_u8(img: torch.Tensor) -> np.ndarray:
    """Float ``[..., 3]`` in [0, 1] -> uint8 (NaN become 0, so output is always finite)."""
    x = torch.nan_to_num(img.detach().float(), nan=0.0).clamp(0, 1)
    return (x * 255 + 0.5).to(torch.uint8).cpu().numpy()


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` through a temporary sibling and a rename, with the usual umask mode (not mkstemp's 0600)."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def load_checkpoint(path: Path, name: str, chash: str, device) -> dict:
    """Read ``model.pt`` written by :func:`atomic_save`; errors name the file and the mismatch."""
    try:
        blob = torch.load(path, map_location=device, weights_only=False)
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable checkpoint ({exc.__class__.__name__})") from None
    if not isinstance(blob, dict) or blob.get("version") != CHECKPOINT_VERSION or blob.get("method") != name:
        raise InputError(f"{path}: not a '{name}' checkpoint of version {CHECKPOINT_VERSION}")
    if blob.get("config_hash") != chash:
        raise InputError(f"{path}: made with config {blob.get('config_hash')}, asked for {chash}; delete it to retrain")
    return blob


def n_frames_of(driving: DrivingAudio) -> int:
    n = driving.n_frames
    if driving.backgrounds is not None and driving.backgrounds.shape[0] not in (1, n):
        raise InputError(f"driving backgrounds have {driving.backgrounds.shape[0]} frames, the audio/cameras {n}")
    return n


def driving_w2c(driving: DrivingAudio, train_w2c: np.ndarray, t: int) -> np.ndarray:
    """Camera of frame ``t``: the driving one, else the training poses replayed cyclically."""
    if driving.w2c is not None:
        return np.asarray(driving.w2c[t], np.float32)
    return np.asarray(train_w2c[t % len(train_w2c)], np.float32)


def driving_background(driving: DrivingAudio, default: np.ndarray, t: int) -> np.ndarray:
    """uint8 ``[H, W, 3]`` background of frame ``t``: the driving one, else the model's mean."""
    if driving.backgrounds is not None:
        b = driving.backgrounds
        return b[t if b.shape[0] > 1 else 0]
    return default


def mean_background(clip: TrainingClip) -> np.ndarray:
    return (clip.backgrounds.astype(np.float32).mean(0) + 0.5).astype(np.uint8)


def head_box(clip: TrainingClip, pad: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """World-space box around the head: depth back-projection and/or 3D landmarks, padded.

    Falls back to a cube of half-size 0.3 x camera distance around the world origin (where
    ER-NeRF / TalkingGaussian track the head) when the clip has neither.
    """
    pts = []
    if clip.depth is not None:
        step = max(1, len(clip) // 8)
        for i in range(0, len(clip), step):
            d = clip.depth[i].astype(np.float32)
            m = d > 0
            if clip.head_masks is not None:
                m &= clip.head_masks[i]
            ys, xs = np.nonzero(m)
            if len(ys) == 0:
                continue
            z = d[ys, xs]
            cam = np.stack([(xs + 0.5 - clip.cx) / clip.focal * z, (ys + 0.5 - clip.cy) / clip.focal * z, z, np.ones_like(z)], 1)
            pts.append((cam @ np.linalg.inv(clip.w2c[i]).T)[:, :3])
    if clip.landmarks3d is not None:
        pts.append(np.asarray(clip.landmarks3d, np.float32).reshape(-1, 3))
    if not pts:
        dist = float(np.linalg.norm(np.linalg.inv(clip.w2c[0])[:3, 3]))
        h = 0.3 * max(dist, 1e-3)
        return np.full(3, -h, np.float32), np.full(3, h, np.float32)
    p = np.concatenate(pts)
    lo, hi = np.percentile(p, 0.5, axis=0), np.percentile(p, 99.5, axis=0)
    size = hi - lo
    m = pad * np.maximum(size, size.max() * 0.3)
    return (lo - m).astype(np.float32), (hi + m).astype(np.float32)


def cost_of(module: torch.nn.Module | None, n_gaussians: int | None = None) -> dict:
    """``n_params``, ``n_gaussians`` (None outside the 3DGS family), ``model_mb`` (float32) and ``device``:
    where the model's parameters are, i.e. where it trained or was loaded and renders."""
    if module is None:
        return {}
    params = list(module.parameters())
    n = sum(p.numel() for p in params)
    device = str(params[0].device) if params else None
    return {"n_params": int(n), "n_gaussians": n_gaussians, "model_mb": n * 4 / 2**20, "device": device}


def landmark_targets(clip: TrainingClip) -> np.ndarray:
    """3D landmark targets ``[T, 68, 3]``: the clip's own, else its 2D tracks lifted (as lmgs does)."""
    if clip.landmarks3d is not None:
        return np.asarray(clip.landmarks3d, np.float32)
    if clip.landmarks2d is None:
        raise InputError("this method needs landmarks: the training clip has neither 3D nor 2D landmarks")

    c2w = np.linalg.inv(clip.w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])
    return lift_2d_landmarks(clip.landmarks2d, c2w, clip.focal, clip.cx, clip.cy).numpy()


def check_landmark_source(budget, method: str, reads_landmarks: bool) -> None:
    """A budget's ``landmark_source`` (where the mouth of the audio-predicted landmarks comes from) must be one
    lmgs knows, and other than ``subject`` only for a method that reads such landmarks."""
    from lmgs.presets import LANDMARK_SOURCES

    source = getattr(budget, "landmark_source", "subject")
    if source not in LANDMARK_SOURCES:
        raise InputError(f"--set landmark_source={source}: not one of {', '.join(LANDMARK_SOURCES)}")
    if source != "subject" and not reads_landmarks:
        raise InputError(f"--set landmark_source={source}: method '{method}' reads no audio-predicted landmarks "
                         "(geneface and ip_lap do, as lmgs does)")
    weights = getattr(budget, "lip_weights", None)
    if weights is not None:
        check_lip_weights(weights, source)


def check_lip_weights(weights: str, source: str, prefix: str = "") -> None:
    """A lip model's weights setting (``{prefix}lip_weights``) names weights lmgs has, and differs from the shipped
    ones only where the generic mouth is read (``{prefix}landmark_source`` other than ``subject``)."""
    from lmgs.lips_weights import DEFAULT, check_weights

    if weights != DEFAULT and source == "subject":
        raise InputError(f"--set {prefix}lip_weights={weights}: the lip model is read only with --set "
                         f"{prefix}landmark_source=generic or generic-tuned")
    try:
        check_weights(weights)
    except InputError as exc:
        raise InputError(f"--set {prefix}lip_weights: {exc}") from None


def lip_weights_read(source: str, weights: str | None) -> str | None:
    """The lip model's weights a method reads under landmark source ``source`` (None under ``subject``)."""
    if source == "subject":
        return None
    from lmgs.lips import DEFAULT

    return weights or DEFAULT


def fit_mouth_model(source: str, clip: TrainingClip, targets: np.ndarray, seed: int,
                    weights: str | None = None) -> dict | None:
    """The generic lip model (:mod:`lmgs.lips`; ``weights``, default the shipped one) retargeted to ``clip`` from its
    68 landmark targets ``[T, 68, 3]``, fine-tuned on them for ``generic-tuned``, as its JSON-able state (what a
    checkpoint's ``build`` keeps); ``None`` for ``subject`` (the method's own predictor gives the whole face)."""
    from lmgs.lips import DEFAULT, retarget_for

    lips = retarget_for(source, clip.audio, len(clip), targets, seed, weights=weights or DEFAULT)
    return None if lips is None else lips.to_state()


def mouth_model(build: dict):
    """``(constructor arguments, lmgs.lips.RetargetedLips or None)`` from a checkpoint's ``build``."""
    rest = {k: v for k, v in build.items() if k != "lips"}
    state = build.get("lips")
    if state is None:
        return rest, None
    from lmgs.lips import RetargetedLips

    return rest, RetargetedLips.from_state(state)


def with_generic_mouth(lips, lms: torch.Tensor, windows: torch.Tensor) -> torch.Tensor:
    """Landmarks ``[T, 68, 3]`` with the mouth (48-67) replaced by ``lips``'s prediction from the audio windows
    ``[T, 16, 80]`` (the project's log-mel front end, which the lip model reads); ``lms`` itself when ``lips`` is None."""
    return lms if lips is None else lips.with_mouth(lms, windows.detach().cpu().numpy())


def project(points: np.ndarray, w2c: np.ndarray, focal: float, cx: float, cy: float) -> np.ndarray:
    """World points ``[..., 3]`` -> pixels ``[..., 2]`` (OpenCV camera)."""
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = np.maximum(p[..., 2:3], 1e-6)
    return np.concatenate([focal * p[..., 0:1] / z + cx, focal * p[..., 1:2] / z + cy], -1)


class Adapter:
    """Base of the torch-module baselines: checkpoint reuse, device, describe/cost plumbing.

    Subclasses set ``name``, ``display_name``, ``family``, ``description``, ``standins`` and
    implement ``_train(clip, seed, progress) -> (module, build)`` (``build``: the JSON-able
    constructor arguments) and ``_build(build) -> module``, plus :meth:`render`.
    """

    name = ""
    display_name = ""
    family = ""
    description = ""
    standins: tuple[str, ...] = ()

    reads_landmarks = False  # whether the method reads audio-predicted landmarks (a budget's landmark_source)

    def __init__(self, preset: str = "quick", device: str | None = None, footage: bool = False, **overrides):
        if footage and self.reads_landmarks:  # recorded footage: the generic lip model's mouth (a --set wins)
            overrides = {"landmark_source": ON_FOOTAGE_SOURCE, **overrides}
        self.cfg = configured(self.budget_cls, preset, overrides, self.name)
        check_landmark_source(self.cfg, self.name, self.reads_landmarks)
        self.preset = preset
        self.device = device
        self.model = None
        self.fit_seconds: float | None = None

    budget_cls: type = object

    @property
    def dev(self) -> torch.device:
        return choose_device(self.device)

    def config(self) -> dict:
        return {"method": self.name, "preset": self.preset, **config_dict(self.cfg)}

    def config_hash(self) -> str:
        return config_hash(self.config())

    def fit(self, clip: TrainingClip, *, seed: int, workdir: Path, progress: bool = True) -> None:
        if len(clip) < 4:
            raise InputError(f"training clip has {len(clip)} frames; {self.name} needs at least 4")
        final = Path(workdir) / "model.pt"
        if final.exists():
            blob = load_checkpoint(final, self.name, self.config_hash(), self.dev)
            self.model = self._build(blob["build"]).to(self.dev)
            self.model.load_state_dict(blob["state"])
            self.model.eval()
            self.fit_seconds = blob.get("fit_seconds")
            return
        t0 = time.perf_counter()
        with torch.random.fork_rng(devices=[]):
            model, build = self._train(clip, seed, progress)
        self.model = model.eval()
        self.fit_seconds = time.perf_counter() - t0
        atomic_save({"version": CHECKPOINT_VERSION, "method": self.name, "config_hash": self.config_hash(),
                     "config": self.config(), "build": build, "state": model.state_dict(),
                     "fit_seconds": self.fit_seconds}, final)

    def _train(self, clip: TrainingClip, seed: int, progress: bool):  # pragma: no cover - abstract
        raise NotImplementedError

    def _start(self, clip: TrainingClip, seed: int) -> tuple[torch.device, np.random.Generator, int, torch.Tensor]:
        """Where a ``_train`` starts: the device, the generator of ``seed`` (torch seeded alike),
        the clip's frame count and its audio windows ``[T, 16, 80]`` on the device."""
        dev = self.dev
        rng = seed_all(seed)
        n = len(clip)
        return dev, rng, n, audio_windows(clip.audio, n).to(dev)

    def _build(self, build: dict):  # pragma: no cover - abstract
        raise NotImplementedError

    def _check_fitted(self) -> None:
        if self.model is None:
            raise RuntimeError(f"{self.name}: render() before fit()")

    def lip_weights(self) -> str | None:
        """The generic lip model's weights this method reads (None where it reads none)."""
        return lip_weights_read(getattr(self.cfg, "landmark_source", "subject"), getattr(self.cfg, "lip_weights", None))

    def describe(self):
        standins = self.standins
        source = getattr(self.cfg, "landmark_source", "subject")
        if source != "subject":
            from lmgs.lips_weights import describe_weights

            standins = standins + (
                f"mouth landmarks (48-67): lmgs's generic lip model ({describe_weights(self.lip_weights())}), retargeted "
                "to the subject" + (", fine-tuned on its training split" if source == "generic-tuned" else ""),)
        tag = generic_mouth_tag(source)
        return MethodInfo(name=self.name, display_name=self.display_name + (f" ({tag})" if tag else ""), family=self.family,
                          description=f"{self.description} Budget '{self.preset}': {self.budget_text()}.",
                          standins=standins, config=self.config(), config_hash=self.config_hash())

    def budget_text(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in config_dict(self.cfg).items())

    def cost(self) -> dict:
        c = cost_of(self.model, None)
        if c and self.fit_seconds is not None:
            c["fit_seconds"] = float(self.fit_seconds)
        return c


def progress_bar(total: int, desc: str, enabled: bool):
    if not enabled:
        return None

    return tqdm(total=total, desc=desc, unit="step", leave=False)
