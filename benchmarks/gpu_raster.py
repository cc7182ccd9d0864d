"""The rasterizer's CUDA paths against numba on the same machine's cores, in one process.

First (``section: "fixed_cost"``), the Triton path's cost per call, split: at a tiny scene
(``--tiny``, default 100 Gaussians at 64 px: nothing there but the fixed cost) and at each
scene, for the whole ``rasterize`` (forward, forward+backward), the torch projection alone
(forward+backward), the Triton compositor alone on a projection made before (forward,
forward+backward), and the binning, ``_triton.bin_tiles`` against the torch-op binning it
replaced (``bin_tiles_reference``). Each part gets the median of synchronised calls
(``ms``), the time per call of ``repeats`` calls queued back to back without a
synchronisation between them, between two CUDA events (``pipelined_ms``: what a loop that
never reads a result back pays), the host synchronisations of one call (``syncs``: counted
with ``torch.cuda.set_sync_debug_mode("warn")``), and the GPU work of one call from
``torch.profiler`` (``kernels``: kernel launches, ``copies``: memcpy and memset, ``gpu_ms``:
their summed durations; ``kernel_names`` where a part launches few).

Then, for each scene (``lmgs.render.bench.head_scene``: N Gaussians, a square image), the medians of
forward (no gradient) and forward+backward (``backward()`` of a sum over every output) of:
numba on every CPU core; on CUDA, the Triton compositor at each chunk size / warp count given
(the first is the shipped one), the numba compositing of the GPU projection (what ``auto``
takes on CUDA without gsplat or Triton), and the pure-torch compositor. Each CUDA call ends
with a synchronisation. Writes one JSON, rewritten after every row (a run cut short keeps
what it measured); the ratios are to the numba row of the same run.

    python benchmarks/gpu_raster.py --json out.json
    python benchmarks/gpu_raster.py --fixed-only --json fixed.json   # the first part alone
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import time
import warnings


def _time(fn, repeats: int, cuda: bool) -> float:
    import torch

    fn()
    fn()
    out = []
    for _ in range(repeats):
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize()
        out.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(out)


def _row(params, cam, backend: str, repeats: int, device: str) -> dict:
    import torch

    from lmgs.render import rasterize
    from lmgs.render.bench_scene import on_device

    ps, c = on_device(params, cam, device)

    def fwd():
        with torch.no_grad():
            rasterize(*ps, c, backend=backend)

    def fwd_bwd():
        out = rasterize(*ps, c, backend=backend)
        (out.rgb.sum() + out.alpha.sum() + out.depth.sum() + out.normal.sum()).backward()
        for p in ps:
            p.grad = None

    cuda = device != "cpu"
    return {"fwd_ms": _time(fwd, repeats, cuda), "fwd_bwd_ms": _time(fwd_bwd, repeats, cuda)}


def _count_syncs(fn) -> int:
    """Host synchronisations in one call of ``fn`` (torch's sync debug mode warns at each)."""
    import torch

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    return sum("synchroniz" in str(w.message) for w in caught)


def _gpu_work(fn) -> dict:
    """Kernels and copies one call of ``fn`` puts on the GPU, and their summed durations."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    gpu = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    kernels = [e for e in gpu if not e.name.startswith(("Memcpy", "Memset"))]
    r = {"kernels": len(kernels), "copies": len(gpu) - len(kernels),
         "gpu_ms": round(sum(e.time_range.elapsed_us() for e in gpu) / 1e3, 4)}
    if len(kernels) <= 24:
        r["kernel_names"] = dict(collections.Counter(e.name[:60] for e in kernels))
    return r


def _measure(fn, repeats: int) -> dict:
    """``ms`` (median, synchronised), ``pipelined_ms`` (CUDA events over ``repeats`` calls queued
    back to back), ``syncs``, and the profiler's kernel count and GPU time of one call."""
    import torch

    r = {"ms": _time(fn, repeats, True)}
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    torch.cuda.synchronize()
    start.record()
    for _ in range(repeats):
        fn()
    end.record()
    end.synchronize()
    r["pipelined_ms"] = start.elapsed_time(end) / repeats
    r["syncs"] = _count_syncs(fn)
    try:
        r.update(_gpu_work(fn))
    except Exception as e:  # noqa: BLE001 - the profiler is optional: say why it gave nothing
        r["profiler_error"] = f"{type(e).__name__}: {e}"[:300]
    return r


def _fixed_cost(n: int, res: int, repeats: int, device: str):
    """Yield the ``fixed_cost`` rows of one scene (see the module docstring)."""
    import torch

    from lmgs.render import _triton, rasterize
    from lmgs.render._projection import project
    from lmgs.render.bench_scene import head_scene, on_device

    ps, c = on_device(*head_scene(n, res), device)
    with torch.no_grad():
        p = project(*ps, None, c)
    leaves = [t.detach().requires_grad_() for t in (p.means2d, p.conics, p.opacities, p.features)]
    flat = [t.detach() for t in leaves]

    def clear(ts):
        for t in ts:
            t.grad = None

    def ras_fwd():
        with torch.no_grad():
            rasterize(*ps, c, backend="triton")

    def ras_fwd_bwd():
        out = rasterize(*ps, c, backend="triton")
        (out.rgb.sum() + out.alpha.sum() + out.depth.sum() + out.normal.sum()).backward()
        clear(ps)

    def proj_fwd_bwd():
        q = project(*ps, None, c)
        (q.means2d.sum() + q.conics.sum() + q.opacities.sum() + q.features.sum()).backward()
        clear(ps)

    def comp_fwd():
        with torch.no_grad():
            _triton.composite(*leaves, p.radii, p.depths, res, res)

    def comp_fwd_bwd():
        feat, alpha = _triton.composite(*leaves, p.radii, p.depths, res, res)
        (feat.sum() + alpha.sum()).backward()
        clear(leaves)

    parts = [("rasterize triton, fwd", ras_fwd), ("rasterize triton, fwd+bwd", ras_fwd_bwd),
             ("projection (torch), fwd+bwd", proj_fwd_bwd), ("composite (triton), fwd", comp_fwd),
             ("composite (triton), fwd+bwd", comp_fwd_bwd),
             ("binning: bin_tiles", lambda: _triton.bin_tiles(*flat, p.radii, p.depths, res, res)),
             ("binning: bin_tiles_reference (torch ops)",
              lambda: _triton.bin_tiles_reference(flat[0], p.radii, p.depths, res, res))]
    for name, fn in parts:
        r = {"section": "fixed_cost", "n": n, "res": res, "part": name}
        try:
            r.update(_measure(fn, repeats))
        except Exception as e:  # noqa: BLE001 - a failed part is a row saying so
            r["error"] = f"{type(e).__name__}: {e}"[:500]
        yield r


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=["10000x256", "50000x512"], help="NxRES (default 10000x256 50000x512)")
    p.add_argument("--configs", nargs="+", default=["16x8", "32x8", "16x4", "32x4"],
                   help="Triton BLOCK_GxNUM_WARPS to try, the shipped one first")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--torch-repeats", type=int, default=3)
    p.add_argument("--tiny", default="100x64", help="NxRES of the scene that measures the fixed cost per call")
    p.add_argument("--fixed-only", action="store_true", help="only the fixed-cost section")
    p.add_argument("--skip-fixed", action="store_true", help="leave the fixed-cost section out")
    p.add_argument("--device", default="cuda", help="the CUDA device the GPU rows run on (default cuda)")
    p.add_argument("--json")
    args = p.parse_args(argv)

    import torch

    from lmgs.render import _triton
    from lmgs.render.bench_scene import head_scene

    if torch.device(args.device).type != "cuda" or not torch.cuda.is_available():
        p.error(f"--device {args.device}: this benchmark measures a CUDA device, and none is here")

    torch.set_num_threads(os.cpu_count() or 1)
    rows = []
    report = {"torch": torch.__version__, "cpu_count": os.cpu_count(),
              "device": torch.cuda.get_device_name(args.device), "rows": rows}

    def emit(r):
        rows.append(r)
        print(json.dumps(r), flush=True)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(report, f, indent=1)

    if not args.skip_fixed:
        for scene in [args.tiny] + args.scenes:
            for r in _fixed_cost(*(int(v) for v in scene.split("x")), args.repeats, args.device):
                emit(r)
    shipped = (_triton.BLOCK_G, _triton.NUM_WARPS)
    for scene in [] if args.fixed_only else args.scenes:
        n, res = (int(v) for v in scene.split("x"))
        params, cam = head_scene(n, res)
        base = {"n": n, "res": res}
        ref = {**base, "path": "numba", "device": f"cpu x{os.cpu_count()}", **_row(params, cam, "numba", args.repeats, "cpu")}
        emit(ref)
        cands = [("triton", c) for c in args.configs] + [("numba-split", None), ("torch", None)]
        for path, conf in cands:
            try:
                if conf is not None:
                    bg, nw = (int(v) for v in conf.split("x"))
                    _triton.BLOCK_G, _triton.NUM_WARPS = bg, nw
                backend = {"numba-split": "numba"}.get(path, path)
                reps = args.torch_repeats if path == "torch" else args.repeats
                r = {**base, "path": path if conf is None else f"triton {conf}",
                     "device": torch.cuda.get_device_name(args.device),
                     **_row(params, cam, backend, reps, args.device)}
                r["speedup_fwd"] = ref["fwd_ms"] / r["fwd_ms"]
                r["speedup_fwd_bwd"] = ref["fwd_bwd_ms"] / r["fwd_bwd_ms"]
            except Exception as e:  # noqa: BLE001 - a failed candidate is a row saying so
                r = {**base, "path": path if conf is None else f"triton {conf}", "error": f"{type(e).__name__}: {e}"[:500]}
            finally:
                _triton.BLOCK_G, _triton.NUM_WARPS = shipped
            emit(r)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
