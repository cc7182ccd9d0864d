"""``lmgs-eval score``: score a rendered clip against ground truth with every available metric."""

from __future__ import annotations

import argparse
import json

HELP = "score a rendered video / frame folder against ground truth (PSNR, SSIM, LPIPS, LMD, LSE)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pred", required=True, help="rendered video (mp4) or folder of frames")
    p.add_argument("--gt", help="ground-truth video or folder (omit for no-reference metrics only)")
    p.add_argument("--audio", help="driving audio (default: the pred video's audio track)")
    p.add_argument("--json", action="store_true", help="print the result record as JSON on stdout")
    p.add_argument("--truncate", action="store_true", help="score the common prefix when lengths differ (recorded)")
    p.add_argument("--alexnet", help="torchvision's alexnet-owt-7be5be79.pth: enables the official LPIPS (a trunk "
                                     "whose sha256 does not start with 7be5be79 scores as lpips-alex-custom)")
    p.add_argument("--lpips", choices=["lpips-alex", "stlpips-alex"], help="force one LPIPS network")
    p.add_argument("--landmarks", default="dlib", choices=["dlib", "fan"], help="LMD landmark backend")
    p.add_argument("--metrics", help="comma-separated subset: psnr,ssim,lpips,lmd,lse (one that cannot be computed, "
                                     "e.g. lse on a video without audio, is reported unavailable with its reason and "
                                     "the others are scored; when none asked can be: one error line, exit code 2)")
    p.epilog = ("A metric that cannot be computed on these inputs (LSE without audio or without a face, LMD without "
                "a face) is reported as unavailable, with its reason, and the other metrics are scored. When no "
                "metric asked for can be computed (e.g. --metrics lse on a video without audio), score prints one "
                "error line and exits with code 2. The clips are read a few frames at a time, never held whole.")
    p.add_argument("--reference", action="store_true",
                   help="the pred is real footage known to be in sync (ground truth): LSE's self-check also "
                        "requires the AV offset to be 0 +- 1")
    from lmgs_eval.commands._sync import add_sync_argument

    add_sync_argument(p)


def run(args: argparse.Namespace) -> int:
    import sys

    from lmgs_eval.commands._sync import print_untrusted, untrusted
    from lmgs_eval.metrics.lpips import custom_trunk_line
    from lmgs_eval.metrics.suite import format_record, require_scored, score

    rec = score(args.pred, args.gt, args.audio, truncate=args.truncate, alexnet=args.alexnet, lpips=args.lpips,
                landmarks=args.landmarks, metrics=args.metrics.split(",") if args.metrics else None,
                reference=args.reference, sync=args.sync)
    require_scored(rec["results"], str(args.pred))
    custom = rec["results"].get("lpips-alex-custom")
    if custom:
        trunk = custom["spec"]["weights_files"]["alexnet"]
        print(f"lmgs-eval score: {custom_trunk_line(trunk['path'], trunk['sha256'])}", file=sys.stderr)
    if args.json:
        print(json.dumps(rec, indent=2))
    else:
        print(format_record(rec))
    lse = rec["results"].get("lse") or {}
    print_untrusted(untrusted([(str(args.pred), lse.get("values"))]), "lmgs-eval score")
    return 0
