"""A benchmark plan as data: a TOML file read into frozen dataclasses, checked key by key.

A plan is a list of stages; each stage crosses protocols, subjects, methods and seeds::

    name = "paper"
    preset = "quick"        # default of every stage
    retries = 1             # a failed run is tried this many more times, then recorded as failed
    cpus = 2                # CPU threads of one run (and Ray's CPU request for it)

    [[stage]]
    protocols = ["self", "cross"]
    subjects = ["astronaut", "hopper"]
    methods = ["lmgs", "talkinggaussian"]
    seeds = [0, 1, 2, 3, 4]
    set = { "train.dynamic_steps" = 4000 }   # like --set KEY=VALUE

Every error is one line naming the file and the key (``paper.toml: stage 3: seeds: ...``).
Paths: ``results`` and ``data_root`` are taken from where the command runs (as ``--results``);
a stage's ``clips`` (audio files) from the plan's own folder.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lmgs_eval.errors import UserError

PROTOCOLS = ("self", "cross", "stress", "capacity")

_TOP = {"name", "description", "results", "data_root", "preset", "retries", "cpus", "gpus", "device", "set", "imports",
        "stage"}
_STAGE = {"protocols", "subjects", "methods", "seeds", "preset", "set", "device", "cpus", "gpus", "retries",
          "clips", "conditions", "max_minutes", "long_seconds", "budgets", "label"}
# keys a stage inherits from the plan's top level when it does not set them
_INHERITED = ("preset", "retries", "cpus", "gpus", "device")
_DEFAULTS = {"preset": "quick", "retries": 1, "cpus": 1, "gpus": 0, "device": None}


@dataclass(frozen=True)
class Stage:
    """One block of runs: every protocol x subject x method x seed of it is a run."""

    protocols: tuple[str, ...]
    subjects: tuple[str, ...]
    methods: tuple[str, ...] = ("lmgs",)
    seeds: tuple[int, ...] = (0,)
    preset: str = "quick"
    overrides: dict[str, Any] = field(default_factory=dict)  # ``set``: dotted key -> value
    device: str | None = None
    cpus: int = 1
    gpus: float = 0
    retries: int = 1
    clips: tuple[str, ...] = ()  # cross: audio files (default: the subject's bundled clips A and B)
    conditions: tuple[str, ...] = ()  # stress: the conditions (default: all)
    max_minutes: float = 15.0  # stress
    long_seconds: float = 300.0  # stress
    budgets: tuple[int, ...] | None = None  # capacity (default: the 500-20k sweep)
    label: str = ""


@dataclass(frozen=True)
class Plan:
    """A whole benchmark: where it came from, its defaults and its stages in order."""

    name: str
    stages: tuple[Stage, ...]
    source: str = "<plan>"
    description: str = ""
    results: str | None = None
    data_root: str | None = None
    imports: tuple[str, ...] = ()  # modules imported before any run (they register methods)


def load_plan(path: str | Path) -> Plan:
    """Read and check a plan file (TOML)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such plan file")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not a valid TOML file ({exc})") from None
    return plan_from_dict(data, str(path), base=path.parent)


def plan_from_dict(data: dict, source: str = "<plan>", base: Path | None = None) -> Plan:
    """A plan from its decoded mapping (what :func:`load_plan` reads); ``base`` resolves relative paths."""
    where = source
    _unknown(data, _TOP, where)
    name = _str(data.get("name", Path(source).stem), f"{where}: name")
    top = {k: data.get(k, _DEFAULTS[k]) for k in _INHERITED}
    top_set = _overrides(data.get("set", {}), f"{where}: set")
    stages = data.get("stage")
    if not isinstance(stages, list) or not stages or not all(isinstance(s, dict) for s in stages):
        raise UserError(f"{where}: stage: expected one or more [[stage]] tables")
    out = [_stage(s, top, top_set, f"{where}: stage {i}", base) for i, s in enumerate(stages, 1)]
    imports = data.get("imports", [])
    if not isinstance(imports, list) or not all(isinstance(m, str) and m for m in imports):
        raise UserError(f"{where}: imports: expected a list of module names")
    results = data.get("results")
    data_root = data.get("data_root")
    for key, v in (("results", results), ("data_root", data_root), ("description", data.get("description", ""))):
        if v is not None:
            _str(v, f"{where}: {key}")
    return Plan(name=name, stages=tuple(out), source=source, description=data.get("description", ""),
                results=results, data_root=data_root, imports=tuple(imports))


