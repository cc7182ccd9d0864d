"""The rasterizer's CUDA paths against numba on the same machine's cores, in one process.

For each scene (``lmgs.render.bench.head_scene``: N Gaussians, a square image), the medians of
forward (no gradient) and forward+backward (``backward()`` of a sum over every output) of:
numba on every CPU core; on CUDA, the Triton compositor at each chunk size / warp count given
(the first is the shipped one), the numba compositing of the GPU projection (what ``auto``
takes on CUDA without gsplat or Triton), and the pure-torch compositor. Each CUDA call ends
with a synchronisation. Writes one JSON; the ratios are to the numba row of the same run.

    python benchmarks/gpu_raster.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time


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

    ps = [t.detach().to(device).requires_grad_() for t in params]
    c = cam.to(device) if device != "cpu" else cam

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


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=["10000x256", "50000x512"], help="NxRES (default 10000x256 50000x512)")
    p.add_argument("--configs", nargs="+", default=["16x8", "32x8", "16x4", "32x4"],
                   help="Triton BLOCK_GxNUM_WARPS to try, the shipped one first")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--torch-repeats", type=int, default=3)
    p.add_argument("--json")
    args = p.parse_args(argv)

    import torch

    from lmgs.render import _triton
    from lmgs.render.bench import head_scene

    torch.set_num_threads(os.cpu_count() or 1)
    rows = []
    shipped = (_triton.BLOCK_G, _triton.NUM_WARPS)
    for scene in args.scenes:
        n, res = (int(v) for v in scene.split("x"))
        params, cam = head_scene(n, res)
        base = {"n": n, "res": res}
        ref = {**base, "path": "numba", "device": f"cpu x{os.cpu_count()}", **_row(params, cam, "numba", args.repeats, "cpu")}
        rows.append(ref)
        print(json.dumps(ref), flush=True)
        cands = [("triton", c) for c in args.configs] + [("numba-split", None), ("torch", None)]
        for path, conf in cands:
            try:
                if conf is not None:
                    bg, nw = (int(v) for v in conf.split("x"))
                    _triton.BLOCK_G, _triton.NUM_WARPS = bg, nw
                backend = {"numba-split": "numba"}.get(path, path)
                reps = args.torch_repeats if path == "torch" else args.repeats
                r = {**base, "path": path if conf is None else f"triton {conf}", "device": torch.cuda.get_device_name(),
                     **_row(params, cam, backend, reps, "cuda")}
                r["speedup_fwd"] = ref["fwd_ms"] / r["fwd_ms"]
                r["speedup_fwd_bwd"] = ref["fwd_bwd_ms"] / r["fwd_bwd_ms"]
            except Exception as e:  # noqa: BLE001 - a failed candidate is a row saying so
                r = {**base, "path": path if conf is None else f"triton {conf}", "error": f"{type(e).__name__}: {e}"[:500]}
            finally:
                _triton.BLOCK_G, _triton.NUM_WARPS = shipped
            rows.append(r)
            print(json.dumps(r), flush=True)
    res = {"torch": torch.__version__, "cpu_count": os.cpu_count(), "rows": rows}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
