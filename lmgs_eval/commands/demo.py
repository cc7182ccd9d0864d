"""``lmgs-eval demo``: the main job of ``make demo``.

Builds the bundled ``astronaut`` subject (cached), runs the self-driven protocol with the
``quick`` preset, the cross-driven protocol with the bundled clips A and B, and writes the
tables and charts; prints where the tables, charts and videos are. Resumable: finished runs
are found in the results store and not redone.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

HELP = "the main job: build astronaut, run self and cross with lmgs (quick preset), write tables and charts"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="astronaut", help="subject (default astronaut)")
    p.add_argument("--method", dest="methods", action="append", metavar="M", help="methods (default lmgs)")
    p.add_argument("--results", default="results", help="results store (default ./results)")
    p.add_argument("--out", default=None, help="tables and charts folder (default RESULTS/tables)")
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.commands._common import print_rows
    from lmgs_eval.protocols import RunConfig, log, run_cross, run_self

    t0 = time.perf_counter()
    results = Path(args.results)
    cfg = RunConfig(subject=args.subject, methods=tuple(args.methods or ("lmgs",)), results=results,
                    data_root=args.data_root, progress=not args.no_progress)
    log(f"[demo] 1/3 self-driven protocol on {cfg.subject}")
    recs = run_self(cfg)
    log(f"[demo] 2/3 cross-driven protocol (bundled clips A and B) [{time.perf_counter() - t0:.0f} s]")
    crecs, errors = run_cross(cfg)
    for e in errors:
        log(f"[demo] cross: {e}")
    if recs or crecs:
        print_rows(recs + crecs)
    log(f"[demo] 3/3 tables and charts [{time.perf_counter() - t0:.0f} s]")
    from lmgs_eval.commands import table

    out = Path(args.out) if args.out else results / "tables"
    targs = argparse.Namespace(results=results, format="all", out=out, ci=False, no_charts=False)
    table.run(targs)
    print(f"\ndemo finished in {time.perf_counter() - t0:.0f} s")
    print(f"  tables and charts: {out.resolve()}")
    print(f"  videos (with sound): {(results / 'renders').resolve()}")
    print(f"  results records: {results.resolve()}")
    return 0
