"""``lmgs-eval metrics``: the metrics, their definitions and which backends this machine has."""

from __future__ import annotations

import argparse
import json

HELP = "list metrics, their exact definitions and which backends are available here"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--alexnet", help="path of torchvision's alexnet-owt-7be5be79.pth (official LPIPS trunk; any "
                                     "other AlexNet-shaped trunk is listed as lpips-alex-custom)")
    p.add_argument("-v", "--verbose", action="store_true", help="print each definition")


def run(args: argparse.Namespace) -> int:
    from lmgs_eval.metrics.registry import list_metrics

    rows = list_metrics(args.alexnet)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    w = max([14, *(len(r["name"]) for r in rows)])
    print(f"{'name':<{w}} {'avail':<5} {'dir':<3} {'unit':<4} {'version':<7} detail")
    for r in rows:
        arrow = "↑" if r["higher_is_better"] else "↓"
        print(f"{r['name']:<{w}} {'yes' if r['available'] else 'no':<5} {arrow:<3} {r['unit']:<4} {r['version']:<7} {r['detail']}")
        if r["standin"]:
            print(f"{'':<{w + 1}}stand-in: {r['standin']}")
        if args.verbose:
            print(f"{'':<{w + 1}}{r['definition']}")
    return 0
