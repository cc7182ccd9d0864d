"""``lmgs-eval bench metrics``: frames/s per metric at 256 and 512, ONNX Runtime vs eager torch LPIPS.

All figures are measured in this run on this machine; the ORT/eager ratio compares the
same network (same weights) on the same frames.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from lmgs_eval.metrics.image import psnr_per_frame, ssim_per_frame
from lmgs_eval.metrics.landmarks import DlibBackend
from lmgs_eval.metrics.lpips import LPIPS, build_stlpips_torch, export_lpips
from lmgs_eval.metrics.lpips_nets import AlexTrunk, LPIPSNet
from lmgs_eval.metrics.ort import load_session, n_threads
from lmgs_eval.metrics.sync import find_scorer, lse

HELP = "frames/s per metric (256, 512) and LPIPS ONNX Runtime vs eager torch, same run"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=8, help="frames per measurement")
    p.add_argument("--sizes", default="256,512", help="comma-separated square sizes")


LSE_FRAMES = 50


def _clip(n: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    import cv2
    from skimage import data

    face = cv2.resize(data.astronaut(), (size, size), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    rng = np.random.default_rng(0)
    gt = np.stack([np.roll(face, i % 4, axis=1) for i in range(n)])
    pred = np.clip(gt + rng.normal(0, 0.03, gt.shape), 0, 1).astype(np.float32)
    return pred, gt


def _best(fn, reps: int = 2) -> float:
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return min(out)


def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(n_threads())
    n = int(args.frames)
    rows = []
    lp = LPIPS(batch=4)
    plain, _ = build_stlpips_torch(fold=False)
    dl = DlibBackend()
    alex_timing = _alex_timing_session() if lp.spec.name != "lpips-alex" else None
    scorer, scorer_reason = find_scorer()
    per_frame_512 = {}
    for size in [int(s) for s in str(args.sizes).split(",")]:
        pred, gt = _clip(n, size)
        tp = torch.from_numpy(pred.transpose(0, 3, 1, 2).copy())
        tg = torch.from_numpy(gt.transpose(0, 3, 1, 2).copy())

        def eager(net):
            with torch.no_grad():
                for s in range(0, n, 4):
                    net(tp[s:s + 4], tg[s:s + 4])

        lp.distances(pred[:2], gt[:2])  # warm-up
        timings = {
            "psnr": _best(lambda: psnr_per_frame(pred, gt)),
            "ssim": _best(lambda: ssim_per_frame(pred, gt)),
            f"{lp.spec.name} onnxruntime": _best(lambda: lp.distances(pred, gt)),
            f"{lp.spec.name} eager torch (folded)": _best(lambda: eager(lp.backend.net), 1),
            f"{lp.spec.name} eager torch (reference)": _best(lambda: eager(plain), 1),
            "lmd landmarks (dlib, pred+gt)": _best(lambda: (dl.landmarks(pred), dl.landmarks(gt)), 1),
        }
        if alex_timing is not None:
            def alex_run():
                for s in range(0, n, 4):
                    alex_timing.run(["dist"], {"pred": tp[s:s + 4].numpy(), "gt": tg[s:s + 4].numpy()})

            alex_run()  # warm-up
            timings[ALEX_TIMING] = _best(alex_run)
        ort_t = timings[f"{lp.spec.name} onnxruntime"]
        for name, t in timings.items():
            rows.append({"size": size, "metric": name, "frames_per_s": n / t, "ms_per_frame": 1000 * t / n,
                         "ort_speedup": (t / ort_t) if "eager" in name else None})
        if size == 512:
            per_frame_512 = {k: v / n for k, v in timings.items() if "eager" not in k and k != ALEX_TIMING}
            alex_512 = timings.get(ALEX_TIMING, 0.0) / n
        if scorer is not None:
            # LSE needs whole 5-frame windows and the +-15 offset search: time it on a longer clip
            m = max(n, LSE_FRAMES)
            frames = gt[np.arange(m) % n]
            audio = (0.1 * np.random.default_rng(1).standard_normal(m * 640)).astype(np.float32)
            # best of 2: the first call of a process also loads the dlib models and the scorer session
            t = _best(lambda: lse(frames, audio, scorer=scorer), 2)
            name = f"lse ({scorer.name}, detect+crop+embed)"
            rows.append({"size": size, "metric": name, "frames_per_s": m / t, "ms_per_frame": 1000 * t / m,
                         "ort_speedup": None})
            if size == 512:
                per_frame_512[name] = t / m
    out = {"threads": n_threads(), "frames": n, "lpips_network": lp.spec.name, "rows": rows}
    if per_frame_512:
        total = sum(per_frame_512.values())
        lmd_key = "lmd landmarks (dlib, pred+gt)"
        out["suite_500x512_estimate_s"] = round(500 * total, 1)
        out["suite_estimate_note"] = ("PSNR+SSIM+LPIPS(ORT)+LMD" + ("+LSE" if scorer is not None else "")
                                      + " per-frame times x 500, extrapolated"
                                      + ("" if scorer is not None else f" (LSE excluded: {scorer_reason})"))
        # ground-truth landmarks are cached by content (cached_landmarks): a re-scored subject pays pred only
        out["suite_500x512_gt_cached_estimate_s"] = round(500 * (total - per_frame_512.get(lmd_key, 0.0) / 2), 1)
        if alex_timing is not None:
            lp_key = f"{lp.spec.name} onnxruntime"
            swap = total - per_frame_512[lp_key] + alex_512
            out["suite_500x512_lpips_alex_estimate_s"] = round(500 * swap, 1)
            out["suite_500x512_lpips_alex_gt_cached_estimate_s"] = round(
                500 * (swap - per_frame_512.get(lmd_key, 0.0) / 2), 1)
    return out


ALEX_TIMING = "lpips-alex onnxruntime (timing only: same network, random weights; official trunk not here)"


def _alex_timing_session():
    """The official LPIPS-alex graph with random weights, exported to a temporary file.

    Only for timing: the network (and so its cost) is the official metric's; its values
    mean nothing and are never reported. Used when the torchvision trunk file is absent.
    """
    torch.manual_seed(0)
    net = LPIPSNet(AlexTrunk()).eval()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "lpips_alex_timing.onnx"
        export_lpips(net, path)
        return load_session(path)
