"""Metric metadata, results, the registry and input checks shared by every metric.

A metric is three things (the torchmetrics split):

* a pure ``update`` that turns a batch of frames into *sufficient statistics* (here: the
  per-frame values and flags, since every metric of this package is a mean of per-frame
  or per-window values),
* a pure ``compute`` that turns the accumulated statistics into a :class:`MetricResult`,
* a thin accumulator (:class:`Accumulator`) that only concatenates statistics, so feeding
  frames one at a time gives exactly the result of one batch.

Each metric carries one frozen :class:`MetricSpec`; the registry maps names to factories
and rejects duplicates (the lm-evaluation-harness ``Registry``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from lmgs_eval.data.frames import CHUNK
from lmgs_eval.errors import UserError


@dataclass(frozen=True)
class MetricSpec:
    """What a metric is, written into every result.

    Attributes:
        name: registry name (``"psnr"``, ``"stlpips-alex"``, ...).
        higher_is_better: direction of improvement.
        unit: unit of the value (``"dB"``, ``"px"``, ``""``).
        backend: what computes it (``"numpy"``, ``"onnxruntime"``, ``"dlib"``...).
        version: version of *this definition*; bumped whenever a number could change.
        weights_sha256: sha256 of the weights file the value depends on, ``None`` for
            closed-form metrics (filled in when the weights are resolved).
        definition: the formula and the reference it follows, one paragraph.
        reference: paper / code the definition is taken from.
        standin: non-empty when the metric is a clearly labelled stand-in for the metric
            papers report (e.g. ST-LPIPS instead of LPIPS when the AlexNet trunk is absent).
        per: ``"frame"`` or ``"window"`` (what one entry of ``per_item`` is).
        weights_files: ``(role, path, sha256)`` of each weights file the value depends on
            (LPIPS alex: ``alexnet`` and ``lpips_heads``), when ``weights_sha256`` is a hash
            over several files; empty otherwise.
    """

    name: str
    higher_is_better: bool
    unit: str
    backend: str
    version: str
    definition: str
    reference: str = ""
    weights_sha256: str | None = None
    standin: str = ""
    per: str = "frame"
    weights_files: tuple[tuple[str, str, str], ...] = ()

    def with_weights(self, sha256: str | None, backend: str | None = None,
                     files: tuple[tuple[str, str, str], ...] = ()) -> "MetricSpec":
        return dataclasses.replace(self, weights_sha256=sha256, backend=backend or self.backend,
                                   weights_files=tuple(tuple(f) for f in files))

    def files(self) -> dict[str, dict[str, str]]:
        """``weights_files`` as ``{role: {"path", "sha256"}}``."""
        return {role: {"path": path, "sha256": sha} for role, path, sha in self.weights_files}

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d.pop("weights_files")
        if self.weights_files:
            d["weights_files"] = self.files()
        return d


@dataclass
class MetricResult:
    """The value of one metric on one clip, and exactly how it was made.

    ``value`` is the headline number (a mean over ``per_item``, unless the spec says
    otherwise); ``values`` holds every number the metric reports (e.g. LSE-D, LSE-C,
    offset); ``per_item`` the per-frame (or per-window) values used for bootstrap CIs
    (NaN where an item could not be scored, e.g. no face detected).
    """

    spec: MetricSpec
    value: float | None
    values: dict[str, float | int | None]
    per_item: np.ndarray
    n_original: int
    n_effective: int
    flags: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    available: bool = True
    reason: str = ""

    def to_dict(self, per_item: bool = True) -> dict[str, Any]:
        d: dict[str, Any] = {
            "name": self.spec.name,
            "available": self.available,
            "value": _jsonable(self.value),
            "values": {k: _jsonable(v) for k, v in self.values.items()},
            "n_original": self.n_original,
            "n_effective": self.n_effective,
            "flags": list(self.flags),
            "notes": list(self.notes),
            "spec": self.spec.to_dict(),
        }
        if not self.available:
            d["reason"] = self.reason
        if per_item:
            d["per_item"] = [_jsonable(float(v)) for v in np.asarray(self.per_item, np.float64).ravel()]
        return d


def unavailable(spec: MetricSpec, reason: str, n_original: int = 0) -> MetricResult:
    """A result that says why there is no number (never a made-up value)."""
    return MetricResult(spec, None, {}, np.zeros(0), n_original, 0, ["unavailable"], [], False, reason)


def _jsonable(v):
    if v is None:
        return None
    if isinstance(v, (np.integer, int)) and not isinstance(v, bool):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    return v


# ----------------------------------------------------------------------------- registry
class Registry:
    """Name -> factory table that rejects duplicate names and non-callables."""

    def __init__(self, kind: str):
        self.kind = kind
        self._items: dict[str, Callable[..., Any]] = {}

    def register(self, name: str, factory: Callable[..., Any]) -> Callable[..., Any]:
        if not isinstance(name, str) or not name:
            raise TypeError(f"{self.kind} name must be a non-empty string, got {name!r}")
        if not callable(factory):
            raise TypeError(f"{self.kind} {name!r}: factory must be callable, got {type(factory).__name__}")
        if name in self._items:
            raise ValueError(f"{self.kind} {name!r} is already registered")
        self._items[name] = factory
        return factory

    def get(self, name: str) -> Callable[..., Any]:
        try:
            return self._items[name]
        except KeyError:
            raise UserError(f"unknown {self.kind} {name!r}; known: {', '.join(sorted(self._items))}") from None

    def names(self) -> list[str]:
        return list(self._items)

    def __contains__(self, name: object) -> bool:
        return name in self._items


# ----------------------------------------------------------------------------- protocol
@runtime_checkable
class FrameMetric(Protocol):
    """A paired (full-reference) frame metric: ``update`` -> stats, ``compute`` -> result."""

    spec: MetricSpec

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]: ...

    def compute(self, stats: dict[str, np.ndarray]) -> MetricResult: ...


def merge_stats(parts: Iterable[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate per-item statistics along axis 0 (streaming == batch by construction)."""
    parts = list(parts)
    if not parts:
        return {}
    keys = parts[0].keys()
    return {k: np.concatenate([np.asarray(p[k]) for p in parts], axis=0) for k in keys}


