"""``lmgs-eval bench TARGET``: speed benchmarks measured side by side in one run.

Each target is a module with ``add_arguments(parser)`` and ``run(args) -> dict``; the dict
is printed as a table, or as one JSON object on stdout with ``--json``. Ratios are always
measured in the same run, on this machine, never compared with stored figures. ``stripped``
and ``ingested`` train one method twice (on a bundled subject, and on its plain copy or on the
ingest of its raw video) and compare quality as well as cost; ``bench all`` leaves them out.
"""

from __future__ import annotations

import argparse
import importlib
import json

HELP = "speed benchmarks (raster, metrics, ...), measured side by side in one run"

TARGETS: dict[str, str] = {
    "raster": "lmgs.render.bench",
    "metrics": "lmgs_eval.metrics.bench",
    "model": "lmgs.bench",
    "ingest": "lmgs_eval.data.ingest.bench",
    "stripped": "lmgs_eval.commands._bench_stripped",
    "ingested": "lmgs_eval.commands._bench_ingested",
    "score-memory": "lmgs_eval.commands._bench_score_memory",
    "lips": "lmgs_eval.commands._bench_lips",
    "sync": "lmgs_eval.commands._bench_sync",
}


def _load(target: str):
    """A target's module; a missing one is an error of the installation, not a benchmark silently left out."""
    return importlib.import_module(TARGETS[target])


def _in_all(target: str) -> bool:
    """Whether ``bench all`` runs a target (a module with ``IN_ALL = False`` trains models, not a speed benchmark)."""
    return getattr(_load(target), "IN_ALL", True)


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="target", metavar="TARGET", required=True)
    for name in TARGETS:
        mod = _load(name)
        sp = sub.add_parser(name, help=getattr(mod, "HELP", name))
        sp.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        mod.add_arguments(sp)
        sp.set_defaults(_bench=mod)
    sp = sub.add_parser("all", help="every speed benchmark (not the training comparisons: "
                        f"{', '.join(n for n in TARGETS if not _in_all(n))}; run those by name)")
    sp.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    sp.set_defaults(_bench=None)


def _is_table(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(r, dict) for r in v)


def _print_table(name: str, result: dict) -> None:
    print(f"== bench {name} ==")
    for k, v in result.items():
        if k != "rows" and not _is_table(v):
            print(f"{k}: {v}")
    for k, v in result.items():
        if k != "rows" and _is_table(v):
            print(f"-- {k} --")
            _print_rows(v)
    if _is_table(result.get("rows")):
        _print_rows(result["rows"])


def _print_rows(rows: list[dict]) -> None:
    if rows:
        cols = list(rows[0])
        widths = [max(len(str(c)), *(len(_fmt(r.get(c))) for r in rows)) for c in cols]
        print("  ".join(str(c).ljust(w) for c, w in zip(cols, widths)))
        for r in rows:
            print("  ".join(_fmt(r.get(c)).ljust(w) for c, w in zip(cols, widths)))


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def run(args: argparse.Namespace) -> int:
    if args._bench is None:
        results = {}
        for name in filter(_in_all, TARGETS):
            mod = _load(name)
            sp = argparse.ArgumentParser()
            mod.add_arguments(sp)
            results[name] = mod.run(sp.parse_args([]))
    else:
        results = {args.target: args._bench.run(args)}
    if args.json:
        print(json.dumps(results if args._bench is None else results[args.target], indent=2))
    else:
        for name, res in results.items():
            _print_table(name, res)
    return 0
