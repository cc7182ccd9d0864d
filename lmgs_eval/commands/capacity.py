"""``lmgs-eval capacity``: train lmgs at a range of Gaussian budgets; quality and cost against the count."""

from __future__ import annotations

import argparse

HELP = "train lmgs with Gaussian budgets 500..20k; quality (PSNR, LPIPS, LMD) and cost against the count, the knee marked"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._common import add_run_arguments

    add_run_arguments(p)
    p.add_argument("--budget", dest="budgets", type=int, action="append", metavar="N",
                   help="Gaussian budget (repeatable; default 500 1000 2000 5000 10000 20000)")
    p.add_argument("--out", help="folder for the chart (default RESULTS/tables)")


def _print_row(width: int, head: str, p: dict, mark: str) -> None:
    """One line of the capacity table: a run (``head`` its seed) or a budget's mean over seeds."""
    def f(v, fmt):
        return fmt.format(v) if isinstance(v, (int, float)) else "-"
    print(f"{head:>{width}} {p['budget']:>7} {f(p['n_gaussians'], '{:.0f}'):>7} {f(p['psnr'], '{:.2f}'):>6} "
          f"{f(p['lpips'], '{:.4f}'):>7} {f(p['lmd'], '{:.2f}'):>5} {f(p['fps'], '{:.1f}'):>6} {f(p['model_mb'], '{:.2f}'):>6} "
          f"{f(p['train_seconds'], '{:.0f}'):>7}{mark}")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lmgs_eval.protocols.capacity import DEFAULT_BUDGETS, run_capacity
    from lmgs_eval.report.capacity import budget_means, failed_points, knee, points_from_records, tolerance_text
    from lmgs_eval.report.charts import capacity_charts
    from lmgs_eval.commands._common import run_config
    from lmgs_eval.errors import UserError
    from lmgs_eval.results import load_records

    if args.methods and set(args.methods) != {"lmgs"}:
        raise UserError("capacity trains lmgs only (--method is not used)")
    args.methods = None
    cfg = run_config(args)
    budgets = tuple(sorted(set(args.budgets or DEFAULT_BUDGETS)))
    if min(budgets) < 1:
        raise UserError("--budget must be a positive number of Gaussians")
    run_capacity(cfg, budgets)
    records, _ = load_records(cfg.results)
    pts = points_from_records(records)
    for subject, ps in pts.items():
        print(f"{subject}: {'budget':>7} {'Gauss.':>7} {'PSNR':>6} {'LPIPS':>7} {'LMD':>5} {'FPS':>6} {'MB':>6} {'train s':>7}")
        means = budget_means(ps)
        k = knee(means)
        knee_mark = {k["budget"]: "  <- knee"} if k is not None else {}
        width = len(subject) + 1
        several = any(m["n_seeds"] > 1 for m in means)
        for p in sorted(ps, key=lambda p: (p["budget"], p["seed"])):
            _print_row(width, f"s{p['seed']}" if several else "", p, "" if several else knee_mark.get(p["budget"], ""))
        if several:  # the knee is marked on the means
            for m in means:
                seeds = f"  ({m['n_seeds']} seed{'s' if m['n_seeds'] > 1 else ''})"
                _print_row(width, "mean", m, seeds + knee_mark.get(m["budget"], ""))
        for fp in failed_points(records).get(subject, []):
            print(f"{'':{len(subject) + 1}} {fp['budget']:>7} FAILED (seed {fp['seed']}): {fp['reason']}")
        print(f"  knee: the smallest budget with {tolerance_text()}" + (", on the means over seeds" if several else ""))
    out = Path(args.out) if args.out else cfg.results / "tables"
    for f in capacity_charts(records, out):
        if f.suffix == ".png":
            print(f"chart: {f}")
    print(f"results: {cfg.results.resolve()}")
    return 0
