"""``lmgs-eval bench raster --threads 1,2,4,8,16``: the numba rasterizer's thread scaling table.

Per scene and thread count, a fresh worker (``python -m lmgs.render.bench --worker``) whose numba and
torch threads are that count (``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS`` and ``MKL_NUM_THREADS`` set before
it imports them, then ``torch.set_num_threads``) times the numba forward and forward+backward, and splits the
latter into the compositing kernels and the rest (projection, depth sort and binning, gradient reduction,
and everything else: conversions, torch ops and Python), each timed inside the same runs
(:func:`measure_scaling`). Speed-ups are over the smallest thread count of the same run.
"""

from __future__ import annotations

import argparse
import os
import time

from lmgs.render.bench_scene import FAST, head_scene, worker_row

SHORT_SPIN = 20_000  # GOMP_SPINCOUNT of the short-spin row (libgomp counts about 100,000 spins a millisecond)


def thread_counts(text: str) -> list[int]:
    try:
        counts = sorted({int(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise argparse.ArgumentTypeError(f"thread counts are integers separated by commas, got {text!r}") from None
    if not counts or counts[0] < 1:
        raise argparse.ArgumentTypeError(f"thread counts must be at least 1, got {text!r}")
    return counts


# the stages of the numba path timed inside a forward+backward: (module, function) -> stage
_STAGES = {
    ("C", "forward"): "kernel",
    ("C", "backward"): "kernel",
    ("NP", "project_forward"): "proj",
    ("NP", "project_backward"): "proj",
    ("K", "depth_order"): "sort_bin",
    ("K", "bin_tiles"): "sort_bin",
    ("C", "reduce_grads"): "reduce",
}


def _stage_clock() -> dict:
    """Wrap the numba path's stage functions (:data:`_STAGES`, looked up by the path at each call)
    so that each call adds its seconds to the returned dict under its stage (and the compositing
    kernels under ``kfwd`` / ``kbwd`` too)."""
    from lmgs.render import _numba_composite as C
    from lmgs.render import _numba_kernels as K
    from lmgs.render import _numba_projection as NP

    mods = {"C": C, "K": K, "NP": NP}
    acc: dict = {}

    def clocked(fn, keys):
        def run(*a, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                dt = time.perf_counter() - t0
                for k in keys:
                    acc[k] = acc.get(k, 0.0) + dt
        return run

    for (mod, name), stage in _STAGES.items():
        fn = getattr(mods[mod], name, None)
        if fn is not None:
            extra = {"forward": ("kfwd",), "backward": ("kbwd",)}.get(name, ()) if mod == "C" else ()
            setattr(mods[mod], name, clocked(fn, (stage, *extra)))
    return acc


def measure_scaling(res: int, n: int, repeats: int, threads: int) -> dict:
    """One scaling row, in this process (a worker started with its thread variables at ``threads``):
    medians of the numba forward and forward+backward (those of :func:`lmgs.render.bench._measure`), and of the
    forward+backward's stages timed inside the same runs (:func:`_stage_clock`)."""
    import numba
    import torch

    from lmgs.render import rasterize

    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    clock = _stage_clock()
    params, cam = head_scene(n, res)
    bg = torch.tensor([0.2, 0.3, 0.4])

    def fwd():
        return rasterize(*params, cam, bg, backend=FAST)

    def fwd_bwd():
        r = fwd()
        (r.rgb.sum() + r.alpha.sum() + r.depth.sum() + r.normal.sum()).backward()
        for t in params:
            t.grad = None

    for _ in range(2):
        fwd_bwd()
    fwds, runs = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fwd()
        fwds.append(time.perf_counter() - t0)
    for _ in range(repeats):
        clock.clear()
        t0 = time.perf_counter()
        fwd_bwd()
        runs.append((time.perf_counter() - t0, dict(clock)))

    def med(xs) -> float:
        xs = sorted(xs)
        return 1e3 * xs[len(xs) // 2]

    stages = ("kernel", "proj", "sort_bin", "reduce")
    row = {
        "res": f"{res}x{res}",
        "n_gaussians": n,
        "threads": threads,
        "fwd_ms": med(fwds),
        "fwd_bwd_ms": med([t for t, _ in runs]),
        "fwd_bwd_min_ms": 1e3 * min(t for t, _ in runs),
        "kernel_ms": med([c.get("kernel", 0.0) for _, c in runs]),
        "other_ms": med([t - c.get("kernel", 0.0) for t, c in runs]),
        "kfwd_ms": med([c.get("kfwd", 0.0) for _, c in runs]),
        "kbwd_ms": med([c.get("kbwd", 0.0) for _, c in runs]),
    }
    for st in stages[1:]:
        row[f"{st}_ms"] = med([c.get(st, 0.0) for _, c in runs])
    row["rest_ms"] = med([t - sum(c.get(st, 0.0) for st in stages) for t, c in runs])
    row.update(numba_threads=numba.get_num_threads(), torch_threads=torch.get_num_threads(),
               wait_policy=os.environ.get("OMP_WAIT_POLICY", "unset"), spin_count=os.environ.get("GOMP_SPINCOUNT"),
               repeats=repeats,
               layer=numba.threading_layer(), gomp_from=_gomp_library(), omp_libraries=_omp_libraries())
    return row


def _gomp_library() -> str:
    """The file of the ``GOMP_parallel`` that this process resolves globally (the OpenMP runtime
    numba's omp layer calls when torch has made its own global), or ``"none"``."""
    import ctypes
    import ctypes.util

    class _Info(ctypes.Structure):
        _fields_ = [("fname", ctypes.c_char_p), ("fbase", ctypes.c_void_p), ("sname", ctypes.c_char_p),
                    ("saddr", ctypes.c_void_p)]

    try:
        fn = ctypes.cast(ctypes.CDLL(None).GOMP_parallel, ctypes.c_void_p)
    except (AttributeError, OSError):
        return "none"
    try:
        info = _Info()
        libdl = ctypes.CDLL(ctypes.util.find_library("dl") or "libdl.so.2")
        if libdl.dladdr(fn, ctypes.byref(info)) and info.fname:
            return info.fname.decode()
    except (AttributeError, OSError):
        pass
    return "unknown"


def _omp_libraries() -> list[str]:
    """The OpenMP runtimes mapped in this process (Linux), e.g. torch's libgomp and the system's."""
    try:
        with open("/proc/self/maps") as f:
            return sorted({ln.split()[-1] for ln in f if "libgomp" in ln or "libiomp" in ln or "libomp" in ln})
    except OSError:
        return []


def scaling(sizes: list[int], counts: list[int], threads: list[int], repeats: int, wait_too: bool = False) -> dict:
    """The thread scaling table (see the module docstring): one fresh worker per scene and thread count."""
    cpus = os.cpu_count() or 1
    rows = []
    for res in sizes:
        for n in counts:
            scene = [worker_row(FAST, res, n, repeats, threads=t) for t in threads]
            if wait_too:
                for env in ({"OMP_WAIT_POLICY": "ACTIVE"}, {"GOMP_SPINCOUNT": str(SHORT_SPIN)}):
                    scene.append(worker_row(FAST, res, n, repeats, threads=threads[-1], omp_env=env))
            base = scene[0]
            for row in scene:
                t = row["threads"]
                row["speedup"] = base["fwd_bwd_ms"] / row["fwd_bwd_ms"]
                row["efficiency"] = row["speedup"] * base["threads"] / t
                row["fwd_speedup"] = base["fwd_ms"] / row["fwd_ms"]
                row["kernel_speedup"] = base["kernel_ms"] / row["kernel_ms"]
                row["other_speedup"] = base["other_ms"] / row["other_ms"]
                notes = [f"oversubscribed: {t} threads on {cpus} cpus"] if t > cpus else []
                if row["wait_policy"] != "PASSIVE":
                    notes.append(f"OMP_WAIT_POLICY={row['wait_policy']}")
                if row["spin_count"] is not None:
                    notes.append(f"GOMP_SPINCOUNT={row['spin_count']}")
                row["note"] = "; ".join(notes)
                rows.append(row)
    omp = {k: rows[0][f] if rows else None
           for k, f in (("libraries", "omp_libraries"), ("gomp_parallel_from", "gomp_from"), ("numba_layer", "layer"))}
    for row in rows:  # the same in every worker: kept once, under "omp"
        for f in ("omp_libraries", "gomp_from", "layer"):
            row.pop(f)
    return {
        "scaling": rows,
        "scaling_note": "numba medians per thread count, numba and torch both on that count, a fresh worker each; "
                        "kernel_ms: the compositing kernels (forward + backward) inside the fwd+bwd runs, other_ms the "
                        "rest of fwd+bwd: proj_ms (projection forward + backward), sort_bin_ms (depth sort, tile "
                        "binning), reduce_ms (per-Gaussian gradient sums), rest_ms (conversions, torch ops: the loss, "
                        "the background; Python); speedup = fwd+bwd at the smallest count / here, efficiency = "
                        "speedup x smallest count / threads",
        "cpus": cpus,
        "omp": omp,
        "omp_note": "the OpenMP runtimes mapped in a worker, and the one whose GOMP_parallel numba's omp layer "
                    "resolves (torch loads its libgomp globally: then numba and torch share one pool)",
    }


def scaling_text(rows: list[dict]) -> str:
    """The scaling rows as a fixed-width table (times in ms)."""
    cols = [("scene", None), ("threads", "threads"), ("fwd", "fwd_ms"), ("fwd+bwd", "fwd_bwd_ms"),
            ("speedup", "speedup"), ("eff", "efficiency"), ("kernels", "kernel_ms"), ("other", "other_ms"),
            ("proj", "proj_ms"), ("sort+bin", "sort_bin_ms"), ("reduce", "reduce_ms"), ("rest", "rest_ms"),
            ("note", "note")]

    def cell(r: dict, key: str | None) -> str:
        if key is None:
            return f"{r['n_gaussians'] // 1000}k@{r['res'].split('x')[0]}"
        v = r.get(key)
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    cells = [[c for c, _ in cols]] + [[cell(r, k) for _, k in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in cells)
