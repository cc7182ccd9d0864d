"""``lmgs-eval report``: the benchmark as a static site (leaderboards, Watch pages, charts, provenance)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "write the benchmark as a static site from a results store: leaderboards, side-by-side videos, charts, provenance"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", default="results", type=Path, help="results store (default: results/)")
    p.add_argument("--out", default=None, type=Path, help="site folder, replaced (default: RESULTS/report)")
    p.add_argument("--renders", default=None, type=Path, metavar="DIR",
                   help="folder the records' relative render paths are under (default: the store; e.g. "
                        "--results tables/records --renders results)")
    p.add_argument("--preview-side", type=int, default=256, metavar="PX",
                   help="longer side of the video previews in pixels (default 256)")
    p.add_argument("--no-previews", action="store_true", help="do not encode video previews of the renders")
    p.add_argument("--no-static-charts", action="store_true", help="skip the matplotlib PNG / SVG charts")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.errors import UserError
    from lmgs_eval.report.site import build_site

    if not 16 <= args.preview_side <= 4096:
        raise UserError(f"--preview-side {args.preview_side}: must be between 16 and 4096 pixels")

    out = args.out if args.out is not None else Path(args.results) / "report"
    index, warnings = build_site(args.results, out, previews=not args.no_previews,
                                 charts=not args.no_static_charts, renders=args.renders,
                                 preview_side=args.preview_side, log=lambda s: print(s, file=sys.stderr))
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(index.resolve())
    return 0
