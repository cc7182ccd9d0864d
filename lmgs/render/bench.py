"""``lmgs-eval bench raster``: the fast CPU rasterizer and the pure-torch anchor side by side
(and gsplat on the same scenes when a CUDA device and gsplat are present).

Each row is measured in a fresh worker process (``python -m lmgs.render.bench --worker``)
so that its peak memory is its own: ``peak_mb`` is the growth of the process's peak
resident set (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) during the first
forward+backward of the row's scene, over the level after building the scene and a tiny
warm-up render (which loads the numba cache). Times are medians of repeated runs after
that; ``fwd_bwd_ms`` is forward plus ``backward()`` of a sum over every output image, and
``fwd_nograd_ms`` the forward under ``torch.no_grad()``, and ``fwd_rgb_ms`` that forward with
``render_mode="RGB"`` (colour and alpha only: how a trained model renders).

``--threads 1,2,4,8,16`` measures the thread scaling table instead (:mod:`lmgs.render.bench_scaling`).
``python -m lmgs.render.bench`` runs the benchmark without ``lmgs-eval``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time

from lmgs.render.bench_scaling import SHORT_SPIN, measure_scaling, scaling, scaling_text, thread_counts
from lmgs.render.bench_scene import FAST, head_scene, on_device, worker_row

HELP = "Gaussian rasterizer: numba fast path vs the pure-torch tiled anchor (fwd, fwd+bwd, peak memory)"

ANCHOR = "torch"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="256x256 with 10k Gaussians only, fewer repeats")
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 512], help="square image sizes (default 256 512)")
    p.add_argument("--counts", type=int, nargs="+", default=[10_000, 50_000], help="Gaussian counts (default 10k 50k)")
    p.add_argument("--repeats", type=int, default=7, help="timed repeats of the fast path (anchor: 2)")
    p.add_argument("--no-anchor", action="store_true", help="skip the (slow) pure-torch anchor")
    p.add_argument("--threads", type=thread_counts, default=None, metavar="N,N,...",
                   help="the thread scaling table instead of the backend rows: numba fwd and fwd+bwd (kernels and "
                        "the rest) with numba and torch on each thread count, e.g. 1,2,4,8,16 (counts above the "
                        "cores run too, marked oversubscribed)")
    p.add_argument("--wait-too", action="store_true",
                   help="with --threads: the largest count twice more, with the OpenMP pool spinning between parallel "
                        "regions (OMP_WAIT_POLICY=ACTIVE) and spinning about 0.2 ms before it sleeps "
                        f"(GOMP_SPINCOUNT={SHORT_SPIN}), against lmgs's default of sleeping at once (PASSIVE)")


def _measure(backend: str, res: int, n: int, repeats: int, device: str = "cpu") -> dict:
    """One row, in this process (called in the worker). On CUDA each timed call ends with a
    device synchronisation and ``peak_mb`` is the growth of the allocator's peak."""
    import torch

    from lmgs.render import rasterize

    cuda = device != "cpu"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    params, cam = on_device(*head_scene(n, res), device)
    bg = torch.tensor([0.2, 0.3, 0.4], device=device)
    tiny, tiny_cam = on_device(*head_scene(64, 32, seed=1), device)

    def fwd(p, c):
        return rasterize(*p, c, bg, backend=backend)

    def fwd_bwd(p, c):
        r = fwd(p, c)
        (r.rgb.sum() + r.alpha.sum() + r.depth.sum() + r.normal.sum()).backward()
        for t in p:
            t.grad = None

    fwd_bwd(tiny, tiny_cam)  # loads the compiled kernels
    if cuda:
        sync()
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.max_memory_allocated(device) / 1024
    else:
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    fwd_bwd(params, cam)
    sync()
    peak_kb = (torch.cuda.max_memory_allocated(device) / 1024 if cuda
               else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) - base
    with torch.no_grad():
        n_visible = int(fwd(params, cam).visible.sum())

    def timed(fn) -> float:
        ts = []
        for _ in range(repeats):
            sync()
            t0 = time.perf_counter()
            fn()
            sync()
            ts.append(time.perf_counter() - t0)
        ts.sort()
        return 1e3 * ts[len(ts) // 2], 1e3 * ts[0]

    fwd_ms, fwd_min = timed(lambda: fwd(params, cam))
    fwd_bwd_ms, fwd_bwd_min = timed(lambda: fwd_bwd(params, cam))
    with torch.no_grad():  # rendering a trained model: no autograd (numba: the projection runs in numba too)
        fwd(params, cam)
        fwd_ng_ms, _ = timed(lambda: fwd(params, cam))
        rasterize(*params, cam, bg, backend=backend, render_mode="RGB")
        fwd_rgb_ms, _ = timed(lambda: rasterize(*params, cam, bg, backend=backend, render_mode="RGB"))
    row = {
        "backend": backend,
        "device": torch.cuda.get_device_name(device) if cuda else "cpu",
        "res": f"{res}x{res}",
        "n_gaussians": n,
        "n_visible": n_visible,
        "fwd_ms": fwd_ms,
        "fwd_bwd_ms": fwd_bwd_ms,
        "fwd_nograd_ms": fwd_ng_ms,
        "nograd_speedup": fwd_ms / fwd_ng_ms,
        "fwd_rgb_ms": fwd_rgb_ms,
        "rgb_speedup": fwd_ng_ms / fwd_rgb_ms,
        "fwd_min_ms": fwd_min,
        "fwd_bwd_min_ms": fwd_bwd_min,
        "peak_mb": peak_kb / 1024.0,
        "repeats": repeats,
    }
    if backend == FAST:
        row.update(kernel_profile(params, cam, repeats))
    return row


def kernel_profile(params, cam, repeats: int) -> dict:
    """The compositing kernels alone on the scene's training inputs (float32), and the
    fraction of the cores' fp32 peak they reach (:mod:`lmgs.render.flops`).

    ``kfwd_ms`` / ``kbwd_ms`` are medians of the forward and backward kernels (no projection,
    sorting, binning or autograd); ``lanes`` the pixel lanes they run; ``fwd_peak`` and
    ``bwd_peak`` the achieved GFLOP/s over the peak of the cores numba runs on.
    """
    import numba
    import numpy as np
    import torch

    from lmgs.render import _cpu
    from lmgs.render import _numba_composite as C
    from lmgs.render import _numba_kernels as K
    from lmgs.render import flops
    from lmgs.render._projection import project, tile_rects

    with torch.no_grad():
        p = project(*params, None, cam)
    w, h = int(cam.width), int(cam.height)
    kd = _cpu._kernel_dtype(p.means2d)
    rows = K.gaussian_rows(_cpu._np(p.means2d, kd), _cpu._np(p.conics, kd), _cpu._np(p.opacities, kd),
                           _cpu._np(p.features, kd))
    rects = tile_rects(p.means2d, p.radii, w, h).numpy()
    _, t_final, _, last, (rows, offsets, ids, tile_order, tiles_w) = _cpu._composite_rows(
        rows, rects, (p.radii > 0).numpy(), p.depths.numpy(), w, h)
    cst, centres = C.consts(rows.dtype), C.pixel_centres(w, h, rows.dtype)
    rng = np.random.default_rng(0)
    g_rgb, g_depth, g_normal = (rng.random((h, w, c)).astype(rows.dtype) for c in (3, 1, 3))
    g_alpha = rng.random((h, w)).astype(rows.dtype)

    def timed(fn) -> float:
        fn()
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return sorted(ts)[len(ts) // 2]

    t_fwd = timed(lambda: C.forward(rows, ids, offsets, tile_order, tiles_w, w, h, K.NF, cst, centres))
    t_bwd = timed(lambda: C.backward(rows, ids, offsets, tile_order, tiles_w, w, h, t_final, last, g_rgb, g_depth,
                                     g_normal, g_alpha, cst, centres, np.empty((ids.shape[0], C.GROW), rows.dtype)))
    n_lanes = flops.lanes(rows, ids, offsets, tiles_w, w, h)
    peak = flops.cpu_peak_gflops(min(numba.get_num_threads(), flops.usable_cores()))
    fwd_gflops = n_lanes * flops.fwd_flops_per_lane(K.NF) / t_fwd / 1e9
    bwd_gflops = n_lanes * flops.BWD_FLOPS / t_bwd / 1e9
    return {
        "kfwd_ms": 1e3 * t_fwd,
        "kbwd_ms": 1e3 * t_bwd,
        "lanes": n_lanes,
        "fwd_gflops": fwd_gflops,
        "bwd_gflops": bwd_gflops,
        "fwd_peak": fwd_gflops / peak["gflops"],
        "bwd_peak": bwd_gflops / peak["gflops"],
    }


def first_call_seconds() -> dict:
    """Seconds of the first render in a fresh process (numba cache load, or compile if cold)."""
    code = (
        "import time; t=time.perf_counter(); import torch; from lmgs.render.bench_scene import head_scene;"
        "from lmgs.render import rasterize; p,c=head_scene(64,32); t0=time.perf_counter();"
        "r=rasterize(*p,c,backend='numba'); r.rgb.sum().backward(); print(time.perf_counter()-t0)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    return {"first_render_s": float(proc.stdout.strip() or "nan")}


def _load_average() -> str:
    """The host's 1/5/15-minute load averages when the run ended (the cores are shared)."""
    try:
        return " / ".join(f"{v:.1f}" for v in os.getloadavg())
    except OSError:  # pragma: no cover - not Unix
        return "unknown"


def run(args: argparse.Namespace) -> dict:
    import numba
    import torch

    from lmgs.render import flops

    sizes = [256] if args.quick else list(args.sizes)
    counts = [10_000] if args.quick else list(args.counts)
    repeats = 3 if args.quick else int(args.repeats)
    if getattr(args, "threads", None):
        out = scaling(sizes, counts, list(args.threads), repeats, bool(getattr(args, "wait_too", False)))
        out.update(load=_load_average(), machine=f"{platform.machine()} {platform.processor() or ''}".strip())
        return out
    gpu = _gpu_backends()
    rows, gpu_rows = [], []
    for res in sizes:
        for n in counts:
            fast = worker_row(FAST, res, n, repeats)
            for backend in gpu:
                row = worker_row(backend, res, n, max(repeats, 20), "cuda")
                row["fwd_ratio_vs_numba"] = fast["fwd_ms"] / row["fwd_ms"]
                row["fwd_bwd_ratio_vs_numba"] = fast["fwd_bwd_ms"] / row["fwd_bwd_ms"]
                gpu_rows.append(row)
            anchor = None if args.no_anchor else worker_row(ANCHOR, res, n, 2 if not args.quick else 1)
            for row in (fast, anchor):
                if row is None:
                    continue
                row["fwd_ratio_vs_anchor"] = anchor["fwd_ms"] / row["fwd_ms"] if anchor else None
                row["fwd_bwd_ratio_vs_anchor"] = anchor["fwd_bwd_ms"] / row["fwd_bwd_ms"] if anchor else None
                rows.append(row)
    out = {
        "rows": rows,
        "peak_mb": "growth of ru_maxrss over the warmed-up worker during one fwd+bwd (fresh process per row)",
        "ratio": "anchor median time / this backend's median time, same run, same scene",
        "times": "fwd_ms/fwd_bwd_ms are medians, *_min_ms minima of the repeats (the 2 cores are shared)",
        "nograd": "fwd_nograd_ms: the same forward under torch.no_grad() (rendering a trained model); "
                  "nograd_speedup = fwd_ms / fwd_nograd_ms, same worker, same scene",
        "rgb": "fwd_rgb_ms: that no-grad forward with render_mode='RGB' (colour and alpha only, what inference draws); "
               "rgb_speedup = fwd_nograd_ms / fwd_rgb_ms, same worker, same scene",
        "scene": "head-sized blob 0.6 m away, fx = 1.5 x res, ~1.5 px sigma at 256 px",
        "threads": {"torch": torch.get_num_threads(), "numba": numba.get_num_threads(), "cpus": os.cpu_count()},
        "fp32_peak": flops.cpu_peak_gflops(min(numba.get_num_threads(), flops.usable_cores())),
        "peak": "kfwd_ms/kbwd_ms: the compositing kernels alone (median); *_gflops: lanes x flops per lane "
                "(lmgs.render.flops) / kernel time; *_peak: that over fp32_peak = cores x SIMD lanes x 2 (FMA) x clock",
        "load": _load_average(),
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "first_call": first_call_seconds(),
    }
    if gpu_rows:
        out["gpu_rows"] = gpu_rows
        out["gpu"] = ("the same scenes on the CUDA device (peak_mb: growth of the allocator's peak); "
                      "ratio_vs_numba = the numba row's median time on this machine's CPU / this row's, same run")
    else:
        out["gpu"] = "no CUDA rows: " + ("gsplat is not installed (pip install 'lmgs[cuda]')"
                                         if torch.cuda.is_available() else "no CUDA device")
    return out


def _gpu_backends() -> list[str]:
    """The CUDA rows to measure: gsplat when a CUDA device and gsplat are present, else none."""
    import torch

    from lmgs.render.rasterize import gsplat_available

    return ["gsplat"] if torch.cuda.is_available() and gsplat_available() else []


def main(argv: list[str]) -> int:
    """``python -m lmgs.render.bench [options]``: the benchmark without ``lmgs-eval`` (one JSON object
    on stdout with ``--json``; the scaling table, if measured, on stderr)."""
    p = argparse.ArgumentParser(prog="python -m lmgs.render.bench", description=HELP)
    add_arguments(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    args = p.parse_args(argv)
    out = run(args)
    if "scaling" in out:
        print(scaling_text(out["scaling"]), file=sys.stderr)
    print(json.dumps(out, indent=2) if args.json else {k: v for k, v in out.items() if k != "scaling"})
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        b, r, n_, rep, dev, thr = json.loads(sys.argv[2])
        if thr is not None:
            print(json.dumps(measure_scaling(int(r), int(n_), int(rep), int(thr))))
        else:
            print(json.dumps(_measure(b, int(r), int(n_), int(rep), dev)))
    else:
        raise SystemExit(main(sys.argv[1:]))
