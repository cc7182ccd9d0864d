"""Records of an older schema read as the current one.

Version 1 kept two facts in prose notes (the share of points Spatial Enhancement selected, and a
subject's own Gaussian budget) and had no ``method.components``: tables read the parts of the
reference model (SE, LC, GR and their settings) out of its config. :func:`migrate` derives both
from the record itself, the one place that knows version 1's config layout, so every record the
store hands out has the current form. A migrated record is not rewritten on disk until it is
written again (``snapshot_records``, ``copy_records``).
"""

from __future__ import annotations

import copy
import re
from typing import Any

from lmgs_eval.results.notes import BUDGET_NOTE, SE_NOTE
from lmgs_eval.results.schema import SCHEMA_VERSION

_SE_RE = re.compile(re.escape(SE_NOTE).replace(re.escape("{pct:.1f}"), "([0-9.]+)"))
_BUDGET_RE = re.compile(re.escape(BUDGET_NOTE) + r"([0-9.e+-]+) per pixel of face area.*not the quick preset's ([0-9.e+-]+);")


def lmgs_components(config: dict[str, Any]) -> dict[str, Any] | None:
    """The reference model's parts as a version-1 record's config states them (None for other configs)."""
    g = config.get("guidance")
    if not isinstance(g, dict) or "theta" not in g:
        return None
    train, audio = config.get("train") or {}, config.get("audio") or {}
    se, lc, mouth = bool(g.get("se", True)), bool(g.get("lc", True)), bool(g.get("mouth_state", False))
    return {
        "se": se, "lc": lc, "gr": bool(config.get("gr", True)), "theta": float(g["theta"]),
        # the config leaves out what a switched-off part would use (its hash stays that of before)
        "se_cap": float(g.get("select_fraction", 0.0)) if se else 0.0,
        "landmark_folds": int(train.get("landmark_folds", 0)) if (se or lc or mouth) else 0,
        "gr_reduce": str(train.get("normal_reduce", "sum")), "gr_weight": float(train.get("lambda_normal", 1e-4)),
        "audio_frontend": audio.get("frontend"), "audio_encoder": bool(audio.get("use_encoder", True)),
        **({"mouth_state": True} if mouth else {}),  # as baselines.lmgs_method.components declares it
    }


def _is_lmgs(name: str) -> bool:
    return name == "lmgs" or name.startswith("lmgs-")


def migrate(record: dict[str, Any]) -> dict[str, Any]:
    """The record in the current schema (a copy when it changes; the record itself when it is current)."""
    if not isinstance(record, dict) or record.get("schema_version") != "1":
        return record
    rec = copy.deepcopy(record)
    rec["schema_version"] = SCHEMA_VERSION
    method = rec.get("method") or {}
    if _is_lmgs(str(method.get("name", ""))) and isinstance(rec.get("config"), dict):
        comps = lmgs_components(rec["config"])
        if comps is not None:
            method["components"] = comps
    run: dict[str, Any] = {}
    for note in rec.get("notes") or ():
        if not isinstance(note, str):
            continue
        m = _SE_RE.match(note)
        if m:
            run["se_fraction"] = float(m.group(1)) / 100.0
        m = _BUDGET_RE.match(note)
        if m:
            run["budget"] = {"density": float(m.group(1)), "preset_density": float(m.group(2))}
    if run:
        rec["run"] = run
    return rec
