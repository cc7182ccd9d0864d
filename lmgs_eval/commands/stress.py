"""``lmgs-eval stress``: the stability suite (perturbed driving audio; where each method breaks)."""

from __future__ import annotations

import argparse
import sys
import time

HELP = "stability suite: drive trained models with silence, noise, clipping, speed/pitch changes, another voice, a long clip..."


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._common import add_run_arguments

    add_run_arguments(p)
    p.add_argument("--condition", dest="conditions", action="append", metavar="NAME",
                   help="run only these conditions (repeatable; clean always runs); default: the whole set")
    p.add_argument("--max-minutes", type=float, default=15.0,
                   help="skip (and report) a condition whose predicted rendering time at the clean FPS is longer (default 15)")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="run N method/seed suites at once in worker processes, the CPU threads shared out "
                        "(default 1; their FPS and wall times are then measured beside each other, and say so)")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.commands._common import run_config
    from lmgs_eval.commands._sync import print_untrusted_records
    from lmgs_eval.protocols.stress import run_stress

    cfg = run_config(args)
    t0 = time.perf_counter()
    records, messages = run_stress(cfg, tuple(args.conditions or ()), args.max_minutes, jobs=args.jobs)
    wall = time.perf_counter() - t0
    for m in messages:
        print(f"lmgs-eval stress: {m}", file=sys.stderr)
    if records:
        print(f"{'method':<26} {'condition':<13} {'frames':>6} {'LSE-C':>7} {'LMD':>6} {'jitter':>7} {'open@sil':>8} {'FPS':>6}  status")
        for r in records:

            def v(k, fmt):
                x = r.value(k)
                return fmt.format(x) if isinstance(x, (int, float)) else "-"

            st = (r.status.reason if r.status else None) or "ok"
            print(f"{r.method.display_name[:26]:<26} {r.protocol.clip:<13} {r.protocol.n_frames:>6} "
                  f"{v('lse_c', '{:.3f}'):>7} {v('lmd', '{:.2f}'):>6} {v('jitter', '{:.3f}'):>7} {v('silence_open', '{:.2f}'):>8} "
                  f"{r.cost.fps or 0:>6.1f}  {st}")
        n_fail = sum(1 for r in records if r.failed)
        print_untrusted_records(records, "lmgs-eval stress")
        print(f"{len(records)} condition runs, {n_fail} failed, {wall / 60:.1f} min wall (jobs {args.jobs}); "
              "`lmgs-eval table` writes the stability tables and heat-maps")
    print(f"results: {cfg.results.resolve()}")
    return 0
