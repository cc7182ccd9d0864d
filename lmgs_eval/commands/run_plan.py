"""``lmgs-eval run PLAN``: a benchmark plan (TOML) run serially or on a Ray cluster, resumable."""

from __future__ import annotations

import argparse

HELP = "run a benchmark plan (TOML): every run not already in the results store, serially or on Ray; resumable"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("plan", help="the plan file (e.g. benchmarks/paper.toml)")
    add_executor_arguments(p)
    p.add_argument("--results", default=None, help="results store (default: the plan's `results`, else ./results)")
    p.add_argument("--data-root", help="folder of subjects (default: the plan's `data_root`, $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--dry-run", action="store_true", help="list the runs and whether each is in the store; run nothing")


def add_executor_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--executor", default="serial", choices=["serial", "ray"],
                   help="serial: one run after another in this process (default); ray: each run a Ray task "
                        "(pip install '.[cluster]')")
    p.add_argument("--address", default=None,
                   help="with --executor ray: the cluster to join (`auto`, or HOST:PORT of `ray start --head`); "
                        "default: a Ray instance on this machine")
    p.add_argument("--max-parallel", type=int, default=None, metavar="N",
                   help="at most N runs at once (default: as many as the cluster's CPUs allow)")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.plans import check_executor, expand, load_plan, make_executor, run_plan
    from lmgs_eval.plans.identity import Identities

    import dataclasses

    plan = load_plan(args.plan)
    if args.data_root:
        plan = dataclasses.replace(plan, data_root=args.data_root)
    results = args.results or plan.results or "results"
    check_executor(args.executor, args.address, args.max_parallel)  # a dry run refuses what the run would
    if args.dry_run:
        ids = Identities(results, plan.data_root)
        for r in expand(plan):
            missing = _unbuilt(r.subject, plan.data_root)
            if missing:
                # a dry run builds nothing: without the subject its config hashes (and records) cannot be looked up
                print(f"todo  {r.label}  (subject not built yet at {missing}: the run builds it)")
                continue
            keys = ids.keys(r)
            done = bool(keys) and all(ids.finished(r, k) for k in keys)
            print(f"{'done' if done else 'todo'}  {r.label}  ({len(keys)} record(s))")
        return 0
    executor = make_executor(args.executor, args.address, args.max_parallel)
    summary = run_plan(plan, executor, results)
    return report(summary, results)


def _unbuilt(subject: str, data_root) -> str | None:
    """The folder of a bundled subject that is not built yet (None when it is, or when ``subject`` is not bundled)."""
    from lmgs_eval.data.bundled_spec import BundledSpec
    from lmgs_eval.data.registry import resolve_subject_dir

    if BundledSpec.parse(subject) is None:
        return None
    folder = resolve_subject_dir(subject, data_root, build=False)
    return None if (folder / "meta.json").is_file() else str(folder)


def report(summary, results) -> int:
    """The end of a plan's run on stdout; 1 when a run failed."""
    print(f"plan: {summary.total} runs, {summary.skipped} already in the store, {len(summary.done)} done, "
          f"{len(summary.failed)} failed in {summary.seconds / 60:.1f} min; results: {results}")
    for m in summary.messages:
        print(f"  note: {m}")
    for f in summary.failed:
        print(f"  failed: {f}")
    return 1 if summary.failed else 0
