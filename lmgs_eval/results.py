"""The results store: one JSON record per (method, subject, protocol, clip, seed, config).

Every number in a table is read from a record, and every record says how it was made
(the lm-evaluation-harness results file; nerfbaselines' results that carry what produced
them). Tables and charts (:mod:`lmgs_eval.tables`, :mod:`lmgs_eval.charts`) are pure
functions of these files; ``lmgs-eval verify`` re-hashes the artefacts they reference.

Schema version ``1`` (``SCHEMA_VERSION``); :data:`SCHEMA` is the machine-checked form used
by :func:`validate`. ``?`` marks an optional field; ``|null`` a field that may be null.

=================  ======================================================================
Field              Meaning
=================  ======================================================================
schema_version     ``"1"``
method             ``name`` (registry name), ``display_name`` (as printed), ``family``
                   (``2D``/``NeRF``/``3DGS``/``external``/``ground-truth``/``control``),
                   ``description`` (what was kept / simplified), ``standins`` [str],
                   ``variant``? (str|null: ablation / sweep variant of a base method,
                   e.g. ``theta0.4``; such rows go to Tables III/IV, not Table I),
                   ``control``? ({kind, targets [metric keys]}: a calibration control and
                   the metrics it is a negative control for)
subject            ``name``, ``bundled`` (bool), ``standin`` (str|null: what it stands in
                   for, e.g. "synthetic head"), ``frames``, ``width``, ``height``
                   (int|null), ``path`` (str|null), ``sha256`` (subject manifest, str|null)
protocol           ``name`` (``self``/``cross``/``stress``/``calibration``/``capacity``),
                   ``version``, ``clip`` (test split, driving clip "A"/"B", or the stress
                   condition), ``split`` (str|null), ``n_frames`` (int|null)
metrics            ``{key: entry}``; keys are canonical (``psnr``, ``ssim``, ``lpips``,
                   ``lmd``, ``lse_d``, ``lse_c``...); entry: ``value`` (float|null),
                   ``n_original``, ``n_effective``, ``higher_is_better``, ``unit``,
                   ``backend`` (what made the number: ``stlpips-alex``, ``lpips-alex``,
                   ``onnxruntime:bundled-sync``...; numbers of different backends never
                   share a column silently), ``backend_version``, ``weights_sha256``
                   (str|null), ``flags`` [str], ``standin`` (str|null), ``per_item``
                   ([float|null] per frame / window, rounded to 6 significant digits, or
                   null), ``values``? (every number the metric reported)
cost               ``train_seconds``, ``fps``, ``ms_per_frame`` {audio, network, raster,
                   total}, ``first_frame_ms``, ``realtime_factor``, ``n_params``,
                   ``n_gaussians``, ``model_mb``, ``peak_mb`` (all number|null),
                   ``device`` (str|null)
config             the method's full configuration (object)
config_hash        short hash of ``config`` (the method's own, or :func:`config_hash`)
seed               int
code               ``version``, ``git_commit`` (str|null), ``dirty`` (bool|null)
machine            ``cpu``, ``threads``, ``torch`` (str|null), ``cuda_device`` (str|null),
                   ``platform``
artefacts          ``{role: {path, sha256}}`` (renders, gt, checkpoint, metric weights);
                   a relative path is relative to the store root
status?            ``{state: "ok"|"failed", reason: str|null}`` (absent means ok)
created            ISO 8601 time of writing
notes              [str]
=================  ======================================================================
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
import platform
import re
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from lmgs_eval.errors import UserError
from lmgs_eval.paths import atomic_dir, atomic_write_text

SCHEMA_VERSION = "1"
FAMILIES = ("2D", "NeRF", "3DGS", "external", "ground-truth", "reference", "control")
PROTOCOLS = ("self", "cross", "stress", "calibration", "capacity")

_STR = {"type": "string"}
_OSTR = {"type": ["string", "null"]}
_ONUM = {"type": ["number", "null"]}
_OINT = {"type": ["integer", "null"]}
_STRS = {"type": "array", "items": _STR}

METRIC_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["value", "n_original", "n_effective", "higher_is_better", "unit", "backend",
                 "backend_version", "weights_sha256", "flags", "standin", "per_item"],
    "properties": {
        "value": _ONUM,
        "n_original": {"type": "integer", "minimum": 0},
        "n_effective": {"type": "integer", "minimum": 0},
        "higher_is_better": {"type": "boolean"},
        "unit": _STR,
        "backend": {"type": "string", "minLength": 1},
        "backend_version": _STR,
        "weights_sha256": _OSTR,
        "flags": _STRS,
        "standin": _OSTR,
        "per_item": {"type": ["array", "null"], "items": _ONUM},
        "values": {"type": "object"},
    },
}

SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["schema_version", "method", "subject", "protocol", "metrics", "cost", "config", "config_hash",
                 "seed", "code", "machine", "artefacts", "created", "notes"],
    "properties": {
        "schema_version": {"type": "string", "enum": [SCHEMA_VERSION]},
        "method": {
            "type": "object",
            "required": ["name", "display_name", "family", "description", "standins"],
            "properties": {
                "name": {"type": "string", "minLength": 1},
                "display_name": _STR,
                "family": {"type": "string", "enum": list(FAMILIES)},
                "description": _STR,
                "standins": _STRS,
                "variant": _OSTR,
                "control": {"type": "object", "required": ["kind"],
                            "properties": {"kind": _STR, "targets": _STRS}},
            },
        },
        "subject": {
            "type": "object",
            "required": ["name", "bundled", "standin", "frames", "width", "height", "path", "sha256"],
            "properties": {
                "name": {"type": "string", "minLength": 1},
                "bundled": {"type": "boolean"},
                "standin": _OSTR,
                "frames": _OINT,
                "width": _OINT,
                "height": _OINT,
                "path": _OSTR,
                "sha256": _OSTR,
            },
        },
        "protocol": {
            "type": "object",
            "required": ["name", "version", "clip", "split", "n_frames"],
            "properties": {
                "name": {"type": "string", "enum": list(PROTOCOLS)},
                "version": _STR,
                "clip": {"type": "string", "minLength": 1},
                "split": _OSTR,
                "n_frames": _OINT,
            },
        },
        "metrics": {"type": "object", "additionalProperties": METRIC_SCHEMA},
        "cost": {
            "type": "object",
            "required": ["train_seconds", "fps", "ms_per_frame", "first_frame_ms", "realtime_factor", "n_params",
                         "n_gaussians", "model_mb", "peak_mb", "device"],
            "properties": {
                "train_seconds": _ONUM,
                "fps": _ONUM,
                "ms_per_frame": {"type": ["object", "null"],
                                 "properties": {k: _ONUM for k in ("audio", "network", "raster", "total")}},
                "first_frame_ms": _ONUM,
                "realtime_factor": _ONUM,
                "n_params": _OINT,
                "n_gaussians": _OINT,
                "model_mb": _ONUM,
                "peak_mb": _ONUM,
                "device": _OSTR,
                "others_cpu_share": _ONUM,
                "host_slowdown": _ONUM,
                "train_others_cpu_share": _ONUM,
                "host_probe_best_ms": _ONUM,
                "host_probe_ms": {"type": ["array", "null"], "items": _ONUM},
            },
        },
        "config": {"type": "object"},
        "config_hash": {"type": "string", "minLength": 1},
        "seed": {"type": "integer"},
        "code": {"type": "object", "required": ["version", "git_commit", "dirty"],
                 "properties": {"version": _STR, "git_commit": _OSTR, "dirty": {"type": ["boolean", "null"]}}},
        "machine": {"type": "object", "required": ["cpu", "threads", "torch", "cuda_device", "platform"],
                    "properties": {"cpu": _STR, "threads": _OINT, "torch": _OSTR, "cuda_device": _OSTR,
                                   "platform": _STR, "cpu_kernels": _OSTR}},
        "artefacts": {"type": "object", "additionalProperties": {
            "type": "object", "required": ["path", "sha256"],
            "properties": {"path": {"type": "string", "minLength": 1},
                           "sha256": {"type": "string", "pattern": "^[0-9a-f]{64}$"}}}},
        "status": {"type": "object", "required": ["state"],
                   "properties": {"state": {"type": "string", "enum": ["ok", "failed"]}, "reason": _OSTR}},
        "created": {"type": "string", "pattern": r"^\d{4}-\d\d-\d\dT\d\d:\d\d"},
        "notes": _STRS,
    },
}

_TYPES: dict[str, tuple[type, ...]] = {
    "string": (str,), "number": (int, float), "integer": (int,), "boolean": (bool,),
    "object": (dict,), "array": (list,), "null": (type(None),),
}


def _is_type(v: Any, t: str) -> bool:
    if t in ("number", "integer") and isinstance(v, bool):
        return False
    if t == "number" and isinstance(v, float) and not math.isfinite(v):
        return False  # JSON has no NaN/inf: a missing number is null
    return isinstance(v, _TYPES[t])


def _check(v: Any, schema: Mapping[str, Any], where: str, out: list[str]) -> None:
    types = schema.get("type")
    if types is not None:
        tl = [types] if isinstance(types, str) else list(types)
        if not any(_is_type(v, t) for t in tl):
            out.append(f"{where}: expected {'|'.join(tl)}, got {type(v).__name__} {v!r:.60}")
            return
    if "enum" in schema and v not in schema["enum"]:
        out.append(f"{where}: {v!r} is not one of {', '.join(map(str, schema['enum']))}")
    if isinstance(v, str):
        if len(v) < schema.get("minLength", 0):
            out.append(f"{where}: empty string")
        if "pattern" in schema and not re.search(schema["pattern"], v):
            out.append(f"{where}: {v!r:.60} does not match {schema['pattern']}")
    if isinstance(v, (int, float)) and not isinstance(v, bool) and "minimum" in schema and v < schema["minimum"]:
        out.append(f"{where}: {v} < {schema['minimum']}")
    if isinstance(v, dict):
        for k in schema.get("required", ()):
            if k not in v:
                out.append(f"{where}.{k}: missing")
        props = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        for k, sub in v.items():
            if k in props:
                _check(sub, props[k], f"{where}.{k}", out)
            elif isinstance(extra, Mapping):
                _check(sub, extra, f"{where}.{k}", out)
    if isinstance(v, list) and "items" in schema:
        for i, item in enumerate(v):
            _check(item, schema["items"], f"{where}[{i}]", out)


def validate(record: Any) -> list[str]:
    """Check a record against :data:`SCHEMA` (and a few cross-field rules).

    Args:
        record: a decoded JSON object.

    Returns:
        Problems, one line each naming the field (``record.metrics.psnr.value: ...``);
        empty when the record is valid.
    """
    out: list[str] = []
    _check(record, SCHEMA, "record", out)
    if out or not isinstance(record, dict):
        return out
    for key, m in record["metrics"].items():
        if m["n_effective"] > m["n_original"]:
            out.append(f"record.metrics.{key}: n_effective {m['n_effective']} > n_original {m['n_original']}")
    status = record.get("status") or {}
    if status.get("state") == "failed" and not status.get("reason"):
        out.append("record.status.reason: a failed run must say why")
    return out


# ----------------------------------------------------------------------------- helpers
def config_hash(config: Mapping[str, Any]) -> str:
    """16 hex digits of the sha256 of ``config`` as canonical JSON (sorted keys)."""
    blob = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def sha256_file(path: str | os.PathLike) -> str:
    """sha256 (hex) of a file's bytes, read in 1 MB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def compact(values: Iterable[float | None] | None, digits: int = 6) -> list[float | None] | None:
    """Per-item values for a record: floats rounded to ``digits`` significant digits, NaN -> null."""
    if values is None:
        return None
    out: list[float | None] = []
    for v in values:
        f = None if v is None else float(v)
        out.append(float(f"{f:.{digits}g}") if f is not None and math.isfinite(f) else None)
    return out


