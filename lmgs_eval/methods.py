"""The talking-head protocol every method implements, and the registry of method names.

``lmgs`` and every adapter in ``baselines/`` satisfy :class:`TalkingHead` structurally (a
``typing.Protocol``), so the model library never imports the toolkit. The toolkit turns a
:class:`~lmgs_eval.data.Subject` into the model library's own input types here
(:func:`subject_to_clip`, :func:`driving_from_subject`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from lmgs.types import DrivingAudio, TrainingClip
from lmgs_eval.data.subject import Subject
from lmgs_eval.errors import UserError


@dataclass(frozen=True)
class MethodInfo:
    """What a method says about itself; goes into every result and the tables' footnotes.

    Attributes:
        name: registry name (``lmgs``, ``talkinggaussian``, ``external:ernerf``...).
        display_name: as printed in tables.
        family: ``3DGS``, ``NeRF``, ``2D``, ``external`` or ``ground-truth``.
        description: what was kept from the original method and what was simplified.
        standins: components replaced because the original cannot be had here.
        config: the full configuration (JSON-able).
        config_hash: a short hash of ``config``; a trained model is reused when it matches.
        variant: an ablation / sweep variant of a base method (rows of Tables III-IV, not I).
    """

    name: str
    display_name: str
    family: str
    description: str
    standins: tuple[str, ...] = ()
    config: dict = field(default_factory=dict)
    config_hash: str = ""
    variant: str | None = None


@runtime_checkable
class TalkingHead(Protocol):
    """fit / render / describe: the whole contract between the toolkit and a method."""

    def fit(self, clip: TrainingClip, *, seed: int, workdir: Path, progress: bool = True) -> None:
        """Train on ``clip`` (the subject's training split); checkpoints go under ``workdir``."""

    def render(self, driving: DrivingAudio) -> np.ndarray:
        """Frames ``[T, H, W, 3]`` uint8 driven by ``driving`` (audio in, frames out)."""

    def describe(self) -> MethodInfo:
        """Name, family, what was simplified, config and its hash."""

    def cost(self) -> dict[str, Any]:
        """Size figures: ``n_params``, ``n_gaussians`` (or None), ``model_mb``."""


# ----------------------------------------------------------------------------- registry
_REGISTRY: dict[str, Callable[..., TalkingHead]] = {}
# Methods whose Gaussian count is ``budget_density`` x face area (the lmgs backbone family):
# they take a subject's own knee density, all alike, so a comparison between them stays fair.
_SCENE_BUDGET: set[str] = set()


def register(name: str, *, scene_budget: bool = False) -> Callable:
    """Decorator registering a method factory under ``name`` (duplicates are rejected).

    ``scene_budget``: the factory takes ``budget_density`` (Gaussians per face pixel), which
    :func:`create_method` sets from a subject that has its own (:attr:`Subject.budget_density`).
    """

    def deco(factory):
        if name in _REGISTRY:
            raise ValueError(f"method '{name}' registered twice")
        _REGISTRY[name] = factory
        if scene_budget:
            _SCENE_BUDGET.add(name)
        return factory

    return deco


def _load_builtin() -> None:
    # Importing these modules registers their methods.
    import importlib

    for mod in ("lmgs_eval.method_lmgs", "baselines"):
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise


def list_methods() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY) + ["external:NAME"]


def create_method(name: str, subject: Subject | None = None, **options) -> TalkingHead:
    """Build a method by name; ``external:NAME`` scores renders made by any other code.

    With ``subject``, a method sized by face area (``register(..., scene_budget=True)``) takes
    the subject's knee density when it has one and ``options`` set none; the density is in the
    method's config, so its hash, and the records and model cache, follow it.
    """
    _load_builtin()
    if name.startswith("external:"):
        from lmgs_eval.external import ExternalRenders

        return ExternalRenders(name.split(":", 1)[1], **options)
    if name not in _REGISTRY:
        raise UserError(f"unknown method '{name}'; known: {', '.join(list_methods())}")
    density = None if subject is None else subject.budget_density
    if density is not None and name in _SCENE_BUDGET:
        options.setdefault("budget_density", density)
    return _REGISTRY[name](**options)


