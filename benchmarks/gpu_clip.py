"""Train and render lmgs on a machine that has no toolkit data: a clip packed here, timed there.

A GPU machine may have torch and nothing of the toolkit's data (no bundled subjects, no video
libraries, a small upload). ``pack`` writes one ``.npz`` from a subject (its frames, plates
and masks as WebP / packed bits, everything else as arrays); ``train`` trains lmgs on it on
any device, renders the test frames, and writes a JSON of the times and the mean PSNR:

    python benchmarks/gpu_clip.py pack --subject astronaut --size 512 --seconds 10 --out clip.npz
    python benchmarks/gpu_clip.py train clip.npz --device cuda --json out.json

``train`` imports only the model library (``lmgs``), numpy and Pillow. ``frames_sha`` in its
JSON is the hash of the decoded training frames: equal on two machines, the same clip.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

IMAGES = ("frames", "backgrounds")
MASKS = ("mouth_masks", "head_masks")
ARRAYS = ("w2c", "audio", "blink", "landmarks2d", "landmarks3d", "depth", "normal")


def _webp(stack: np.ndarray, quality: int) -> np.ndarray:
    from PIL import Image

    out = []
    for im in stack:
        buf = io.BytesIO()
        Image.fromarray(im).save(buf, format="WEBP", quality=quality, method=4)
        out.append(np.frombuffer(buf.getvalue(), np.uint8))
    lengths = np.array([len(b) for b in out], np.int64)
    return np.concatenate(out), lengths


def _unwebp(blob: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    from PIL import Image

    ends = np.cumsum(lengths)
    return np.stack([np.asarray(Image.open(io.BytesIO(blob[e - n:e].tobytes())).convert("RGB"))
                     for n, e in zip(lengths, ends)])


def _pack_clip(clip, prefix: str, quality: int, driving_only: bool = False) -> dict:
    """Arrays of a clip; ``driving_only`` keeps what rendering it needs (and its frames, to score)."""
    out = {}
    for name in IMAGES:
        out[f"{prefix}{name}"], out[f"{prefix}{name}_len"] = _webp(getattr(clip, name), quality)
    for name in () if driving_only else MASKS:
        m = getattr(clip, name)
        if m is not None:
            out[f"{prefix}{name}"] = np.packbits(m, axis=-1)
            out[f"{prefix}{name}_shape"] = np.array(m.shape)
    for name in ("w2c", "audio", "blink") if driving_only else ARRAYS:
        a = getattr(clip, name)
        if name == "normal" and a is not None:  # camera-space normals x127 as an 8-bit image (lossy, like the frames)
            out[f"{prefix}normal_img"], out[f"{prefix}normal_img_len"] = _webp((a.astype(np.int16) + 128).astype(
                np.uint8), quality)
        elif a is not None:
            out[f"{prefix}{name}"] = a
    for k, v in (clip.audio_features or {}).items():
        out[f"{prefix}feat_{k}"] = v
    out[f"{prefix}intrinsics"] = np.array([clip.focal, clip.cx, clip.cy, clip.fps, clip.sample_rate], np.float64)
    return out


def _unpack_clip(z, prefix: str):
    from lmgs.types import TrainingClip

    kw = {name: _unwebp(z[f"{prefix}{name}"], z[f"{prefix}{name}_len"]) for name in IMAGES}
    for name in MASKS:
        if f"{prefix}{name}" in z:
            shape = tuple(z[f"{prefix}{name}_shape"])
            kw[name] = np.unpackbits(z[f"{prefix}{name}"], axis=-1, count=shape[-1]).astype(bool)
    for name in ARRAYS:
        if f"{prefix}{name}" in z:
            kw[name] = z[f"{prefix}{name}"]
    if f"{prefix}normal_img" in z:
        kw["normal"] = (_unwebp(z[f"{prefix}normal_img"], z[f"{prefix}normal_img_len"]).astype(np.int16) - 128).astype(
            np.int8)
    feats = {k[len(prefix) + 5:]: z[k] for k in z.files if k.startswith(f"{prefix}feat_")}
    focal, cx, cy, fps, sr = z[f"{prefix}intrinsics"]
    return TrainingClip(focal=float(focal), cx=float(cx), cy=float(cy), fps=int(fps), sample_rate=int(sr),
                        audio_features=feats or None, **kw)


def pack(args) -> None:
    from lmgs_eval.convert import subject_to_clip
    from lmgs_eval.data.registry import find_subject

    subject = find_subject(f"{args.subject}-{args.size}px-{args.seconds:g}s")
    train_ids = subject.train_ids[::args.every]
    train = subject_to_clip(subject, train_ids)
    test = subject_to_clip(subject, subject.test_ids)
    arrays = {**_pack_clip(train, "train_", args.quality), **_pack_clip(test, "test_", args.quality, driving_only=True)}
    arrays["budget_density"] = np.array(subject.budget_density or np.nan)
    np.savez_compressed(args.out, **arrays)
    print(f"{args.out}: {Path(args.out).stat().st_size / 2**20:.1f} MiB, {len(train_ids)} training and "
          f"{len(subject.test_ids)} test frames")


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def train(args) -> None:
    import tempfile

    import torch

    from lmgs.config import override
    from lmgs.presets import preset as make_preset
    from lmgs.train import fit
    from lmgs.types import DrivingAudio

    t0 = time.perf_counter()
    z = np.load(args.clip)
    train_clip, test_clip = _unpack_clip(z, "train_"), _unpack_clip(z, "test_")
    load_s = time.perf_counter() - t0
    cfg = make_preset(args.preset)
    sets = {} if np.isnan(z["budget_density"]) else {"train.budget_density": float(z["budget_density"])}
    for item in args.set:
        key, value = item.split("=", 1)
        try:
            sets[key] = json.loads(value)
        except json.JSONDecodeError:
            sets[key] = value
    cfg = override(cfg, sets)
    dev = torch.device(args.device)
    prof = None
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
        prof = profile(activities=acts)
        prof.__enter__()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        model, report = fit(train_clip, cfg, seed=args.seed, workdir=Path(work), progress=args.progress,
                            device=args.device)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    fit_s = time.perf_counter() - t0
    if prof is not None:
        prof.__exit__(None, None, None)
        ka = prof.key_averages()
        tables = [ka.table(sort_by=key, row_limit=40) for key in
                  (("self_cuda_time_total", "self_cpu_time_total") if dev.type == "cuda" else ("self_cpu_time_total",))]
        Path(args.profile).write_text("\n\n".join(tables) + "\n")
    driving = DrivingAudio(audio=test_clip.audio, w2c=test_clip.w2c, backgrounds=test_clip.backgrounds,
                           blink=test_clip.blink, audio_features=test_clip.audio_features)
    model.render(driving)  # warm-up
    t0 = time.perf_counter()
    frames = model.render(driving)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    render_s = time.perf_counter() - t0
    from lmgs.render.rasterize import _choose_backend

    res = {
        "backend_auto": _choose_backend("auto", dev),
        "device": dev.type, "gpu": torch.cuda.get_device_name() if dev.type == "cuda" else platform.processor(),
        "torch": torch.__version__, "threads": torch.get_num_threads(),
        "rasterizer": args.backend_note, "train_frames": len(train_clip.frames), "test_frames": len(frames),
        "frames_sha": hashlib.sha256(train_clip.frames.tobytes()).hexdigest()[:16], "load_s": load_s,
        "fit_s": fit_s, "fit_report_s": report.seconds, "steps": report.steps,
        "render_s": render_s, "render_fps": len(frames) / render_s,
        "psnr_mean_of_frames": float(np.mean([_psnr(f, g) for f, g in zip(frames, test_clip.frames)])),
        "n_gaussians": int(getattr(report, "n_gaussians", 0) or 0), "set": sets,
        "curve_seconds": [(row["step"], row["stage"], round(row["seconds"], 2)) for row in report.curve],
    }
    text = json.dumps(res, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack", help="a subject's clip into one .npz (run where the toolkit's data is)")
    a.add_argument("--subject", default="astronaut")
    a.add_argument("--size", type=int, default=512)
    a.add_argument("--seconds", type=float, default=10)
    a.add_argument("--every", type=int, default=2, help="keep every n-th training frame (default 2)")
    a.add_argument("--quality", type=int, default=90, help="WebP quality of frames and plates")
    a.add_argument("--out", required=True)
    b = sub.add_parser("train", help="train lmgs on a packed clip, render its test frames, time both")
    b.add_argument("clip")
    b.add_argument("--device", default="cuda" if "cuda" in sys.argv else "cpu")
    b.add_argument("--preset", default="quick")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--set", action="append", default=[], help="config override KEY=VALUE (repeatable)")
    b.add_argument("--backend-note", default="auto", help="what rasterized, for the JSON")
    b.add_argument("--json")
    b.add_argument("--progress", action="store_true", help="the training's progress bar on standard error")
    b.add_argument("--profile", help="profile the training with torch.profiler; its per-operator tables to this file")
    args = p.parse_args(argv)
    pack(args) if args.cmd == "pack" else train(args)


if __name__ == "__main__":
    main()
