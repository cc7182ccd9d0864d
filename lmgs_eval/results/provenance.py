"""What made a number: the code's commit, the machine, the config hash, file hashes, the time."""

from __future__ import annotations

import datetime
import math
import os
import platform
import sys
from collections.abc import Iterable, Mapping
from importlib import metadata
from typing import Any

from lmgs.config import config_hash
from lmgs_eval import __version__
from lmgs_eval.paths import git_state
from lmgs_eval.results.schema import SCHEMA_VERSION


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
    commit, dirty = git_state()
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
                code: Mapping | None = None, machine: Mapping | None = None,
                run: Mapping | None = None) -> dict[str, Any]:
    """Assemble a record, filling ``schema_version``, ``code``, ``machine``, ``created`` and defaults.

    Args:
        method, subject, protocol, metrics: the sections of the schema (see module docstring).
        seed: the run's seed.
        config: the method's full config (default ``{}``).
        config_hash_: the method's own config hash; default :func:`config_hash` of ``config``.
        cost: cost figures; missing keys are null.
        artefacts: ``{role: {path, sha256}}``.
        run: the run's structured facts (``se_fraction``, ``budget``), or None.
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
    if run:
        rec["run"] = dict(run)
    return rec


_CANONICAL = {"psnr": "psnr", "ssim": "ssim", "lpips-alex": "lpips", "stlpips-alex": "lpips",
              "lpips-alex-custom": "lpips_custom", "lmd": "lmd"}
LPIPS_KEYS = ("lpips", "lpips_custom")
"""Record keys of the LPIPS family; their ``backend`` is the network's name."""


def metric_entries(result: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Schema entries from a metric result dict (:meth:`MetricResult.to_dict` of :mod:`lmgs_eval.metrics`).

    ``lpips-alex`` and ``stlpips-alex`` both go under key ``lpips`` with their own name as
    ``backend`` (so a column mixing them is flagged). ``lpips-alex-custom`` (an AlexNet-shaped
    trunk that is not torchvision's published one) goes under its own key ``lpips_custom``, never
    into ``lpips``, with backend ``lpips-alex-custom(<first 8 hex digits of the trunk's sha256>)``
    so that numbers of two different trunks are flagged too. ``lse`` becomes ``lse_d`` and
    ``lse_c`` (``per_item`` on ``lse_d`` only: the per-window distances at the chosen offset).
    A metric whose weights are several files also records each file's path and sha256
    (``weights_files``, by role) beside ``weights_sha256``, the hash over them.

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
    if spec.get("weights_files"):
        base["weights_files"] = {role: dict(f) for role, f in spec["weights_files"].items()}
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
    backend = name if key in LPIPS_KEYS else spec["backend"]
    if key == "lpips_custom":
        backend += f"({((spec.get('weights_files') or {}).get('alexnet') or {}).get('sha256', '')[:8]})"
    return {key: {**base, "value": result.get("value"), "higher_is_better": bool(spec["higher_is_better"]),
                  "backend": backend, "per_item": compact(result.get("per_item")), "values": dict(values)}}
