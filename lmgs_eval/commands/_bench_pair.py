"""One method trained on a bundled subject and on a second folder of the same footage, side by side.

Shared by ``bench stripped`` (the second folder is the subject stripped to a plain processed
folder) and ``bench ingested`` (the second folder is the ingest of the subject's raw video).
The method is built from the bundled subject (preset, ``--set`` changes, seed and Gaussian
budget: one config; a method with a geometry term weighs a folder's derived depth / normal priors
as it would on that folder alone, and then each folder has its own hash), trained afresh on each
folder's training split in a temporary folder, rendered from the test split's audio and scored by
the run's metric suite, as ``lmgs-eval self`` runs it, each against its own folder's ground truth.
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

# record metric -> label; lower is better for all but PSNR, SSIM and LSE-C
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


def cpu_seconds() -> float:
    """CPU seconds of this process and of its finished worker processes."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def folder_mb(root: Path) -> float:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 2**20


def bundled_spec(args: argparse.Namespace):
    """The bundled subject ``--subject`` at ``--size`` / ``--seconds`` (a UserError for any other name)."""
    from lmgs_eval.data.bundled_spec import BundledSpec
    from lmgs_eval.errors import UserError

    spec = BundledSpec.parse(args.subject)
    if spec is None or spec.name != args.subject:
        raise UserError(f"--subject {args.subject}: a bundled subject name (astronaut, hopper); --size and --seconds size it")
    return BundledSpec(args.subject, args.size, args.seconds)


def prepare(root: Path) -> dict:
    """Read a folder and load its clips (for a plain folder the depth / normal priors are ray-cast here)."""
    from lmgs_eval.convert import driving_from_clip, subject_to_clip
    from lmgs_eval.data.layout import read_subject

    t0 = time.perf_counter()
    s = read_subject(root)
    train, test = subject_to_clip(s, s.train_ids), subject_to_clip(s, s.test_ids)
    return {"subject": s, "train": train, "test": test, "driving": driving_from_clip(test),
            "prepare_s": time.perf_counter() - t0}


def value(rec, key: str):
    v = rec.value(key)
    return float(v) if isinstance(v, (int, float)) and v == v else None


def why_missing(a, b, key: str) -> str:
    """Why a figure is missing: the metric's first ``unavailable`` flag (LMD needs a face dlib finds, LSE 5-frame windows)."""
    for rec in (a, b):
        for f in getattr(rec.metrics.get(key), "flags", ()):
            if f.startswith("unavailable:"):
                return f
    return "not scored"


def diff(a, b):
    return None if a is None or b is None else b - a


def train_both(args: argparse.Namespace, runs: dict[str, dict], tmp: Path, results: Path, tag: str) -> tuple[object, str]:
    """Fit, render and score ``args.method`` on each prepared folder of ``runs`` (``{label: prepare(...)}``,
    the bundled one first); fills in each run's ``record``, ``method``, ``train_cpu_s`` and ``folder_mb``.
    Returns the run config and its config hash: one, or one per folder (``HASH (label), ...``) where a
    folder's derived depth / normal priors are weighed as such (the configs otherwise the same)."""
    from lmgs.config import config_hash
    from lmgs.presets import DERIVED_PRIOR_KEYS
    from lmgs_eval.commands._common import check_seeds, parse_overrides
    from lmgs_eval.commands._sync import suite
    from lmgs_eval.results.records import RunId
    from lmgs_eval.runner import RunConfig, build_method, fit_render_score, log

    check_seeds([args.seed])
    first = next(iter(runs.values()))
    cfg = RunConfig(subject=str(first["subject"].root), methods=(args.method,), preset=args.preset, seeds=(args.seed,),
                    results=results, device=args.device, progress=False, method_options=parse_overrides(args.overrides),
                    suite=suite(args))
    hashes, shared = {}, set()
    for label, r in runs.items():
        # one config for every folder: the bundled subject's (its Gaussian budget, where it has its own); a
        # method with a geometry term weighs a folder's derived priors as it would on that folder alone
        method = build_method(cfg, args.method, first["subject"], priors_from=r["subject"])
        info = method.describe()
        hashes[label] = info.config_hash
        train = info.config.get("train")  # what may differ between folders: the weights on derived priors
        shared.add(config_hash({**info.config, "train": {k: v for k, v in train.items() if k not in DERIVED_PRIOR_KEYS}}
                               if isinstance(train, dict) else info.config))
        log(f"bench {tag}: {args.method} on the {label} folder ({r['subject'].root})")
        c0 = cpu_seconds()
        run = RunId(r["subject"], info, args.seed)
        r["record"] = fit_render_score(cfg, method, run, r["train"], r["driving"], r["test"].frames,
                                       f"renders/bench-{tag}/{label}-{args.method}-seed{args.seed}.mp4",
                                       workdir=tmp / "models" / label)
        r["method"] = method
        r["train_cpu_s"] = cpu_seconds() - c0
        r["folder_mb"] = folder_mb(r["subject"].root)
    if len(shared) != 1:
        raise RuntimeError(f"{args.method}: two configs ({', '.join(sorted(set(hashes.values())))}) where one was built twice")
    if len(set(hashes.values())) == 1:
        return cfg, next(iter(hashes.values()))
    return cfg, ", ".join(f"{h} ({label})" for label, h in hashes.items())


def rows(a: dict, b: dict, names: tuple[str, str]) -> list[dict]:
    """The figures and costs of two runs side by side, with ``b - a``."""
    la, lb = names
    out = []
    for key, label in FIGURES:
        x, y = value(a["record"], key), value(b["record"], key)
        why = "" if x is not None and y is not None else why_missing(a["record"], b["record"], key)
        out.append({"figure": label, la: x, lb: y, f"{lb} - {la}": diff(x, y), "note": why})
    for key, label in COSTS:
        x, y = (r.get(key, getattr(r["record"].cost, key, None)) for r in (a, b))
        out.append({"figure": label, la: x, lb: y, f"{lb} - {la}": diff(x, y), "note": ""})
    return out
