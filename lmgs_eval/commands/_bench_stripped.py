"""``lmgs-eval bench stripped``: one method on a bundled subject, and on its copy stripped to a plain folder.

The bundled subject carries what its generator knows (``lms3d.npy``, rendered ``depth/`` and
``normal/`` maps). Its copy holds only what the field's preprocessing leaves
(:data:`complete.PLAIN_LAYOUT`), and reading it derives 3D landmarks and a head prior
(:mod:`complete`). The method is built once from the full subject (same preset, ``--set``
changes, seed and Gaussian budget: one config hash), trained afresh on each folder's
training split in a temporary folder, rendered from the test split's audio and scored by
the run's metric suite, as ``lmgs-eval self`` runs it. The figures are printed side by side
with ``stripped - full``; both ground truths are the same frames (checked).

The defaults are the full-size run: the bundled 60 s at 256 px, the ``quick`` preset (two
trainings of 4-10 minutes each on 2 cores, see ``docs/benchmark.md``). ``--seconds``,
``--size`` and ``--set train.*=N`` make it smaller. Records go to a temporary store unless
``--results`` keeps them.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

IN_ALL = False  # two trainings at its defaults, not a speed benchmark: `bench all` leaves it out
HELP = "a method trained on a bundled subject and on its copy stripped to a plain processed folder, side by side"

# record metric -> (label, format); lower is better for all but PSNR, SSIM and LSE-C
FIGURES = (("psnr", "PSNR dB"), ("ssim", "SSIM"), ("lpips", "LPIPS"), ("lmd", "LMD px"), ("lse_d", "LSE-D"), ("lse_c", "LSE-C"))
COSTS = (("prepare_s", "read + clips, s"), ("train_seconds", "train, s"),
         ("train_others_cpu_share", "others' CPU share while training"), ("train_cpu_s", "train + render + score, CPU s"),
         ("fps", "render FPS"), ("n_gaussians", "Gaussians"), ("model_mb", "model MB"), ("peak_mb", "peak MB"),
         ("folder_mb", "folder MB"))


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lmgs_eval.commands._sync import add_sync_argument

    p.add_argument("--subject", default="astronaut", help="bundled subject (default astronaut)")
    p.add_argument("--size", type=int, default=256, help="frame size of the bundled subject (default 256, its full size)")
    p.add_argument("--seconds", type=float, default=60.0, help="length of the bundled subject (default 60, its full length)")
    p.add_argument("--method", default="lmgs", help="method trained on both folders (default lmgs)")
    p.add_argument("--preset", default="quick", choices=["quick", "paper"], help="training preset (default quick)")
    p.add_argument("--seed", type=int, default=0, help="seed of both trainings (default 0)")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", default=[],
                   help="config change for both trainings, as `lmgs-eval self --set` (e.g. train.dynamic_steps=600)")
    p.add_argument("--data-root", help="where the bundled subject is built (default: $LMGS_DATA or ~/.cache/lmgs/data)")
    p.add_argument("--results", help="keep the two records (and renders) in this store (default: a temporary one)")
    p.add_argument("--device", help="cpu, cuda, cuda:1 (default: CUDA when present)")
    add_sync_argument(p)


def _cpu() -> float:
    """CPU seconds of this process and of its finished worker processes."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def _folder_mb(root: Path) -> float:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 2**20


def _prepare(root: Path):
    """Read a folder and load its clips (for the plain folder: the depth / normal priors are ray-cast here)."""
    from lmgs_eval.convert import driving_from_subject, subject_to_clip
    from lmgs_eval.data.layout import read_subject

    t0 = time.perf_counter()
    s = read_subject(root)
    train, test = subject_to_clip(s, s.train_ids), subject_to_clip(s, s.test_ids)
    return {"subject": s, "train": train, "test": test, "driving": driving_from_subject(s, s.test_ids, test),
            "prepare_s": time.perf_counter() - t0}


def _value(rec: dict, key: str):
    v = (rec["metrics"].get(key) or {}).get("value")
    return float(v) if isinstance(v, (int, float)) and v == v else None


def _why(full: dict, plain: dict, key: str) -> str:
    """Why a figure is missing: the metric's first ``unavailable`` flag (LMD needs a face dlib finds, LSE 5-frame windows)."""
    for rec in (full, plain):
        flags = (rec["metrics"].get(key) or {}).get("flags") or []
        for f in flags:
            if f.startswith("unavailable:"):
                return f
    return "not scored"


