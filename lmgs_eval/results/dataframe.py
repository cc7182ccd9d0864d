"""A results store as a pandas DataFrame: one row per record and metric.

>>> df = frame("tables/records")
>>> psnr = df[(df.protocol == "self") & (df.metric == "psnr") & df.variant.isna()]
>>> psnr.pivot_table("value", index="method", columns="subject")   # the mean over seeds, as Table I

Each row carries the record's identity, the metric's value and how it was made, the run's cost and
its provenance (:data:`COLUMNS`). A record without metrics (a failed run) has no row. pandas is
imported when a frame is made, so the command line never pays for it.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable
from typing import Any

from lmgs_eval.results.store import iter_store
from lmgs_eval.results.types import Record

IDENTITY = ("subject", "protocol", "clip", "method", "display_name", "family", "variant", "seed", "split",
            "config_hash", "status")
"""Which run: ``clip`` is the test split, the driving clip (cross) or the stress condition; ``status`` ok / failed."""
METRIC = ("metric", "value", "unit", "higher_is_better", "ci_low", "ci_high", "n_original", "n_effective", "backend",
          "backend_version", "weights_sha256", "standin", "metric_standin", "subject_standin")
"""The number and what made it. ``ci_low`` / ``ci_high``: where the metric's ``values`` record an interval
(the tables' intervals are bootstraps over ``per_item``, :mod:`lmgs_eval.report.stats`); ``standin``: the
scorer, the subject or a part of the method stands in for the paper's (which: ``metric_standin``,
``subject_standin``, the record's ``method.standins``)."""
COST = ("fps", "ms_per_frame", "train_seconds", "device", "model_mb", "n_gaussians", "n_params", "peak_mb")
"""The run's cost where recorded (``ms_per_frame``: its total)."""
PROVENANCE = ("code_version", "commit", "dirty", "created", "cpu", "threads", "cpu_kernels", "torch", "cuda_device",
              "platform", "path")
"""What made the record, and its file (None for records not read from a store)."""
COLUMNS = IDENTITY + METRIC + COST + PROVENANCE
_NUMERIC = ("value", "ci_low", "ci_high", "fps", "ms_per_frame", "train_seconds", "model_mb", "n_gaussians",
            "n_params", "peak_mb")


def _rows(rec: Record, path: str | None) -> Iterable[dict[str, Any]]:
    m, s, p, c, mc = rec.method, rec.subject, rec.protocol, rec.cost, rec.machine
    common = {
        "subject": s.name, "protocol": p.name, "clip": p.clip, "method": m.name, "display_name": m.display_name,
        "family": m.family, "variant": m.variant, "seed": rec.seed, "split": p.split, "config_hash": rec.config_hash,
        "status": "failed" if rec.failed else "ok",
        "fps": c.fps, "ms_per_frame": c.ms_per_frame.total if c.ms_per_frame else None, "train_seconds": c.train_seconds,
        "device": c.device, "model_mb": c.model_mb, "n_gaussians": c.n_gaussians, "n_params": c.n_params,
        "peak_mb": c.peak_mb,
        "code_version": rec.code.version, "commit": rec.code.git_commit, "dirty": rec.code.dirty, "created": rec.created,
        "cpu": mc.cpu, "threads": mc.threads, "cpu_kernels": mc.cpu_kernels, "torch": mc.torch,
        "cuda_device": mc.cuda_device, "platform": mc.platform, "path": path,
    }
    for key, e in rec.metrics.items():
        values = e.values or {}
        yield {**common, "metric": key, "value": e.value, "unit": e.unit, "higher_is_better": e.higher_is_better,
               "ci_low": values.get("ci_low"), "ci_high": values.get("ci_high"), "n_original": e.n_original,
               "n_effective": e.n_effective, "backend": e.backend, "backend_version": e.backend_version,
               "weights_sha256": e.weights_sha256, "standin": bool(e.standin or s.standin or m.standins),
               "metric_standin": e.standin, "subject_standin": s.standin}


def frame(source: str | os.PathLike | Iterable[Record]):
    """Every record of a results store (a folder) or of a list of records as a ``pandas.DataFrame``.

    One row per record and metric, with the columns of :data:`COLUMNS` in that order; numbers are
    floats (NaN where not recorded), ``seed`` an integer. A file of the store that is not a valid
    record is left out with a :class:`UserWarning` naming it (as ``lmgs-eval table`` warns).
    """
    import pandas as pd

    if isinstance(source, (str, os.PathLike)):
        items, skipped = iter_store(source)
        for w in skipped:
            warnings.warn(w, stacklevel=2)
        pairs = [(rec, os.fspath(path)) for path, rec in items]
    else:
        pairs = [(rec, None) for rec in source]
    df = pd.DataFrame([row for rec, path in pairs for row in _rows(rec, path)], columns=list(COLUMNS))
    for col in _NUMERIC:
        df[col] = pd.to_numeric(df[col]).astype("float64")
    df["seed"] = df["seed"].astype("int64")
    return df