def git_info() -> dict[str, Any]:
    """``{version, git_commit, dirty}`` of the code that made a record (commit None outside git)."""
    from lmgs_eval import __version__

    here = Path(__file__).resolve().parent
    commit: str | None = None
    dirty: bool | None = None
    try:
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        if r.returncode == 0:
            commit = r.stdout.strip() or None
            s = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10)
            dirty = bool(s.stdout.strip()) if s.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"version": __version__, "git_commit": commit, "dirty": dirty}


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine_info() -> dict[str, Any]:
    """Hardware fingerprint: CPU model, threads, torch version, CUDA device (if torch is loaded), platform,
    and the instruction set torch's CPU kernels use (``cpu_kernels``: "AVX512", "AVX2", ...; training
    and ONNX Runtime scoring round differently on different ones, so the same seed and data give
    slightly different numbers on a CPU with AVX-512 and one without).

    torch is not imported here (it is slow); its version comes from the package metadata and
    the CUDA device is only read when the caller has already imported torch.
    """
    from importlib import metadata

    try:
        torch_version: str | None = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch_version = None
    threads = os.cpu_count()
    cuda = kernels = None
    torch = sys.modules.get("torch")
    if torch is not None:
        threads = int(torch.get_num_threads())
        if torch.cuda.is_available():
            cuda = str(torch.cuda.get_device_name(0))
        try:
            kernels = str(torch.backends.cpu.get_cpu_capability())
        except AttributeError:  # torch < 2.1
            kernels = None
    return {"cpu": _cpu_name(), "threads": threads, "torch": torch_version, "cuda_device": cuda,
            "platform": platform.platform(), "cpu_kernels": kernels}


