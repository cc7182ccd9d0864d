"""The record and its parts as typed values: frozen dataclasses that are the schema.

A record on disk is JSON; :meth:`Record.from_dict` reads it into these types and
:func:`decode` says, one line a field, what does not fit (``record.metrics.psnr.value: expected
number|null, got str 'high'``). The store checks every record through them when it writes and
when it reads (:func:`lmgs_eval.results.schema.validate`). A field with a default may be absent
from the JSON; ``X | None`` may be null. Constraints beyond the type (one of a set of values, a
pattern, a minimum) are in the field's metadata.

The sections (see the field table in :mod:`lmgs_eval.results`): :class:`MethodBlock` (with the
method's declared ``components``), :class:`SubjectBlock`, :class:`ProtocolBlock`,
:class:`MetricEntry` per metric key, :class:`Cost`, :class:`Code`, :class:`Machine`,
:class:`Artefact` per role, :class:`Status`, and :class:`RunFacts`: what a run measured or was
given that the tables read (the share of points Spatial Enhancement selected, the Gaussian
budget a subject imposed), as fields rather than prose.

A record read from JSON writes back the same JSON: an optional field the JSON held as ``null`` is
written as ``null`` again, one it left out stays out (:func:`replace` keeps that for the fields it
does not change).
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
from dataclasses import dataclass, field
from typing import Any, Union, get_args, get_origin, get_type_hints

FAMILIES = ("2D", "NeRF", "3DGS", "external", "ground-truth", "reference", "control")
PROTOCOLS = ("self", "cross", "stress", "calibration", "capacity")
SHA256 = "^[0-9a-f]{64}$"


def _enum(*values: str) -> Any:
    return {"enum": values}


def _nonempty() -> dict:
    return {"min_length": 1}


@dataclass(frozen=True)
class Control:
    kind: str
    targets: tuple[str, ...] = ()
    frames: int | None = None  # audio-shift controls: by how many frames


@dataclass(frozen=True)
class MethodBlock:
    name: str = field(metadata=_nonempty())
    display_name: str
    family: str = field(metadata=_enum(*FAMILIES))
    description: str
    standins: tuple[str, ...]
    variant: str | None = None
    control: Control | None = None
    # the method's switchable parts as it declares them (lmgs: se, lc, gr, theta, se_cap, ...)
    components: dict[str, Any] | None = None


@dataclass(frozen=True)
class SubjectBlock:
    name: str = field(metadata=_nonempty())
    bundled: bool
    standin: str | None
    frames: int | None
    width: int | None
    height: int | None
    path: str | None
    sha256: str | None


@dataclass(frozen=True)
class ProtocolBlock:
    name: str = field(metadata=_enum(*PROTOCOLS))
    version: str
    clip: str = field(metadata=_nonempty())
    split: str | None
    n_frames: int | None


@dataclass(frozen=True)
class MetricEntry:
    value: float | None
    n_original: int = field(metadata={"minimum": 0})
    n_effective: int = field(metadata={"minimum": 0})
    higher_is_better: bool
    unit: str
    backend: str = field(metadata=_nonempty())
    backend_version: str
    weights_sha256: str | None
    flags: tuple[str, ...]
    standin: str | None
    per_item: tuple[float | None, ...] | None
    values: dict[str, Any] | None = None
    # each weights file by role (lpips alex: alexnet, lpips_heads) when weights_sha256 is a hash over several
    weights_files: dict[str, Artefact] | None = None


@dataclass(frozen=True)
class MsPerFrame:
    audio: float | None = None
    network: float | None = None
    raster: float | None = None
    total: float | None = None


@dataclass(frozen=True)
class Cost:
    train_seconds: float | None
    fps: float | None
    ms_per_frame: MsPerFrame | None
    first_frame_ms: float | None
    realtime_factor: float | None
    n_params: int | None
    n_gaussians: int | None
    model_mb: float | None
    peak_mb: float | None
    device: str | None
    others_cpu_share: float | None = None
    host_slowdown: float | None = None
    train_others_cpu_share: float | None = None
    host_probe_best_ms: float | None = None
    host_probe_ms: tuple[float | None, ...] | None = None
    render_repeats: int | None = None
    wall_seconds: float | None = None
    fps_side_by_side: float | None = None
    fps_side_by_side_run: str | None = None


@dataclass(frozen=True)
class Code:
    version: str
    git_commit: str | None
    dirty: bool | None


@dataclass(frozen=True)
class Machine:
    cpu: str
    threads: int | None
    torch: str | None
    cuda_device: str | None
    platform: str
    cpu_kernels: str | None = None


@dataclass(frozen=True)
class Artefact:
    path: str = field(metadata=_nonempty())
    sha256: str = field(metadata={"pattern": SHA256})


@dataclass(frozen=True)
class Status:
    state: str = field(metadata=_enum("ok", "failed"))
    reason: str | None = None


@dataclass(frozen=True)
class GaussianBudget:
    """A subject's own Gaussian density (its capacity knee) that a method sized by face area took."""

    density: float
    preset_density: float


@dataclass(frozen=True)
class RunFacts:
    """What a run measured or was given that tables read, beyond metrics and cost."""

    se_fraction: float | None = None  # share of face points Spatial Enhancement selected (0..1)
    budget: GaussianBudget | None = None


