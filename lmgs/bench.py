"""``lmgs-eval bench model``: per-frame cost of the neural parts on this machine.

Times, per frame at inference: the audio path (Audio Encoder on the frame's 8-frame context +
attention smoother) and the deformation of N canonical Gaussians (landmark tri-plane
features, Spatial Enhancement, region attention, offset MLP, Landmark Compensation) with the
canonical points' tri-plane features cached, as they are constant at inference. Also the
tri-plane encoder's forward+backward on N points (a training step's share). Medians of
repeated runs, measured in this run, never compared with stored figures.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

HELP = "per-frame audio + deformation cost of the model's neural parts (5k / 10k Gaussians)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--points", type=int, nargs="+", default=[5000, 10000], help="Gaussian counts")
    p.add_argument("--repeats", type=int, default=30, help="timed runs per row (median reported)")
    p.add_argument("--preset", choices=["quick", "paper"], default="quick", help="config preset")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")


def _median_ms(fn, repeats: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def run(args: argparse.Namespace) -> dict:
    from lmgs.audio import AudioNet
    from lmgs.config import AudioConfig, DeformConfig, GuidanceConfig, TriplaneConfig
    from lmgs.deform import DeformNet

    if args.threads:
        torch.set_num_threads(args.threads)
    preset = args.preset
    acfg = getattr(AudioConfig, preset)()
    tcfg, gcfg, dcfg = getattr(TriplaneConfig, preset)(), getattr(GuidanceConfig, preset)(), getattr(DeformConfig, preset)()
    torch.manual_seed(0)
    C, W = (80, 16) if acfg.frontend in ("logmel", "mfcc") else (1024, 2)
    audio = AudioNet(C, W, acfg).eval()
    feats = torch.randn(100, W, C)
    idx = torch.tensor([50])
    rows = []
    with torch.no_grad():
        t_audio = _median_ms(lambda: audio(feats, idx), args.repeats)
    for n in args.points:
        xyz = torch.rand(n, 3) * 2 - 1
        lms = torch.rand(68, 3) * 2 - 1
        for name, g in (("full (SE+LC)", gcfg), ("no SE/LC", GuidanceConfig(se=False, lc=False))):
            face = DeformNet(acfg.dim, dcfg, tcfg, g).eval()
            with torch.no_grad():
                cached = face.encode_points(xyz)
                fa = audio(feats, idx)[0]
                t_def = _median_ms(lambda: face(xyz, fa, lms, blink=0.3, point_features=cached), args.repeats)
            rows.append(
                {
                    "points": n,
                    "guidance": name,
                    "audio_ms": round(t_audio, 3),
                    "deform_ms": round(t_def, 3),
                    "total_ms": round(t_audio + t_def, 3),
                    "frames_per_s": round(1e3 / (t_audio + t_def), 1),
                }
            )
        enc = face.encoder

        def step():
            enc.embeddings.grad = None
            (enc(xyz) ** 2).sum().backward()

        rows.append(
            {
                "points": n,
                "guidance": "triplane fwd+bwd",
                "audio_ms": None,
                "deform_ms": round(_median_ms(step, args.repeats), 3),
                "total_ms": None,
                "frames_per_s": None,
            }
        )
    return {
        "preset": preset,
        "threads": torch.get_num_threads(),
        "triplane": f"{tcfg.n_levels} levels x {tcfg.n_features} features, table 2^{tcfg.log2_table_size}, res {tcfg.base_resolution}-{tcfg.finest_resolution}",
        "note": "inference per frame, canonical tri-plane features cached; no rasterization",
        "rows": rows,
    }