def now_iso(timespec: str = "seconds") -> str:
    """Current UTC time, ISO 8601, to the second (or ``timespec``, e.g. ``"microseconds"``)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec=timespec)


EMPTY_COST: dict[str, Any] = {
    "train_seconds": None, "fps": None, "ms_per_frame": None, "first_frame_ms": None, "realtime_factor": None,
    "n_params": None, "n_gaussians": None, "model_mb": None, "peak_mb": None, "device": None,
}


def make_record(*, method: Mapping, subject: Mapping, protocol: Mapping, metrics: Mapping, seed: int,
                config: Mapping | None = None, config_hash_: str | None = None, cost: Mapping | None = None,
                artefacts: Mapping | None = None, notes: Iterable[str] = (), status: Mapping | None = None,
                code: Mapping | None = None, machine: Mapping | None = None) -> dict[str, Any]:
    """Assemble a record, filling ``schema_version``, ``code``, ``machine``, ``created`` and defaults.

    Args:
        method, subject, protocol, metrics: the sections of the schema (see module docstring).
        seed: the run's seed.
        config: the method's full config (default ``{}``).
        config_hash_: the method's own config hash; default :func:`config_hash` of ``config``.
        cost: cost figures; missing keys are null.
        artefacts: ``{role: {path, sha256}}``.
        notes, status, code, machine: as in the schema; ``code``/``machine`` default to
            :func:`git_info` / :func:`machine_info`.

    Returns:
        The record (not yet validated; :func:`write_record` validates).
    """
    config = dict(config or {})
    rec: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "method": dict(method),
        "subject": dict(subject),
        "protocol": dict(protocol),
        "metrics": {k: dict(v) for k, v in metrics.items()},
        "cost": {**EMPTY_COST, **dict(cost or {})},
        "config": config,
        "config_hash": config_hash_ or config_hash(config),
        "seed": int(seed),
        "code": dict(code) if code is not None else git_info(),
        "machine": dict(machine) if machine is not None else machine_info(),
        "artefacts": {k: dict(v) for k, v in (artefacts or {}).items()},
        "created": now_iso(),
        "notes": list(notes),
    }
    if status is not None:
        rec["status"] = dict(status)
    return rec


_CANONICAL = {"psnr": "psnr", "ssim": "ssim", "lpips-alex": "lpips", "stlpips-alex": "lpips", "lmd": "lmd"}


def metric_entries(result: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Schema entries from a metric result dict (:meth:`MetricResult.to_dict` of :mod:`lmgs_eval.metrics`).

    ``lpips-alex`` and ``stlpips-alex`` both go under key ``lpips`` with their own name as
    ``backend`` (so a column mixing them is flagged); ``lse`` becomes ``lse_d`` and ``lse_c``
    (``per_item`` on ``lse_d`` only: the per-window distances at the chosen offset).

    Returns:
        ``{key: entry}``; an unavailable metric gives an entry with ``value`` null and
        its reason in ``flags``.
    """
    spec = result["spec"]
    name = spec["name"]
    flags = list(result.get("flags", []))
    if not result.get("available", True):
        flags.append(f"unavailable: {result.get('reason', '')}")
    base = {
        "n_original": int(result["n_original"]), "n_effective": int(result["n_effective"]),
        "unit": spec.get("unit", ""), "backend_version": str(spec.get("version", "")),
        "weights_sha256": spec.get("weights_sha256"), "flags": flags, "standin": spec.get("standin") or None,
    }
    values = result.get("values", {})
    if name == "lse":
        return {
            "lse_d": {**base, "value": values.get("lse_d"), "higher_is_better": False, "backend": spec["backend"],
                      "per_item": compact(result.get("per_item")), "values": dict(values)},
            "lse_c": {**base, "value": values.get("lse_c"), "higher_is_better": True, "backend": spec["backend"],
                      "per_item": None},
            # |AV offset| in frames: LSE-D/C take the best of +-15 offsets by definition, so a
            # shifted audio track is seen here, not in them.
            "av_offset": {**base, "value": None if values.get("offset") is None else abs(int(values["offset"])),
                          "unit": "frames", "higher_is_better": False, "backend": spec["backend"], "per_item": None},
        }
    key = _CANONICAL.get(name, name)
    backend = name if key == "lpips" else spec["backend"]
    return {key: {**base, "value": result.get("value"), "higher_is_better": bool(spec["higher_is_better"]),
                  "backend": backend, "per_item": compact(result.get("per_item")), "values": dict(values)}}


