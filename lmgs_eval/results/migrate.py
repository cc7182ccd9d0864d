"""Records of an older schema read as the current one.

Version 1 kept two facts in prose notes (the share of points Spatial Enhancement selected, and a
subject's own Gaussian budget) and had no ``method.components``: tables read the parts of the
reference model (SE, LC, GR and their settings) out of its config. :func:`migrate` derives both
from the record itself (the parts from its config, rebuilt as a checkpoint's is and read by the
same function the lmgs adapter declares them with), so every record the store hands out has the
current form. A migrated record is not rewritten on disk until it is
written again (``snapshot_records``, ``copy_records``).
"""

from __future__ import annotations

import copy
import re
from typing import Any

from lmgs.presets import components, config_from_dict
from lmgs_eval.results.notes import BUDGET_NOTE, SE_NOTE
from lmgs_eval.results.schema import SCHEMA_VERSION

_SE_RE = re.compile(re.escape(SE_NOTE).replace(re.escape("{pct:.1f}"), "([0-9.]+)"))
_BUDGET_RE = re.compile(re.escape(BUDGET_NOTE) + r"([0-9.e+-]+) per pixel of face area.*not the quick preset's ([0-9.e+-]+);")


def lmgs_components(config: dict[str, Any]) -> dict[str, Any] | None:
    """The reference model's parts as a version-1 record's config states them, as the lmgs adapter declares
    them for that config (:func:`lmgs.presets.components`); None for a config that is not lmgs's."""
    g = config.get("guidance")
    if not isinstance(g, dict) or "theta" not in g:
        return None
    return components(config_from_dict(config))


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