def _diff(a, b):
    return None if a is None or b is None else b - a


def run(args: argparse.Namespace) -> dict:
    import numpy as np

    from lmgs_eval.commands._common import check_seeds, parse_overrides
    from lmgs_eval.data.ingest.complete import derive, strip_to_plain
    from lmgs_eval.data.registry import BundledSpec, ensure_bundled
    from lmgs_eval.errors import UserError
    from lmgs_eval.metrics.metric_suite import MetricSuite
    from lmgs_eval.runner import RunConfig, build_method, fit_render_score, log

    spec = BundledSpec.parse(args.subject)
    if spec is None or spec.name != args.subject:
        raise UserError(f"--subject {args.subject}: a bundled subject name (astronaut, hopper); --size and --seconds size it")
    spec = BundledSpec(args.subject, args.size, args.seconds)
    check_seeds([args.seed])
    t0 = time.perf_counter()
    full_root = ensure_bundled(spec, args.data_root, progress=False)
    build_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="lmgs-bench-stripped-") as tmp:
        tmp = Path(tmp)
        results = Path(args.results) if args.results else tmp / "results"
        plain_root = strip_to_plain(full_root, tmp / f"{spec.folder}-plain")
        cfg = RunConfig(subject=str(full_root), methods=(args.method,), preset=args.preset, seeds=(args.seed,), results=results,
                        device=args.device, progress=False, method_options=parse_overrides(args.overrides),
                        suite=MetricSuite(sync=getattr(args, "sync", None) or "auto"))
        runs = {"full": _prepare(full_root), "stripped": _prepare(plain_root)}
        full, plain = runs["full"], runs["stripped"]
        if not np.array_equal(full["test"].frames, plain["test"].frames):
            raise RuntimeError(f"{plain_root}: the stripped copy's test frames differ from {full_root}'s")
        s = plain["subject"]
        # what the derivation itself costs (the read above may have found it cached)
        t0 = time.perf_counter()
        derive(plain_root, s.landmarks, s.c2w, s.focal, s.cx, s.cy, cache_dir=tmp / "derived")
        derive_s = time.perf_counter() - t0
        hashes = set()
        for variant, r in runs.items():
            # one config for both: the full subject's (its Gaussian budget, where it has its own)
            method = build_method(cfg, args.method, full["subject"])
            hashes.add(method.describe().config_hash)
            log(f"bench stripped: {args.method} on the {variant} folder ({r['subject'].root})")
            c0 = _cpu()
            r["record"] = fit_render_score(cfg, method, r["subject"], args.seed, r["train"], r["driving"], r["test"].frames,
                                           f"renders/bench-stripped/{variant}-{args.method}-seed{args.seed}.mp4",
                                           workdir=tmp / "models" / variant)
            r["train_cpu_s"] = _cpu() - c0
            r["folder_mb"] = _folder_mb(r["subject"].root)
        if len(hashes) != 1:
            raise RuntimeError(f"{args.method}: two configs ({', '.join(sorted(hashes))}) where one was built twice")
        rows = []
        for key, label in FIGURES:
            a, b = _value(full["record"], key), _value(plain["record"], key)
            why = "" if a is not None and b is not None else _why(full["record"], plain["record"], key)
            rows.append({"figure": label, "full": a, "stripped": b, "stripped - full": _diff(a, b), "note": why})
        for key, label in COSTS:
            a, b = (r.get(key, r["record"]["cost"].get(key)) for r in (full, plain))
            rows.append({"figure": label, "full": a, "stripped": b, "stripped - full": _diff(a, b), "note": ""})
        rec = plain["record"]
        out = {
            "subject": f"{spec.folder} ({spec.size} px, {spec.seconds:g} s, bundled; built in {build_s:.1f} s)",
            "full": str(full_root),
            "stripped": f"{plain_root} (removed at the end)",
            "method": f"{args.method} (preset {args.preset}, config {hashes.pop()}, seed {args.seed}"
                      + (f", --set {' '.join(args.overrides)}" if args.overrides else "") + ")",
            "frames": f"{len(full['train'])} train / {len(full['test'])} test, {full['subject'].width} px",
            "derived": next((n for n in rec["notes"] if "derived 3D landmarks" in n), "nothing derived"),
            "derive_s": round(derive_s, 3),
            "lpips": (rec["metrics"].get("lpips") or {}).get("backend"),
            "cores": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "results": str(results) if args.results else "temporary (--results keeps the records)",
            "rows": rows,
        }
    return out
