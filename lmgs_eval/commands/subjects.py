"""``lmgs-eval subjects``: list bundled and found subjects."""

from __future__ import annotations

import argparse
import json

HELP = "list bundled and found subjects (built or not, frames, size, split)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.data.registry import list_subjects
    from lmgs_eval.paths import data_root

    rows = list_subjects(args.data_root)
    if args.json:
        print(json.dumps({"data_root": str(data_root(args.data_root)), "subjects": rows}, indent=2))
        return 0
    print(f"data root: {data_root(args.data_root)}")
    print(f"{'name':<22} {'kind':<8} {'frames':>6} {'size':>9} {'split':>11}  status")
    for r in rows:
        kind = "bundled" if r.get("bundled") else "real"
        frames = str(r.get("frames", "-"))
        size = f"{r['width']}x{r['height']}" if "width" in r else "-"
        split = f"{r['train_frames']}/{r['test_frames']}" if "train_frames" in r else "-"
        status = r.get("status", "ok")
        if r.get("bundled") and r.get("standin"):
            status += " (synthetic stand-in)"
        print(f"{r['name']:<22} {kind:<8} {frames:>6} {size:>9} {split:>11}  {status}")
    return 0