def unit(x: np.ndarray) -> np.ndarray:
    """uint8 frames as float32 in [0, 1]: the one conversion, made where a computation needs floats."""
    if x.dtype != np.uint8:
        raise UserError(f"frames must be uint8 [T, H, W, 3] here, got dtype {x.dtype}")
    return x.astype(np.float32) / 255.0


class FloatFrames:
    """Base of the paired metrics that compute on float frames in [0, 1] (PSNR, SSIM).

    :meth:`stream` is how the metric suite feeds every paired metric: uint8 chunks of both clips, in
    step. These convert :data:`~lmgs_eval.data.frames.CHUNK` frames at a time, so no float copy of
    a clip is held.
    """

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    def stream(self, gt_key: str | None = None, same: bool = False):
        """A function of successive uint8 chunks ``(pred, gt)`` of two clips returning each chunk's statistics
        (``gt_key`` and ``same``, the ground truth's digest and whether ``pred`` is it, matter to metrics that
        cache the ground truth's side)."""

        def feed(pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
            return merge_stats(self.update(unit(pred[s:s + CHUNK]), unit(gt[s:s + CHUNK])) for s in range(0, len(pred), CHUNK))

        return feed


class Accumulator:
    """Streaming wrapper: ``update`` batches of frames, ``compute`` once.

    Example:
        >>> acc = Accumulator(create_metric("psnr"))
        >>> for p, g in zip(pred_chunks, gt_chunks):
        ...     acc.update(p, g)
        >>> acc.compute().value
    """

    def __init__(self, metric: FrameMetric):
        self.metric = metric
        self._parts: list[dict[str, np.ndarray]] = []

    def update(self, pred: np.ndarray, gt: np.ndarray) -> None:
        self._parts.append(self.metric.update(pred, gt))

    def reset(self) -> None:
        self._parts.clear()

    def compute(self) -> MetricResult:
        if not self._parts:
            raise UserError(f"{self.metric.spec.name}: no frames were given")
        return self.metric.compute(merge_stats(self._parts))


# ----------------------------------------------------------------------------- checks
def check_frames(x: np.ndarray, name: str) -> np.ndarray:
    """Validate frames: float ``[T, H, W, 3]`` (or one ``[H, W, 3]``), finite, in [0, 1].

    Integer frames are refused rather than guessed at (a uint8 frame divided by the wrong
    range is the classic silent PSNR bug).
    """
    x = np.asarray(x)
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[-1] != 3:
        raise UserError(f"{name}: frames must be [T, H, W, 3] RGB, got shape {tuple(x.shape)}")
    if not np.issubdtype(x.dtype, np.floating):
        raise UserError(f"{name}: frames must be float in [0, 1], got dtype {x.dtype} (divide uint8 by 255)")
    if x.shape[0] == 0:
        raise UserError(f"{name}: no frames")
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x).reshape(x.shape[0], -1).all(axis=1))[0])
        raise UserError(f"{name}: frame {bad} has non-finite pixels (NaN/inf)")
    lo, hi = float(x.min()), float(x.max())
    if lo < -1e-6 or hi > 1 + 1e-6:
        raise UserError(f"{name}: pixel values must be in [0, 1], got range [{lo:.4g}, {hi:.4g}]")
    return x


def check_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = check_frames(pred, "pred")
    gt = check_frames(gt, "gt")
    if pred.shape != gt.shape:
        raise UserError(f"pred and gt shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    return pred, gt


def align_lengths(n_pred: int, n_gt: int, truncate: bool) -> tuple[int, list[str]]:
    """Frames to score when the two clips differ in length: an error unless ``truncate``.

    Returns the common length and the flags to record (never a silent truncation).
    """
    if n_pred == n_gt:
        return n_pred, []
    if not truncate:
        raise UserError(
            f"pred has {n_pred} frames but gt has {n_gt}; pass --truncate to score the first {min(n_pred, n_gt)}"
        )
    return min(n_pred, n_gt), [f"truncated: pred {n_pred} frames, gt {n_gt} frames, scored {min(n_pred, n_gt)}"]


def mean_result(spec: MetricSpec, per_item: np.ndarray, flags: list[str], notes: list[str] | None = None,
                n_original: int | None = None) -> MetricResult:
    """Mean over the finite per-item values, with n_original / n_effective."""
    per_item = np.asarray(per_item, np.float64)
    ok = np.isfinite(per_item)
    n_eff = int(ok.sum())
    value = float(per_item[ok].mean()) if n_eff else None
    return MetricResult(spec, value, {spec.name: value}, per_item,
                        int(n_original if n_original is not None else per_item.shape[0]), n_eff,
                        sorted(set(flags)), list(notes or []))