def _stage(d: dict, top: dict, top_set: dict, where: str, base: Path | None) -> Stage:
    _unknown(d, _STAGE, where)
    for key in ("protocols", "subjects"):
        if key not in d:
            raise UserError(f"{where}: {key}: missing (one or more names)")
    protocols = _names(d["protocols"], f"{where}: protocols")
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad:
        raise UserError(f"{where}: protocols: unknown protocol '{bad[0]}' (known: {', '.join(PROTOCOLS)})")
    if "capacity" in protocols and len(protocols) > 1:
        raise UserError(f"{where}: protocols: capacity trains lmgs at each budget; give it a stage of its own")
    if "capacity" in protocols:
        methods = _names(d.get("methods", ["lmgs"]), f"{where}: methods")
        if methods != ("lmgs",):
            raise UserError(f"{where}: methods: the capacity protocol runs lmgs only, got {', '.join(methods)}")
    else:
        if "methods" not in d:
            raise UserError(f"{where}: methods: missing (one or more method names; `lmgs-eval methods` lists them)")
        methods = _names(d["methods"], f"{where}: methods")
    seeds = d.get("seeds", [0])
    if not isinstance(seeds, list) or not seeds or not all(type(s) is int and s >= 0 for s in seeds):
        raise UserError(f"{where}: seeds: expected a list of non-negative integers, got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise UserError(f"{where}: seeds: {seeds!r} repeats a seed")
    kw = {k: d.get(k, top[k]) for k in _INHERITED}
    _str(kw["preset"], f"{where}: preset")
    for k in ("retries", "cpus"):
        if type(kw[k]) is not int or kw[k] < (0 if k == "retries" else 1):
            raise UserError(f"{where}: {k}: expected an integer >= {0 if k == 'retries' else 1}, got {kw[k]!r}")
    if isinstance(kw["gpus"], bool) or not isinstance(kw["gpus"], (int, float)) or kw["gpus"] < 0:
        raise UserError(f"{where}: gpus: expected a number >= 0, got {kw['gpus']!r}")
    if kw["device"] is not None:
        _str(kw["device"], f"{where}: device")
        if str(kw["device"]).startswith("cuda") and "gpus" not in d and top["gpus"] == 0:
            kw["gpus"] = 1  # a run told to use a GPU asks the scheduler for one
    overrides = {**top_set, **_overrides(d.get("set", {}), f"{where}: set")}
    clips = tuple(_path(c, base) for c in _names(d.get("clips", []), f"{where}: clips", empty=True))
    for c in clips:  # a clip that is not there would leave its cross runs with nothing to drive them
        if not Path(c).is_file():
            raise UserError(f"{where}: clips: {c}: " + ("is a folder, not an audio file" if Path(c).is_dir()
                                                         else "no such audio file"))
    conditions = _names(d.get("conditions", []), f"{where}: conditions", empty=True)
    for k in ("max_minutes", "long_seconds"):
        v = d.get(k, Stage.__dataclass_fields__[k].default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0:
            raise UserError(f"{where}: {k}: expected a positive number, got {v!r}")
    budgets = d.get("budgets")
    if budgets is not None and (not isinstance(budgets, list) or not budgets
                                or not all(type(b) is int and b > 0 for b in budgets)):
        raise UserError(f"{where}: budgets: expected a list of positive integers (Gaussians), got {budgets!r}")
    for key, applies in (("clips", "cross"), ("conditions", "stress"), ("max_minutes", "stress"),
                         ("long_seconds", "stress"), ("budgets", "capacity")):
        if key in d and applies not in protocols:
            raise UserError(f"{where}: {key}: applies to the {applies} protocol, which this stage does not run")
    return Stage(protocols=protocols, subjects=_names(d["subjects"], f"{where}: subjects"), methods=methods,
                 seeds=tuple(seeds), overrides=overrides, clips=clips, conditions=conditions,
                 max_minutes=float(d.get("max_minutes", 15.0)), long_seconds=float(d.get("long_seconds", 300.0)),
                 budgets=None if budgets is None else tuple(budgets), label=_str(d.get("label", ""), f"{where}: label"),
                 **kw)


def _unknown(d: dict, known: set[str], where: str) -> None:
    extra = sorted(set(d) - known)
    if extra:
        raise UserError(f"{where}: unknown key '{extra[0]}' (known: {', '.join(sorted(known))})")


def _str(v, where: str) -> str:
    if not isinstance(v, str):
        raise UserError(f"{where}: expected a string, got {v!r}")
    return v


def _names(v, where: str, empty: bool = False) -> tuple[str, ...]:
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or (not v and not empty) or not all(isinstance(x, str) and x for x in v):
        raise UserError(f"{where}: expected a list of names, got {v!r}")
    if len(set(v)) != len(v):
        raise UserError(f"{where}: {v!r} names one twice")
    return tuple(v)


def _overrides(v, where: str) -> dict[str, Any]:
    """``set`` as ``--set`` reads it: dotted keys to values (a nested table is flattened with dots)."""
    if not isinstance(v, dict):
        raise UserError(f"{where}: expected a table of KEY = VALUE")
    out: dict[str, Any] = {}
    for k, x in v.items():
        if isinstance(x, dict):
            out.update({f"{k}.{kk}": xx for kk, xx in _overrides(x, f"{where}.{k}").items()})
        else:
            out[k] = x
    return out


def _path(p: str | None, base: Path | None) -> str | None:
    if p is None or base is None or Path(p).expanduser().is_absolute():
        return None if p is None else str(Path(p).expanduser())
    return str(base / p)
