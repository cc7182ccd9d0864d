"""``lmgs-eval bench metrics``: frames/s per metric at 256 and 512, ONNX Runtime vs eager torch LPIPS,
and (``--suite``) the whole metric suite on one method's clip against a ground truth already scored.

All figures are measured in this run on this machine; the ORT/eager ratio compares the
same network (same weights) on the same frames. The official LPIPS network's cost is timed
with random weights of its shape when torchvision's trunk is absent (the same convolutions,
so the same cost); its values are never reported.
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
from lmgs_eval.metrics.lpips import LPIPS, LPIPS_ALEX_SPEC, backend_of, build_stlpips_torch
from lmgs_eval.metrics.lpips_nets import AlexTrunk, LPIPSNet
from lmgs_eval.metrics.ort import n_threads
from lmgs_eval.metrics.sync.scorers import find_scorer
from lmgs_eval.metrics.sync.scoring import lse

HELP = "frames/s per metric (256, 512) and LPIPS ONNX Runtime vs eager torch, same run"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=None, help="frames per measurement (default 8; with --suite: the "
                   "clip's length, default 500)")
    p.add_argument("--sizes", default=None, help="comma-separated square sizes (default 256,512; with --suite: one "
                   "size, default 512)")
    p.add_argument("--suite", action="store_true",
                   help="time the whole metric suite (PSNR, SSIM, LPIPS, LMD, LSE) on one method's clip against a "
                        "ground truth scored before it, with the official LPIPS network's shape and with ST-LPIPS")


LSE_FRAMES = 50


def _clip(n: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Float ``pred, gt`` in [0, 1] of :func:`_talking_clip` (without its audio)."""
    gt, pred, _ = _talking_clip(n, size)
    return pred.astype(np.float32) / 255, gt.astype(np.float32) / 255


def _best(fn, reps: int = 2) -> float:
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return min(out)


def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(n_threads())
    if getattr(args, "suite", False):
        return run_suite(args)
    n = int(args.frames or 8)
    rows = []
    lp = LPIPS(batch=4)
    plain, _ = build_stlpips_torch(fold=False)
    dl = DlibBackend()
    alex_timing = alex_timing_lpips() if lp.spec.name != "lpips-alex" else None
    scorer, scorer_reason = find_scorer()
    per_frame_512 = {}
    for size in [int(s) for s in str(args.sizes or "256,512").split(",")]:
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
            alex_timing.distances(pred[:2], gt[:2])  # warm-up
            timings[ALEX_TIMING] = _best(lambda: alex_timing.distances(pred, gt))
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


def alex_timing_lpips() -> LPIPS:
    """The official LPIPS-alex network with random weights, as an :class:`LPIPS` metric (exported to a temp file).

    Only for timing: the network (and so its cost) is the official metric's; its values
    mean nothing and are never reported. Used when the torchvision trunk file is absent.
    """
    torch.manual_seed(0)
    net = LPIPSNet(AlexTrunk()).eval()
    with torch.no_grad():
        for lin in net.lins:
            lin.weight.abs_()  # the published heads are non-negative
    spec = LPIPS_ALEX_SPEC.with_weights(None)
    with tempfile.TemporaryDirectory() as d:  # the session keeps the graph in memory
        backend = backend_of(net, spec, "lpips-alex-timing", None, path=Path(d) / "lpips_alex_timing.onnx")
    return LPIPS(backend=backend)


def _talking_clip(n: int, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ``n``-frame uint8 ground truth (the astronaut photo, drifting), a noisy prediction and 16 kHz audio."""
    import cv2
    from skimage import data

    face = cv2.resize(data.astronaut(), (size, size), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(0)
    gt = np.empty((n, size, size, 3), np.uint8)
    pred = np.empty_like(gt)
    for i in range(n):
        gt[i] = np.roll(face, (i % 8) - 4, axis=1)
        pred[i] = np.clip(gt[i].astype(np.int16) + rng.integers(-8, 9, gt[i].shape), 0, 255)
    audio = (0.1 * rng.standard_normal(n * 640)).astype(np.float32)
    return gt, pred, audio


def run_suite(args: argparse.Namespace) -> dict:
    """The metric suite on one method's clip against a ground truth already scored, both LPIPS networks.

    For each network: the ground truth is scored first (the protocols' "Ground Truth" row; it
    fills the ground-truth caches), then the method's clip is scored and timed metric by metric.
    """
    from lmgs_eval.metrics.config import SuiteConfig
    from lmgs_eval.metrics.metric_suite import MetricSuite
    from lmgs_eval.metrics.sync.select import candidates

    n = int(args.frames or 500)
    size = int(str(args.sizes or "512").split(",")[0])
    gt, pred, audio = _talking_clip(n, size)
    sync = candidates("auto")[0]  # the default scorer alone (on noise audio auto would go on to try the next one)
    rows, totals = [], {}
    for label, make in (("lpips-alex (official shape, random weights)", alex_timing_lpips),
                        ("stlpips-alex", lambda: LPIPS("stlpips-alex"))):
        suite = MetricSuite(SuiteConfig(sync=sync))
        suite.use_lpips(make())
        t = time.perf_counter()
        suite.score(gt, gt, audio, in_sync=True)
        gt_s = time.perf_counter() - t
        res = suite.score(pred, gt, audio)
        for metric, sec in suite.timings.items():
            rows.append({"lpips_network": label, "metric": metric, "seconds": round(sec, 2),
                         "ms_per_frame": round(1000 * sec / n, 2)})
        totals[label] = {"ground_truth_pass_s": round(gt_s, 1), "method_pass_s": round(suite.timings["total"], 1),
                         "lpips_notes": [x for x in res[suite.lpips_name].notes if "cache" in x]}
        del suite
    return {"threads": n_threads(), "frames": n, "size": size, "sync_scorer": sync, "totals": totals, "rows": rows,
            "goal": "method pass <= 60 s with the official LPIPS network, <= 150 s with ST-LPIPS (500 frames, 512x512)"}