# ----------------------------------------------------------------------------- the store
def _slug(s: str) -> str:
    slug = re.sub(r"[^A-Za-z0-9._+-]+", "_", s).strip("._") or "x"
    if slug != s:  # keep distinct names distinct after cleaning ("a:b" vs "a_b")
        slug += "-" + hashlib.sha256(s.encode()).hexdigest()[:6]
    return slug


def record_path(root: str | os.PathLike, record: Mapping[str, Any]) -> Path:
    """Stable file of a record: ``root/<subject>/<protocol>/<method>--<clip>--seed<N>--<config_hash>.json``."""
    name = (f"{_slug(record['method']['name'])}--{_slug(record['protocol']['clip'])}--seed{int(record['seed'])}"
            f"--{_slug(record['config_hash'])}.json")
    return Path(root) / _slug(record["subject"]["name"]) / _slug(record["protocol"]["name"]) / name


def write_record(root: str | os.PathLike, record: Mapping[str, Any]) -> Path:
    """Validate and write a record atomically (temp file + rename); returns its path.

    A record that does not validate writes nothing and raises :class:`UserError`. Two
    writers at once never leave a partial file: each writes its own temporary file and
    the rename is atomic (the last one wins for the same record).
    """
    problems = validate(record)
    if problems:
        who = (f"{record.get('method', {}).get('name', '?')}/{record.get('subject', {}).get('name', '?')}"
               if isinstance(record, Mapping) else "?")
        raise UserError(f"result record {who} is invalid: {'; '.join(problems[:5])}"
                        + (f" (+{len(problems) - 5} more)" if len(problems) > 5 else ""))
    text = json.dumps(record, indent=1, sort_keys=True, allow_nan=False, ensure_ascii=False) + "\n"
    path = record_path(root, record)
    atomic_write_text(path, text)
    return path


