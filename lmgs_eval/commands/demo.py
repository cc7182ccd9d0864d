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

HELP = ("the main job: build astronaut, run self and cross with lmgs (quick preset), write tables, charts and the "
        "report site; "
        "--full: every method on both bundled subjects, ablations, stress and capacity (make bench)")

REPORT_PREVIEW_SIDE = 160  # px: previews of the committed report stay small
PAPER_PLAN = "benchmarks/paper.toml"  # the committed benchmark (every method, both subjects, Tables III-IV, stress, capacity)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--subject", default="astronaut", help="subject (default astronaut)")
    p.add_argument("--method", dest="methods", action="append", metavar="M", help="methods (default lmgs)")
    p.add_argument("--results", default="results", help="results store (default ./results)")
    p.add_argument("--out", default=None, help="tables and charts folder (default RESULTS/tables)")
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", default=[],
                   help="override a config value of the methods, dotted (e.g. train.dynamic_steps=400: a shorter demo)")
    p.add_argument("--full", action="store_true",
                   help="the whole benchmark (resumable, hours on 2 cores): the plan --plan (default "
                        f"{PAPER_PLAN}: every method on astronaut and hopper, Tables III-IV variants, the stress suite "
                        "and capacity); tables to ./tables")
    p.add_argument("--plan", default=PAPER_PLAN, help=f"with --full: the benchmark plan (default {PAPER_PLAN})")
    from lmgs_eval.commands.run_plan import add_executor_arguments

    add_executor_arguments(p)


def run_full(args: argparse.Namespace) -> int:
    """``make bench``: the committed plan through the plan runner; every run resumes from the results store."""
    import dataclasses

    from lmgs_eval.commands import table
    from lmgs_eval.commands.run_plan import report
    from lmgs_eval.plans import load_plan, make_executor, run_plan
    from lmgs_eval.runner import log

    t0 = time.perf_counter()
    plan = load_plan(args.plan)
    if args.data_root:
        plan = dataclasses.replace(plan, data_root=args.data_root)
    executor = make_executor(args.executor, args.address, args.max_parallel)
    results = Path(args.results)
    out = Path(args.out) if args.out else Path("tables")
    archive = out / "records"
    if archive.is_dir():
        # The committed records of earlier sittings (on other machines): runs already
        # recorded there are not redone, and the tables are made from them and the new runs.
        from lmgs_eval.results import copy_records

        n, warnings = copy_records(archive, results)
        for w in warnings:
            log(f"[bench] {w}")
        log(f"[bench] {n} records of earlier sittings imported from {archive} into {results}")
    rc = report(run_plan(plan, executor, results), results)
    table.run(argparse.Namespace(results=results, format="all", out=out, ci=False, no_charts=False,
                                 records=archive))
    # from the committed snapshot of records (its pages link those), with the renders of this store;
    # 160 px previews keep the committed report small
    index = _report(archive, out / "report", renders=results, preview_side=REPORT_PREVIEW_SIDE)
    print(f"\nbenchmark finished in {(time.perf_counter() - t0) / 60:.0f} min; tables and charts: {out.resolve()}")
    print(f"  report (open in a browser): {index.resolve()}")
    return rc


def run(args: argparse.Namespace) -> int:
    if args.full:
        return run_full(args)
    import dataclasses
    import os

    from lmgs_eval.commands._common import parse_overrides, print_rows
    from lmgs_eval.plans import make_executor, plan_from_dict, run_plan
    from lmgs_eval.runner import log

    t0 = time.perf_counter()
    results = Path(args.results)
    # a small plan: the self- and cross-driven protocols of the methods on one subject
    plan = plan_from_dict({"name": "demo", "cpus": max(1, os.cpu_count() or 1),
                           "set": parse_overrides(args.overrides).get("overrides", {}), "stage": [
        {"protocols": ["self", "cross"], "subjects": [args.subject], "methods": list(args.methods or ("lmgs",))}]})
    if args.data_root:
        plan = dataclasses.replace(plan, data_root=args.data_root)
    log(f"[demo] 1/2 self- and cross-driven protocols on {args.subject} (bundled clips A and B)")
    summary = run_plan(plan, make_executor(args.executor, args.address, args.max_parallel), results)
    for m in summary.messages:
        log(f"[demo] {m}")
    for f in summary.failed:
        log(f"[demo] failed: {f}")
    if summary.records:
        print_rows(summary.records)
    log(f"[demo] 2/2 tables and charts [{time.perf_counter() - t0:.0f} s]")
    from lmgs_eval.commands import table

    out = Path(args.out) if args.out else results / "tables"
    targs = argparse.Namespace(results=results, format="all", out=out, ci=False, no_charts=False, records=None)
    table.run(targs)
    index = _report(results, results / "report")
    print(f"\ndemo finished in {time.perf_counter() - t0:.0f} s")
    print(f"  tables and charts: {out.resolve()}")
    print(f"  videos (with sound): {(results / 'renders').resolve()}")
    print(f"  results records: {results.resolve()}")
    print(f"  report (open in a browser): {index.resolve()}")
    return 1 if summary.failed else 0


def _report(results: Path, out: Path, renders: Path | None = None, preview_side: int = 256) -> Path:
    """The static site of the store (``lmgs-eval report``); returns its index page."""
    from lmgs_eval.report.site import build_site
    from lmgs_eval.runner import log

    index, _ = build_site(results, out, renders=renders, preview_side=preview_side, log=log)
    return index
