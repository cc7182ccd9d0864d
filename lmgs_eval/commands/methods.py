"""``lmgs-eval methods``: the methods ``--method`` accepts, with family and what each keeps."""

from __future__ import annotations

import argparse
import json

HELP = "list the methods --method accepts (family, config hash, what each keeps and simplifies)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=("quick", "paper"), default="quick", help="preset whose config hash is shown")
    p.add_argument("--subject", help="show the configs as built for this subject (a bundled name, a folder name "
                   "under the data root, or a path): a subject's own Gaussian budget, derived priors, recorded footage")
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    from baselines.protocol import create_method, list_methods
    from lmgs.errors import InputError
    from lmgs_eval.hooks import adapter_hooks

    hooks = adapter_hooks()  # as the protocols build them, so the config hashes are theirs
    subject = None
    if args.subject:
        from lmgs_eval.data.registry import find_subject

        subject = find_subject(args.subject, args.data_root, progress=False)

    rows = []
    for name in list_methods():
        if name.startswith("external:"):
            rows.append({"name": name, "family": "external", "config_hash": "-", "variant": "",
                         "description": "scores a folder or video rendered by any other code (--renders PATH)"})
            continue
        try:
            info = create_method(name, subject=subject, preset=args.preset, hooks=hooks).describe()
        except InputError:  # a method without this preset: listed, with no config under it
            info = create_method(name, subject=subject, hooks=hooks).describe()
            rows.append({"name": name, "family": info.family, "config_hash": "-", "variant": info.variant or "",
                         "description": f"(no '{args.preset}' preset) {info.description}"})
            continue
        rows.append({"name": name, "family": info.family, "config_hash": info.config_hash,
                     "variant": info.variant or "", "description": info.description})
    if args.json:
        print(json.dumps({"preset": args.preset, "subject": subject.name if subject else None, "methods": rows}, indent=2))
        return 0
    if subject is not None:
        print(f"configs as built for subject {subject.name} ({subject.root}; "
              f"{'bundled' if subject.bundled else 'recorded footage'})")
    print(f"{'method':<18} {'family':<9} {'config':<17} description (preset {args.preset})")
    for r in rows:
        desc = r["description"].split(". ")[0].rstrip(".")
        if r["variant"]:
            desc = f"variant {r['variant']} (an ablation row of Tables III/IV)"
        print(f"{r['name']:<18} {r['family']:<9} {r['config_hash']:<17} {desc[:110]}")
    return 0