def iter_store(root: str | os.PathLike) -> tuple[list[tuple[Path, dict[str, Any]]], list[str]]:
    """Every valid record of a store with its file, and a warning per skipped file.

    Files are read in sorted order; hidden files and folders (temporary files of writers in
    progress) are ignored. A file that is not JSON, not a record of this schema (foreign),
    of another schema version or invalid is skipped with a warning naming it.
    """
    root = Path(root)
    if not root.exists():
        return [], []
    if not root.is_dir():
        raise UserError(f"{root}: results store is not a folder")
    out: list[tuple[Path, dict[str, Any]]] = []
    warnings: list[str] = []
    for path in sorted(root.rglob("*.json")):
        if any(part.startswith(".") for part in path.relative_to(root).parts):
            continue
        try:
            rec = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            warnings.append(f"{path}: skipped, not readable JSON ({exc})")
            continue
        if not isinstance(rec, dict) or "schema_version" not in rec:
            warnings.append(f"{path}: skipped, not a result record (no schema_version)")
            continue
        if rec["schema_version"] != SCHEMA_VERSION:
            warnings.append(f"{path}: skipped, schema_version {rec['schema_version']!r} (this code reads {SCHEMA_VERSION!r})")
            continue
        problems = validate(rec)
        if problems:
            warnings.append(f"{path}: skipped, invalid record: {'; '.join(problems[:3])}")
            continue
        out.append((path, rec))
    return out, warnings


