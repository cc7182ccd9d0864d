"""Arguments shared by the protocol commands (self, cross, stress)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def add_run_arguments(p: argparse.ArgumentParser, default_methods: tuple[str, ...] = ("lmgs",)) -> None:
    p.add_argument("--subject", default="astronaut", help="bundled name, folder name under the data root, or a path (default astronaut)")
    p.add_argument("--method", dest="methods", action="append", metavar="M",
                   help=f"method to run (repeatable; default {', '.join(default_methods)}; `all`: every method of the field, "
                        "the ablation variants aside; `lmgs-eval methods` lists them)")
    p.add_argument("--preset", default="quick", choices=["quick", "paper"], help="training preset (quick: CPU minutes)")
    p.add_argument("--seed", dest="seeds", type=int, action="append", metavar="N", help="seed (repeatable; default 0)")
    p.add_argument("--results", default="results", help="results store folder (default ./results)")
    p.add_argument("--data-root", help="folder of subjects (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--device", help="cpu, cuda, cuda:1 (default: CUDA when present)")
    p.add_argument("--renders", help="for --method external:NAME: the video or frame folder it rendered")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", default=[],
                   help="override a config value of the method, dotted (e.g. train.dynamic_steps=4000, guidance.theta=0.4); "
                        "the config hash changes with it")
    p.add_argument("--force", action="store_true", help="redo runs already in the results store")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    from lmgs_eval.commands._sync import add_sync_argument

    add_sync_argument(p)
    p.set_defaults(_default_methods=default_methods)


def run_config(args: argparse.Namespace):
    from baselines.protocol import field_methods, list_methods
    from lmgs.device import choose_device
    from lmgs_eval.commands._sync import suite
    from lmgs_eval.runner import RunConfig

    methods = tuple(args.methods or args._default_methods)
    if "all" in methods:  # in place, the rest kept once in order
        methods = tuple(dict.fromkeys(m for x in methods for m in (field_methods() if x == "all" else [x])))
    known = list_methods()
    for m in methods:
        if not m.startswith("external:") and m not in known:
            from lmgs_eval.errors import UserError

            raise UserError(f"unknown method '{m}'; known: {', '.join(known)}")
    check_seeds(args.seeds or ())
    if args.device is not None or os.environ.get("LMGS_DEVICE"):
        choose_device(args.device)  # a device this machine lacks stops the run before any work
    return RunConfig(
        method_options=parse_overrides(args.overrides),
        subject=args.subject,
        methods=methods,
        preset=args.preset,
        seeds=tuple(args.seeds or (0,)),
        results=Path(args.results),
        data_root=args.data_root,
        device=args.device,
        progress=not args.no_progress,
        renders=args.renders,
        force=args.force,
        suite=suite(args),
    )


def check_seeds(seeds) -> None:
    """Seeds numpy and torch both accept: integers in [0, 2**32 - 1]."""
    from lmgs_eval.errors import UserError

    for s in seeds:
        if not 0 <= s < 2 ** 32:
            raise UserError(f"--seed {s}: a seed is an integer from 0 to {2 ** 32 - 1}")


def print_rows(records: list) -> None:
    """The records just made, as a small table on stdout (§: FPS timed on a busy host)."""
    from lmgs_eval.report.cells import BUSY_NOTE, busy_text, timed_busy, trained_busy
    from lmgs_eval.report.table_model import BUSY, BUSY_SHARE

    cols = [("psnr", "PSNR↑", "{:.2f}"), ("lpips", "LPIPS↓", "{:.4f}"), ("lmd", "LMD↓", "{:.2f}"),
            ("lse_d", "LSE-D↓", "{:.3f}"), ("lse_c", "LSE-C↑", "{:.3f}")]
    if any("lpips_custom" in r.metrics for r in records):  # a trunk that is not torchvision's: its own column
        cols.insert(2, ("lpips_custom", "LPIPS*↓", "{:.4f}"))
    head = f"{'method':<26} {'clip':<6} {'seed':>4} " + " ".join(f"{h:>8}" for _, h, _ in cols) + f" {'FPS':>7} {'train s':>8} {'Gauss.':>7} {'MB':>6}"
    print(head)
    for r in records:
        vals = []
        for key, _, fmt in cols:
            v = r.value(key)
            vals.append(f"{fmt.format(v):>8}" if isinstance(v, (int, float)) and v == v else f"{'n/a':>8}")
        c = r.cost

        def f(v, fmt):
            return fmt.format(v) if isinstance(v, (int, float)) else "-"

        fps = f(c.fps, "{:.1f}") + (BUSY if timed_busy(c) else "")
        train = f(c.train_seconds, "{:.0f}") + (BUSY if trained_busy(c) else "")
        print(f"{r.method.display_name[:26]:<26} {r.protocol.clip[:6]:<6} {r.seed:>4} " + " ".join(vals)
              + f" {fps:>7} {train:>8} {f(c.n_gaussians, '{:d}'):>7} {f(c.model_mb, '{:.2f}'):>6}")
    busy = [busy_text(r.cost) for r in records if timed_busy(r.cost)]
    if busy:
        print(f"  {BUSY_NOTE} ({'; '.join(dict.fromkeys(busy))}): a quiet host renders faster")
    if any(trained_busy(r.cost) for r in records):
        print(f"  {BUSY} train s: trained while other processes took more than {BUSY_SHARE:.0%} of the host's CPU "
              "(cost.train_others_cpu_share): a quiet host trains faster")
    # a metric that could not be computed on a clip: n/a in the table, its reason here (lse_d/lse_c/av_offset once)
    for r in records:
        seen = set()
        for k, v in r.metrics.items():
            why = next((f[len("unavailable: "):] for f in v.flags if f.startswith("unavailable: ")), None)
            name = "lse" if k in ("lse_d", "lse_c", "av_offset") else k
            if why is not None and name not in seen:
                seen.add(name)
                print(f"  {r.method.display_name}/{r.protocol.clip} seed {r.seed}: {name} unavailable: {why}")
    backends = sorted({f"{k}: {v.backend}" + (f" (stand-in: {v.standin})" if v.standin else "")
                       for r in records for k, v in r.metrics.items() if k in ("lpips", "lpips_custom", "lse_d", "lmd")})
    for b in backends:
        print(f"  {b}")


def parse_overrides(items: list[str]) -> dict:
    """``["a.b=1", "c=true"]`` -> ``{"overrides": {"a.b": 1, "c": True}}`` (JSON values, else strings)."""
    import json

    from lmgs_eval.errors import UserError

    out = {}
    for item in items or []:
        if "=" not in item:
            raise UserError(f"--set {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return {"overrides": out} if out else {}
