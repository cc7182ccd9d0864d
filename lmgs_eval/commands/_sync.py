"""The ``--sync`` flag of every command that scores, and the one line printed for an untrusted LSE."""

from __future__ import annotations

import argparse
import sys

SYNC_CHOICES = ("auto", "mesh", "landmark", "pixel", "syncnet-v2")  # metrics.config.SYNC_CHOICES, without importing the metrics


def add_sync_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sync", choices=SYNC_CHOICES, default="auto",
                   help="LSE scorer: syncnet-v2 (official weights, once imported), mesh (bundled, the dense face "
                        "mesh's mouth vs audio, adapted on real speakers), landmark (bundled, mouth landmarks vs "
                        "audio), pixel (bundled, mouth crops); auto: official when imported, else the bundled scorer "
                        "that passes its self-check on the clip (default; `lmgs-eval metrics` says which is tried "
                        "first)")


def suite(args: argparse.Namespace):
    """The metric suite of a scoring command: ``--sync`` goes into its config, and the suite resolves the
    scorer from there (:class:`~lmgs_eval.metrics.sync.select.SyncScorers`)."""
    from lmgs_eval.metrics.config import SuiteConfig
    from lmgs_eval.metrics.metric_suite import MetricSuite

    return MetricSuite(SuiteConfig(sync=getattr(args, "sync", None) or "auto"))


def untrusted(entries) -> list[str]:
    """Labels of LSE results whose self-check failed; ``entries``: ``(label, values)`` pairs."""
    return [label for label, values in entries if (values or {}).get("trusted") is False]


def print_untrusted(labels: list[str], prog: str) -> None:
    if labels:
        from lmgs_eval.metrics.sync.check import UNTRUSTED_HINT

        shown = ", ".join(labels[:4]) + (f" and {len(labels) - 4} more" if len(labels) > 4 else "")
        print(f"{prog}: LSE not trusted on {shown}: {UNTRUSTED_HINT}", file=sys.stderr)


def print_untrusted_records(records: list, prog: str) -> None:
    """The line for protocol records (``metrics.lse_d.values`` carries the self-check)."""
    entries = [(f"{r.method.display_name}/{r.protocol.clip}", getattr(r.metrics.get("lse_d"), "values", None))
               for r in records]
    print_untrusted(untrusted(entries), prog)