def load_records(root: str | os.PathLike) -> tuple[list[dict[str, Any]], list[str]]:
    """All valid records under ``root`` and a warning (naming the file) per skipped file."""
    items, warnings = iter_store(root)
    return [r for _, r in items], warnings


def copy_records(src: str | os.PathLike, dst: str | os.PathLike) -> tuple[int, list[str]]:
    """Copy into store ``dst`` every valid record of store ``src`` that ``dst`` does not hold.

    Only the JSON records travel: renders and checkpoints stay where they were made, while
    tables, charts and resume (:func:`find_record`) work from the record alone. The copies
    are listed in ``dst``'s :data:`IMPORTED_FILE`, so ``lmgs-eval verify`` does not call
    their absent renders and checkpoints missing. A record already in ``dst`` (same subject,
    protocol, method, clip, seed and config hash) is kept as it is. Returns the number
    copied and a warning per skipped file of ``src``.
    """
    items, warnings = iter_store(src)
    copied = []
    for _, rec in items:
        if not record_path(dst, rec).is_file():
            copied.append(write_record(dst, rec).relative_to(dst).as_posix())
    if copied:
        atomic_write_text(Path(dst) / IMPORTED_FILE, json.dumps(
            {"records": sorted(imported_records(dst) | set(copied))}, indent=1) + "\n")
    return len(copied), warnings


IMPORTED_FILE = ".imported.json"
"""Ledger of a store's records copied from elsewhere by :func:`copy_records` (hidden: not a record)."""
MADE_ELSEWHERE = ("render", "checkpoint")
"""Artefact roles that stay on the machine that made a record (ground truth and weights travel)."""


def imported_records(root: str | os.PathLike) -> set[str]:
    """Paths (relative to the store) of the records :func:`copy_records` brought into ``root``."""
    try:
        return set(json.loads((Path(root) / IMPORTED_FILE).read_text(encoding="utf-8"))["records"])
    except (OSError, ValueError, KeyError, TypeError):
        return set()


def snapshot_records(records: Iterable[Mapping[str, Any]], dst: str | os.PathLike) -> Path:
    """Write exactly ``records`` as a store at ``dst``, replacing what was there, atomically.

    This is how the committed ``tables/records/`` is made: the records a set of tables was
    generated from, so ``lmgs-eval table --results tables/records`` makes the same tables
    again on any machine and ``make bench`` can resume from them.
    """
    with atomic_dir(Path(dst)) as tmp:
        for rec in records:
            write_record(tmp, rec)
    return Path(dst)


# The self protocol notes how many face points Spatial Enhancement selected (lmgs and its variants).
# A record's note when its method was sized by the subject's own knee density (protocols.budget_notes).
BUDGET_NOTE = "Gaussian budget: "
SE_NOTE = "spatial enhancement selected {pct:.1f}% of face points on average"
_SE_NOTE_RE = re.compile(re.escape(SE_NOTE).replace(re.escape("{pct:.1f}"), "([0-9.]+)"))


