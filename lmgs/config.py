"""Frozen configs of the neural parts of the model, with CPU (``quick``) and paper presets.

Each section is a frozen dataclass; the full model config embeds them. Presets are
classmethods (``quick()``, ``paper()``) so a caller names a preset instead of copying numbers.
Sizes follow ER-NeRF / TalkingGaussian where they are known; the ``quick`` presets shrink them
so that the per-frame deformation of 10k Gaussians stays well under 20 ms on 2 CPU cores
(measured by ``lmgs-eval bench model``).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import types
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

from lmgs.errors import InputError

AudioKind = Literal["logmel", "mfcc", "ds", "hu", "wavlm"]


def added_option(neutral: Any, default: Any = None) -> Any:
    """A field added after records existed; ``neutral`` is the behaviour before it.

    :func:`config_dict` leaves it out while it holds ``neutral``, so the config and its hash
    (and every record and checkpoint made before the option) stay what they were. ``default``
    (when given) is a new default that differs from ``neutral``: configs at it hash anew.
    """
    return field(default=neutral if default is None else default, metadata={"omit_when": neutral})


def config_dict(obj: Any) -> Any:
    """:func:`dataclasses.asdict`, without :func:`added_option` fields at their neutral value."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {}
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if "omit_when" in f.metadata and v == f.metadata["omit_when"]:
                continue
            out[f.name] = config_dict(v)
        return out
    if isinstance(obj, (list, tuple)):
        return type(obj)(config_dict(x) for x in obj)
    if isinstance(obj, dict):
        return {k: config_dict(v) for k, v in obj.items()}
    return copy.deepcopy(obj)


