"""``lmgs-eval cross``: drive trained models with other audio (LSE; LMD where the clip has GT)."""

from __future__ import annotations

import argparse
import sys

HELP = "cross-driven protocol: drive trained models with other audio clips (default: the bundled A and B)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._common import add_run_arguments

    p.add_argument("--audio", nargs="+", metavar="WAV", help="driving audio files (any rate, mono or stereo)")
    add_run_arguments(p)


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.commands._common import print_rows, run_config
    from lmgs_eval.commands._sync import print_untrusted_records
    from lmgs_eval.protocols.cross import run_cross

    cfg = run_config(args)
    records, errors = run_cross(cfg, args.audio)
    for e in errors:
        print(f"lmgs-eval cross: error: {e}", file=sys.stderr)
    if records:
        print_rows(records)
        print_untrusted_records(records, "lmgs-eval cross")
    print(f"results: {cfg.results.resolve()}")
    return 2 if errors and not records else (1 if errors else 0)