@dataclass(frozen=True)
class Record:
    schema_version: str
    method: MethodBlock
    subject: SubjectBlock
    protocol: ProtocolBlock
    metrics: dict[str, MetricEntry]
    cost: Cost
    config: dict[str, Any]
    config_hash: str = field(metadata=_nonempty())
    seed: int
    code: Code
    machine: Machine
    artefacts: dict[str, Artefact]
    created: str = field(metadata={"pattern": r"^\d{4}-\d\d-\d\dT\d\d:\d\d"})
    notes: tuple[str, ...]
    status: Status | None = None
    run: RunFacts | None = None

    @classmethod
    def from_dict(cls, data: Any) -> "Record":
        """The typed record of a decoded JSON object; :class:`ValueError` listing what does not fit."""
        problems: list[str] = []
        rec = decode(cls, data, "record", problems)
        if problems:
            raise ValueError("; ".join(problems))
        return rec

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (absent optional sections left out)."""
        return _encode(self)

    @property
    def failed(self) -> bool:
        """A run recorded as failed (``status.state == "failed"``; no status means ok)."""
        return self.status is not None and self.status.state == "failed"

    def value(self, key: str) -> float | None:
        """The value of metric ``key`` (None when the record has no such metric or it has no value)."""
        m = self.metrics.get(key)
        return None if m is None else m.value


def replace(obj: Any, **changes: Any) -> Any:
    """:func:`dataclasses.replace` that keeps which untouched optional fields the JSON held as ``null``."""
    new = dataclasses.replace(obj, **changes)
    nulls = getattr(obj, _NULLS, frozenset()) - changes.keys()
    if nulls:
        object.__setattr__(new, _NULLS, nulls)
    return new


# ----------------------------------------------------------------------------- decoding
def _type_label(tp: Any) -> str:
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        return "|".join(_type_label(a) for a in get_args(tp))
    if tp is type(None):
        return "null"
    if origin is tuple:
        return "array"
    if origin is dict or dataclasses.is_dataclass(tp):
        return "object"
    return {int: "integer", float: "number", bool: "boolean", str: "string"}.get(tp, "value")


def _fits(value: Any, tp: Any) -> bool:
    """Whether ``value``'s JSON type is ``tp``'s (not looking inside containers)."""
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        return any(_fits(value, a) for a in get_args(tp))
    if tp is Any:
        return True
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:  # JSON has no NaN / inf: a missing number is null
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if tp is str:
        return isinstance(value, str)
    if origin is tuple:
        return isinstance(value, list | tuple)
    if origin is dict or dataclasses.is_dataclass(tp):
        return isinstance(value, dict)
    return True


def _check_metadata(value: Any, meta: Any, where: str, out: list[str]) -> None:
    if "enum" in meta and value not in meta["enum"]:
        out.append(f"{where}: {value!r} is not one of {', '.join(map(str, meta['enum']))}")
    if isinstance(value, str):
        if len(value) < meta.get("min_length", 0):
            out.append(f"{where}: empty string")
        if "pattern" in meta and not re.search(meta["pattern"], value):
            out.append(f"{where}: {value!r:.60} does not match {meta['pattern']}")
    if isinstance(value, (int, float)) and not isinstance(value, bool) and "minimum" in meta and value < meta["minimum"]:
        out.append(f"{where}: {value} < {meta['minimum']}")


def decode(tp: Any, value: Any, where: str, out: list[str]) -> Any:
    """``value`` (decoded JSON) as type ``tp``; each misfit appended to ``out`` as one line naming the field."""
    if not _fits(value, tp):
        out.append(f"{where}: expected {_type_label(tp)}, got {type(value).__name__} {value!r:.60}")
        return None
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        if value is None:
            return None
        return decode(next(a for a in get_args(tp) if a is not type(None) and _fits(value, a)), value, where, out)
    if origin is tuple:
        item = get_args(tp)[0]
        return tuple(decode(item, x, f"{where}[{i}]", out) for i, x in enumerate(value))
    if origin is dict:
        item = get_args(tp)[1]
        if item is Any:
            return dict(value)
        return {k: decode(item, v, f"{where}.{k}", out) for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        hints = get_type_hints(tp)
        kwargs = {}
        for f in dataclasses.fields(tp):
            if f.name not in value:
                if not _optional(f):
                    out.append(f"{where}.{f.name}: missing")
                continue
            v = decode(hints[f.name], value[f.name], f"{where}.{f.name}", out)
            if value[f.name] is not None:
                _check_metadata(value[f.name], f.metadata, f"{where}.{f.name}", out)
            kwargs[f.name] = v
        try:
            obj = tp(**kwargs)
        except TypeError:  # a required field was missing (already reported)
            return None
        nulls = frozenset(f.name for f in dataclasses.fields(tp) if _optional(f) and value.get(f.name, 0) is None)
        if nulls:
            object.__setattr__(obj, _NULLS, nulls)  # written back as null (not a field: equality ignores it)
        return obj
    if tp is float and isinstance(value, int):
        return value  # an integer-valued number stays as it was written
    return value


_NULLS = "_json_nulls"
"""The attribute that lists the optional fields a decoded object's JSON held as ``null``."""


def _optional(f: dataclasses.Field) -> bool:
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def _encode(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {}
        nulls = getattr(obj, _NULLS, frozenset())
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if v is None and _optional(f) and f.name not in nulls:
                continue
            out[f.name] = _encode(v)
        return out
    if isinstance(obj, tuple):
        return [_encode(x) for x in obj]
    if isinstance(obj, dict):
        return {k: _encode(v) for k, v in obj.items()}
    return obj