def config_hash(config: Any) -> str:
    """16 hex digits of the sha256 of a config as JSON (sorted keys): the one hasher of configs.

    ``config`` is a mapping, or a dataclass (taken through :func:`config_dict`). A trained model,
    its checkpoint folder and every record made with it are named by this hash.
    """
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = config_dict(config)
    blob = json.dumps(config, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _type_name(tp: Any) -> str:
    if get_origin(tp) is Literal:
        return " or ".join(repr(a) for a in get_args(tp))
    if get_origin(tp) in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if tp is type(None):
        return "null"
    if get_origin(tp) is tuple:
        args = get_args(tp)
        if args and args[-1] is not Ellipsis:
            return f"a list of {len(args)} {_type_name(args[0]).removeprefix('an ').removeprefix('a ')}s"
        return "a list"
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(tp, getattr(tp, "__name__", str(tp)))


def _coerce(value: Any, tp: Any) -> tuple[bool, Any]:
    """``(ok, value)``: ``value`` as a field of type ``tp`` takes it (an int for a float, a list for a tuple)."""
    origin = get_origin(tp)
    if tp is Any:
        return True, value
    if origin is Literal:
        return value in get_args(tp), value
    if origin in (Union, types.UnionType):
        for a in get_args(tp):
            ok, v = _coerce(value, a)
            if ok:
                return True, v
        return False, value
    if tp is type(None):
        return value is None, value
    if tp is bool:
        return isinstance(value, bool), value
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if tp is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return ok, float(value) if ok else value
    if tp is str:
        return isinstance(value, str), value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            return False, value
        args = get_args(tp)
        if args and args[-1] is not Ellipsis and len(args) != len(value):
            return False, value  # a fixed-length tuple
        items = [args[0] if (not args or args[-1] is Ellipsis) else args[i] for i in range(len(value))] if args else []
        out = []
        for x, item in zip(value, items or [Any] * len(value)):
            ok, v = _coerce(x, item)
            if not ok:
                return False, value
            out.append(v)
        return True, tuple(out)
    return True, value


def override(config: Any, changes: Mapping[str, Any], *, what: str = "--set") -> Any:
    """A copy of a frozen dataclass config with dotted changes, each checked against its field's type.

    ``override(cfg, {"train.dynamic_steps": 4000, "gr": False})``. This is the one path every
    method's ``--set KEY=VALUE`` takes. A key that is not a field, or a value of the wrong type,
    is an :class:`~lmgs.errors.InputError` of one line naming the key (``what`` says where it
    came from) and what it takes. Integers are taken for float fields and lists for tuples.
    """
    for key, value in changes.items():
        config = _override_one(config, key.split("."), value, key, what)
    return config


def _override_one(obj: Any, parts: list[str], value: Any, key: str, what: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(obj)}
    name = parts[0]
    if name not in fields:
        raise InputError(f"{what} {key}: {type(obj).__name__} has no field '{name}'; its fields: {', '.join(sorted(fields))}")
    hints = get_type_hints(type(obj))
    current = getattr(obj, name)
    if len(parts) > 1:
        if not (dataclasses.is_dataclass(current) and not isinstance(current, type)):
            raise InputError(f"{what} {key}: '{name}' is a value, not a section with fields")
        return dataclasses.replace(obj, **{name: _override_one(current, parts[1:], value, key, what)})
    if dataclasses.is_dataclass(current) and not isinstance(current, type):
        raise InputError(f"{what} {key}: '{name}' is a section; set one of its fields ({key}.FIELD)")
    ok, coerced = _coerce(value, hints[name])
    if not ok:
        raise InputError(f"{what} {key}={value!r}: expected {_type_name(hints[name])}, got {type(value).__name__}")
    return dataclasses.replace(obj, **{name: coerced})


@dataclass(frozen=True)
class AudioConfig:
    """Audio front end, Audio Encoder and attention smoother.

    Attributes:
        frontend: which per-frame features: ``logmel`` (computed here, the default), ``mfcc``,
            or precomputed ``ds`` (``aud_ds.npy`` [N,16,29]), ``hu`` (``aud_hu.npy`` [N,2,1024]),
            ``wavlm`` (a user array [N,T,C] or [N,C]).
        n_mels: mel bands of ``logmel`` (and the filterbank under ``mfcc``).
        n_mfcc: cepstral coefficients kept by ``mfcc``.
        win_ms, hop_ms: STFT window and hop in milliseconds (25 ms / 10 ms: 100 steps/s).
        n_fft: FFT size (>= window length in samples).
        window_steps: spectrogram steps per video frame window (16 steps = 160 ms, centred).
        encoder_channels: channels of the four 1D convolutions of the Audio Encoder.
        dim: size of the compact audio feature :math:`F_a`.
        smooth_frames: frames seen by the attention smoother (8: features[i-4:i+4]).
        use_encoder: ``False`` is the paper's "w/o Audio Encoder" ablation (mean over the
            window, then one linear projection).
        use_smoother: apply the attention smoother over neighbouring frames.
    """

    frontend: AudioKind = "logmel"
    n_mels: int = 80
    n_mfcc: int = 20
    win_ms: float = 25.0
    hop_ms: float = 10.0
    n_fft: int = 512
    window_steps: int = 16
    encoder_channels: tuple[int, int, int, int] = (32, 32, 64, 64)
    dim: int = 32
    smooth_frames: int = 8
    use_encoder: bool = True
    use_smoother: bool = True

    @classmethod
    def quick(cls) -> "AudioConfig":
        return cls()

    @classmethod
    def paper(cls) -> "AudioConfig":
        return cls(frontend="wavlm", dim=64, encoder_channels=(64, 64, 64, 64))


@dataclass(frozen=True)
class TriplaneConfig:
    """Tri-plane hash encoder (three 2D multiresolution hash grids, ER-NeRF).

    Attributes:
        n_levels: resolution levels per plane.
        n_features: features per level.
        log2_table_size: :math:`\\log_2 T`, the hash table size per level.
        base_resolution: coarsest grid resolution :math:`N_{min}`.
        finest_resolution: finest grid resolution :math:`N_{max}`.
        bound: half-size of the cube ``[-bound, bound]^3`` mapped onto ``[0,1]^3`` when no box is given.
    """

    n_levels: int = 8
    n_features: int = 2
    log2_table_size: int = 14
    base_resolution: int = 16
    finest_resolution: int = 256
    bound: float = 1.0

    @property
    def out_dim(self) -> int:
        return 3 * self.n_levels * self.n_features

    @classmethod
    def quick(cls) -> "TriplaneConfig":
        return cls()

    @classmethod
    def paper(cls) -> "TriplaneConfig":
        # ER-NeRF / TalkingGaussian: 16 levels x 2 features, finest 512 (about), table 2^17 on GPU.
        return cls(n_levels=16, n_features=2, log2_table_size=17, base_resolution=16, finest_resolution=512)


@dataclass(frozen=True)
class GuidanceConfig:
    """Spatial Enhancement (SE) and Landmark Compensation (LC), from the paper.

    Attributes:
        se: enable Spatial Enhancement.
        lc: enable Landmark Compensation.
        theta: cosine-similarity threshold :math:`\\theta` of SE (paper: 0.6).
        n_landmarks: keypoints per frame (68).
        cond_dim: size of the global landmark condition :math:`c_{lms}`.
        hidden: hidden width of :math:`\\psi`, :math:`MLP_{offset}` and :math:`MLP_\\tau`.
        tau_activation: activation giving :math:`\\tau_i` (``sigmoid``: in (0, 1)).
        select_fraction: at most this share of the face points per frame is selected, the most
            similar ones (the threshold is raised to the similarity of the last one kept, never
            lowered below :math:`\\theta`); 0.2 by default, the share the paper reports at
            :math:`\\theta` = 0.6 ("about 20 %"). Here :math:`\\theta` = 0.6 alone selected 17-79 %
            of the face points depending on the trained model (61-79 % on astronaut), and lmgs with
            that uncapped SE did worse than without SE on astronaut; 0 leaves
            :math:`\\theta` alone (variant ``lmgs-uncapped``, the records made before the cap).
            An :func:`added_option`.
        mouth_state: the face and mouth deformations also read the frame's mouth state, two numbers
            from the same 68 landmarks SE and LC read (the inner lips' opening, 62-66, and the
            mouth's width, 48-54, each over the outer eye corners' distance, 36-45; centred and
            scaled by their spread over the training frames), through the expression input and its
            region attention, as the blink is read. SE and LC reach the landmarks through the
            tri-plane's features of their 3D positions, in which a lip opening of a few
            millimetres is a small, irregular change; this is the opening itself. Not in the
            paper; an :func:`added_option` (off).
    """

    se: bool = True
    lc: bool = True
    theta: float = 0.6
    n_landmarks: int = 68
    cond_dim: int = 32
    hidden: int = 32
    tau_activation: Literal["sigmoid", "tanh"] = "sigmoid"
    select_fraction: float = added_option(0.0, 0.2)
    mouth_state: bool = added_option(False)

    @property
    def reads_landmarks(self) -> bool:
        """Whether the model reads the audio-predicted landmarks (SE, LC or the mouth state)."""
        return bool(self.se or self.lc or self.mouth_state)

    def __post_init__(self) -> None:
        if not 0.0 <= self.select_fraction < 1.0:
            raise ValueError(f"guidance.select_fraction must be in [0, 1), not {self.select_fraction!r}")

    @classmethod
    def quick(cls) -> "GuidanceConfig":
        return cls()

    @classmethod
    def paper(cls) -> "GuidanceConfig":
        return cls(cond_dim=64, hidden=64)


@dataclass(frozen=True)
class DeformConfig:
    """Region-attention deformation network (TalkingGaussian / ER-NeRF style).

    Attributes:
        hidden: width of the offset MLP.
        n_layers: hidden layers of the offset MLP.
        att_hidden: width of the attention MLPs.
        attention: ``sigmoid`` (channel gates in (0, 1)) or ``softmax`` (over the channels of a modality).
        exp_dim: size of the extra expression vector (0: blink AU45 only).
        blink: use the blink (AU45) scalar.
        position_only: predict only position offsets (TalkingGaussian's mouth branch).
        position_scale: position offsets are the MLP output times this (TalkingGaussian: 1e-2).
        zero_init: the offset MLP's last layer starts at zero, so the dynamic stage starts from
            the static stage's solution (as Landmark Compensation's head). Off by default: it
            keeps large budgets from collapsing (a 16,000-Gaussian hopper run whose audio encoder
            ran away, |F_a| ~ 500, throwing the face off-screen, trained normally with it), but
            on the default budget it cost lip sync on all 3 hopper seeds (self LSE-C 0.31 -> 0.21
            mean; PSNR and LPIPS unchanged). Without it :class:`lmgs.train.CollapseGuard` stops
            a run that collapses.
        bound_audio: feed ``tanh(F_a)`` instead of :math:`F_a`. Off: it also stopped that
            collapse, but training then drove F_a into saturation (98 % of entries with
            |tanh| > 0.9 on hopper seed 0) and lip sync fell (LSE-C 0.40 -> 0.22).
        (Both are :func:`added_option` fields: off, they leave the config hash as it was.)
    """

    hidden: int = 64
    n_layers: int = 2
    att_hidden: int = 32
    attention: Literal["sigmoid", "softmax"] = "sigmoid"
    exp_dim: int = 0
    blink: bool = True
    position_only: bool = False
    position_scale: float = 1e-2
    zero_init: bool = added_option(False)
    bound_audio: bool = added_option(False)

    @classmethod
    def quick(cls) -> "DeformConfig":
        return cls()

    @classmethod
    def mouth(cls) -> "DeformConfig":
        return cls(blink=False, exp_dim=0, position_only=True)

    @classmethod
    def paper(cls) -> "DeformConfig":
        return cls(hidden=64, n_layers=3, att_hidden=64)