def scene_budget_methods() -> list[str]:
    """The registered methods that size their Gaussians by face area (and take a subject's knee)."""
    _load_builtin()
    return sorted(_SCENE_BUDGET)


# ----------------------------------------------------------------------------- conversion
PARSING_HEAD = (255, 0, 0)


def _background(subject: Subject, i: int, bc: np.ndarray) -> np.ndarray:
    """The torso (``torso_imgs`` RGBA) composited over ``bc.jpg``: what lies behind the head."""
    torso = subject.torso(i)
    if torso is None:
        return bc
    a = torso[..., 3:4]
    return torso[..., :3] * a + bc * (1 - a)


def subject_to_clip(subject: Subject, ids: np.ndarray, *, progress: bool = False) -> TrainingClip:
    """Load frames ``ids`` of a subject into a :class:`TrainingClip` (uint8/float16 storage)."""
    from lmgs_eval.data.io import to_u8

    ids = np.asarray(ids)
    bc = subject.background()
    frames = np.empty((len(ids), subject.height, subject.width, 3), np.uint8)
    backs = np.empty_like(frames)
    mouth = np.zeros((len(ids), subject.height, subject.width), bool)
    head = np.zeros_like(mouth)
    have_mouth = have_head = False
    depth = normal = None
    if subject.has_geometry:
        depth = np.zeros((len(ids), subject.height, subject.width), np.float16)
        normal = np.zeros((len(ids), subject.height, subject.width, 3), np.int8)
    it = enumerate(ids)
    if progress:
        from tqdm import tqdm

        it = tqdm(list(it), desc=f"loading {subject.name}", unit="frame", leave=False)
    for k, i in it:
        frames[k] = to_u8(subject.frame(i))
        backs[k] = to_u8(_background(subject, i, bc))
        m = subject.mouth_mask(i)
        if m is not None:
            mouth[k], have_mouth = m, True
        p = subject.parsing(i)
        if p is not None:
            head[k], have_head = np.all(p == PARSING_HEAD, axis=-1), True
        if depth is not None:
            depth[k] = subject.depth(i)
            normal[k] = np.clip(np.rint(subject.normal(i) * 127), -127, 127).astype(np.int8)
    w2c = np.stack([subject.camera(i).world_to_camera.numpy() for i in ids]).astype(np.float32)
    spf = subject.samples_per_frame()
    audio = subject.audio[int(ids[0]) * spf : (int(ids[-1]) + 1) * spf]
    feats = {k: v[ids] for k, v in subject.audio_features.items()}
    return TrainingClip(
        frames=frames,
        backgrounds=backs,
        w2c=w2c,
        focal=subject.focal,
        cx=subject.cx,
        cy=subject.cy,
        audio=np.ascontiguousarray(audio),
        blink=subject.blink[ids],
        landmarks2d=subject.landmarks[ids],
        landmarks3d=None if subject.landmarks3d is None else subject.landmarks3d[ids],
        audio_features=feats or None,
        mouth_masks=mouth if have_mouth else None,
        head_masks=head if have_head else None,
        depth=depth,
        normal=normal,
    )


def driving_from_subject(subject: Subject, ids: np.ndarray, clip: TrainingClip | None = None) -> DrivingAudio:
    """The self-driven input for frames ``ids``: their audio, cameras, backgrounds and blinks."""
    ids = np.asarray(ids)
    if clip is None:
        clip = subject_to_clip(subject, ids)
    return DrivingAudio(
        audio=clip.audio,
        w2c=clip.w2c,
        backgrounds=clip.backgrounds,
        blink=clip.blink,
        audio_features=clip.audio_features,
    )
