"""``lmgs-eval weights``: import metric weights supplied by the user (nothing is downloaded)."""

from __future__ import annotations

import argparse
import json

HELP = "import metric weights you have (e.g. the official SyncNet syncnet_v2.model) into the cache as ONNX"


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    s = sub.add_parser("import-syncnet", help="convert syncnet_python's syncnet_v2.model state dict to ONNX")
    s.add_argument("path", help="syncnet_v2.model (a torch state dict of SyncNetModel S)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    if args.action == "import-syncnet":
        from lmgs_eval.metrics.sync import import_syncnet

        print(json.dumps(import_syncnet(Path(args.path)), indent=2))
    return 0