def se_fraction(rec: Mapping[str, Any]) -> float | None:
    """The share of face points Spatial Enhancement selected in this run (0..1), from its note; None if absent."""
    for note in rec.get("notes") or ():
        m = _SE_NOTE_RE.match(note)
        if m:
            return float(m.group(1)) / 100.0
    return None


def is_failed(rec: Mapping[str, Any]) -> bool:
    """True for a run recorded as failed (``status.state == "failed"``; no status means ok)."""
    return (rec.get("status") or {}).get("state") == "failed"


def find_finished(root: str | os.PathLike, method: str, subject: str, protocol: str, clip: str, seed: int,
                  config_hash: str, subject_sha: str | None = None) -> dict[str, Any] | None:
    """:func:`find_record`, but a failed run counts as not done: it is retried (the failure may have been fixed)."""
    rec = find_record(root, method, subject, protocol, clip, seed, config_hash, subject_sha)
    return None if rec is None or is_failed(rec) else rec


def find_record(root: str | os.PathLike, method: str, subject: str, protocol: str, clip: str, seed: int,
                config_hash: str, subject_sha: str | None = None) -> dict[str, Any] | None:
    """The stored record for this run, or None (so an interrupted run can resume).

    Only a valid record whose fields match is returned; a failed run (``status.state ==
    "failed"``) is returned too, and the caller decides whether to retry it. With
    ``subject_sha`` (the subject's manifest hash), a record made on other data of a subject of
    the same name (re-generated, re-processed) is a :class:`UserError`: it is neither reused
    as if it were of this data nor overwritten.
    """
    key = {"method": {"name": method}, "subject": {"name": subject}, "protocol": {"name": protocol, "clip": clip},
           "seed": seed, "config_hash": config_hash}
    path = record_path(root, key)
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if validate(rec):
        return None
    same = (rec["method"]["name"] == method and rec["subject"]["name"] == subject and rec["protocol"]["name"] == protocol
            and rec["protocol"]["clip"] == clip and rec["seed"] == seed and rec["config_hash"] == config_hash)
    if not same:
        return None
    made_on = rec["subject"].get("sha256")
    if subject_sha and made_on and made_on != subject_sha:
        raise UserError(f"{path}: made on other data of subject '{subject}' (manifest sha256 {made_on[:12]}, now "
                        f"{subject_sha[:12]}); move the old records out of the store, or use another --results")
    return rec


def resolve_artefact(root: str | os.PathLike, path: str) -> Path:
    """An artefact's file: absolute paths as is, relative ones under the store root."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else Path(root) / p


def check_artefacts(root: str | os.PathLike, record: Mapping[str, Any], imported: bool = False) -> tuple[list[str], int]:
    """Re-hash a record's artefacts: one line per artefact that changed or went missing, and how many were checked.

    ``imported``: the record was copied from another machine (:func:`copy_records`), so its
    render and checkpoint being absent here is expected, not a problem, and they are not
    counted as checked; present ones, and every other artefact (ground truth, metric
    weights), are checked as usual.
    """
    out = []
    checked = 0
    for role, a in sorted(record.get("artefacts", {}).items()):
        p = resolve_artefact(root, a["path"])
        if imported and role in MADE_ELSEWHERE and not p.is_file():
            continue
        checked += 1
        if not p.is_file():
            p = package_file(p) or p
        if not p.is_file():
            out.append(f"{role} {p}: missing")
            continue
        now = sha256_file(p)
        if now != a["sha256"]:
            out.append(f"{role} {p}: changed (recorded sha256 {a['sha256'][:12]}, now {now[:12]})")
    return out, checked


def package_file(path: Path) -> Path | None:
    """The file of this ``lmgs_eval`` checkout at the place ``path`` had in the checkout it was
    recorded from (the bundled metric weights: a record made in another clone or worktree names
    that one's absolute path); None when ``path`` is not inside an ``lmgs_eval`` folder or this
    checkout lacks the file. The caller still compares the sha256, so a different file is caught.
    """
    parts = Path(path).parts
    if "lmgs_eval" not in parts:
        return None
    i = len(parts) - 1 - parts[::-1].index("lmgs_eval")
    here = Path(__file__).resolve().parent.joinpath(*parts[i + 1:])
    return here if here.is_file() else None
