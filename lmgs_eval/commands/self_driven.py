"""``lmgs-eval self``: the self-driven protocol (train on the training split, drive with the test audio)."""

from __future__ import annotations

import argparse

HELP = "self-driven protocol: fit each method, render the test split from its audio, score, record"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._common import add_run_arguments

    add_run_arguments(p)


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.commands._common import print_rows, run_config
    from lmgs_eval.commands._sync import print_untrusted_records
    from lmgs_eval.protocols.self_driven import run_self

    cfg = run_config(args)
    records = run_self(cfg)
    if records:
        print_rows(records)
        print_untrusted_records(records, "lmgs-eval self")
    print(f"results: {cfg.results.resolve()}  (lmgs-eval table --results {cfg.results} makes the tables)")
    return 0
