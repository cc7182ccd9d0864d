"""The record and its parts as typed values: frozen dataclasses that are the schema, each checking itself when made.

Every block here (a :class:`Record` and each of its parts) checks its own fields when it is made:
each field's type, the constraints in its metadata (one of a set of values, a pattern, a minimum)
and the rules that tie its fields together (a metric's ``n_effective`` is at most its
``n_original``, a failed run says why). A block in hand is therefore a valid one, whether it was
read from JSON (:meth:`Record.from_dict`), built by the runner or changed with :func:`replace`: it
is checked once, when it is made, and nowhere after. A block that does not fit is
:class:`Invalid`, naming each field (``value: expected number|null, got str 'high'``); read from
JSON, each line names the field from the record down (``record.metrics.psnr.value: ...``). A field
with a default may be absent from the JSON; ``X | None`` may be null.

The sections (see the field table in :mod:`lmgs_eval.results`): :class:`MethodBlock` (with the
method's declared ``components``), :class:`SubjectBlock`, :class:`ProtocolBlock`,
:class:`MetricEntry` per metric key, :class:`Cost`, :class:`Code`, :class:`Machine`,
:class:`Artefact` per role, :class:`Status`, and :class:`RunFacts`: what a run measured or was
given that the tables read (the share of points Spatial Enhancement selected, the Gaussian
budget a subject imposed), as fields rather than prose.

The machinery (checking, reading from JSON, writing back) is :mod:`lmgs_eval.results.blocks`.
A record read from JSON writes back the same JSON (:func:`~lmgs_eval.results.blocks.json_object`): an optional field the JSON
held as ``null`` is written as ``null`` again, one it left out stays out (:func:`replace` keeps that
for the fields it does not change).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from lmgs_eval.results.blocks import Block, Invalid, decode, json_object, replace

__all__ = ["FAMILIES", "PROTOCOLS", "READ_VERSIONS", "SCHEMA_VERSION", "Invalid", "Record", "decode_record",
           "json_object", "replace"]

FAMILIES = ("2D", "NeRF", "3DGS", "external", "ground-truth", "reference", "control")
PROTOCOLS = ("self", "cross", "stress", "calibration", "capacity")
SHA256 = "^[0-9a-f]{64}$"

SCHEMA_VERSION = "2"
"""Written by this code. Version 2 added ``method.components`` and ``run`` (structured facts that
version 1 kept in prose notes or left to be read out of a method's config)."""
READ_VERSIONS = ("1", SCHEMA_VERSION)
"""Read by this code; older records are migrated on read (:mod:`lmgs_eval.results.migrate`)."""


def _enum(*values: str) -> Any:
    return {"enum": values}


def _nonempty() -> dict:
    return {"min_length": 1}


@dataclass(frozen=True)
class Control(Block):
    kind: str
    targets: tuple[str, ...] = ()
    frames: int | None = None  # audio-shift controls: by how many frames


@dataclass(frozen=True)
class MethodBlock(Block):
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
class SubjectBlock(Block):
    name: str = field(metadata=_nonempty())
    bundled: bool
    standin: str | None
    frames: int | None
    width: int | None
    height: int | None
    path: str | None
    sha256: str | None


@dataclass(frozen=True)
class ProtocolBlock(Block):
    name: str = field(metadata=_enum(*PROTOCOLS))
    version: str
    clip: str = field(metadata=_nonempty())
    split: str | None
    n_frames: int | None


@dataclass(frozen=True)
class MetricEntry(Block):
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

    @classmethod
    def _tied(cls, values: Mapping[str, Any]) -> list[tuple[str, str]]:
        ne, no = values.get("n_effective"), values.get("n_original")
        if type(ne) is int and type(no) is int and ne > no:
            return [("", f"n_effective {ne} > n_original {no}")]
        return []


@dataclass(frozen=True)
class MsPerFrame(Block):
    audio: float | None = None
    network: float | None = None
    raster: float | None = None
    total: float | None = None


@dataclass(frozen=True)
class Cost(Block):
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
class Code(Block):
    version: str
    git_commit: str | None
    dirty: bool | None


@dataclass(frozen=True)
class Machine(Block):
    cpu: str
    threads: int | None
    torch: str | None
    cuda_device: str | None
    platform: str
    cpu_kernels: str | None = None


@dataclass(frozen=True)
class Artefact(Block):
    path: str = field(metadata=_nonempty())
    sha256: str = field(metadata={"pattern": SHA256})


@dataclass(frozen=True)
class Status(Block):
    state: str = field(metadata=_enum("ok", "failed"))
    reason: str | None = None

    @classmethod
    def _tied(cls, values: Mapping[str, Any]) -> list[tuple[str, str]]:
        return [(".reason", "a failed run must say why")] if values.get("state") == "failed" and not values.get("reason") else []


@dataclass(frozen=True)
class GaussianBudget(Block):
    """A subject's own Gaussian density (its capacity knee) that a method sized by face area took."""

    density: float
    preset_density: float


@dataclass(frozen=True)
class RunFacts(Block):
    """What a run measured or was given that tables read, beyond metrics and cost."""

    se_fraction: float | None = None  # share of face points Spatial Enhancement selected (0..1)
    budget: GaussianBudget | None = None


@dataclass(frozen=True)
class Record(Block):
    schema_version: str = field(metadata=_enum(*READ_VERSIONS))
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
        rec, problems = decode_record(data)
        if problems:
            raise ValueError("; ".join(problems))
        return rec

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (absent optional sections left out)."""
        return json.loads(json.dumps(self, default=json_object))

    @property
    def key(self) -> tuple[str, str, str, str, int, str]:
        """What the store tells it by: ``(subject, protocol, method, clip, seed, config_hash)``."""
        return (self.subject.name, self.protocol.name, self.method.name, self.protocol.clip, self.seed, self.config_hash)

    @property
    def failed(self) -> bool:
        """A run recorded as failed (``status.state == "failed"``; no status means ok)."""
        return self.status is not None and self.status.state == "failed"

    def value(self, key: str) -> float | None:
        """The value of metric ``key`` (None when the record has no such metric or it has no value)."""
        m = self.metrics.get(key)
        return None if m is None else m.value


def decode_record(data: Any) -> tuple[Record | None, list[str]]:
    """A decoded JSON object as a typed :class:`Record` (None when it does not fit) and what does not
    fit, one line a field (``record.metrics.psnr.value: ...``); no lines when it fits."""
    if not isinstance(data, dict):
        return None, [f"record: expected object, got {type(data).__name__} {data!r:.60}"]
    out: list[str] = []
    rec = decode(Record, data, "record", out)
    return (None if out else rec), out


