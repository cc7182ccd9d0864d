"""The ``--sync`` flag of every command that scores, and the one line printed for an untrusted LSE."""

from __future__ import annotations

import argparse
import sys

SYNC_CHOICES = ("auto", "landmark", "pixel", "syncnet-v2")  # sync_select.CHOICES, without importing the metrics


def add_sync_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sync", choices=SYNC_CHOICES, default="auto",
                   help="LSE scorer: syncnet-v2 (official weights, once imported), landmark (bundled, mouth "
                        "landmarks vs audio), pixel (bundled, mouth crops); auto: official when imported, else the "
                        "bundled scorer that passes its self-check on the clip (default)")


def apply(args: argparse.Namespace) -> None:
    from lmgs_eval.metrics.sync_select import set_backend

    set_backend(getattr(args, "sync", None))


def untrusted(entries) -> list[str]:
    """Labels of LSE results whose self-check failed; ``entries``: ``(label, values)`` pairs."""
    return [label for label, values in entries if (values or {}).get("trusted") is False]


def print_untrusted(labels: list[str], prog: str) -> None:
    if labels:
        from lmgs_eval.metrics.sync_check import UNTRUSTED_HINT

        shown = ", ".join(labels[:4]) + (f" and {len(labels) - 4} more" if len(labels) > 4 else "")
        print(f"{prog}: LSE not trusted on {shown}: {UNTRUSTED_HINT}", file=sys.stderr)


def print_untrusted_records(records: list[dict], prog: str) -> None:
    """The line for protocol records (``metrics.lse_d.values`` carries the self-check)."""
    entries = [(f"{r['method']['display_name']}/{r['protocol']['clip']}",
                ((r.get("metrics") or {}).get("lse_d") or {}).get("values")) for r in records]
    print_untrusted(untrusted(entries), prog)
