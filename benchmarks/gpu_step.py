"""What one lmgs training step costs on a device, and where it makes the host wait.

Trains lmgs on a packed clip (``benchmarks/gpu_clip.py pack``) for a short schedule and reports,
per stage (static, dynamic), the time per step measured from one step's start to the next (the
GPU is not synchronised in between, so this is the throughput a training run sees), and, for a few
sampled steps, every host synchronisation the step made (``torch.cuda.set_sync_debug_mode``: the
file and line that asked, counted). With ``--profile`` a few dynamic steps also go through
``torch.profiler`` (the operators by GPU and by host time, and the counts of kernel launches,
synchronisations and copies).

It reads only ``lmgs.train.fit`` and its ``_step``, so the same script times another tree of the
model library: ``PYTHONPATH=/path/to/other/tree python benchmarks/gpu_step.py ...`` (the ``tree``
field of the JSON says which ``lmgs`` was imported).

    python benchmarks/gpu_step.py .gpu/astronaut512.npz --device cuda --json step.json
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _stage_times(starts: list[tuple[int, bool, float]], skip: int) -> dict:
    """ms per step by stage from consecutive step starts, leaving out each stage's first ``skip``."""
    out = {}
    for dynamic in (False, True):
        steps = [(s, t) for s, d, t in starts if d == dynamic]
        dts = [1e3 * (b[1] - a[1]) for a, b in zip(steps, steps[1:]) if b[0] == a[0] + 1][skip:]
        if dts:
            out["dynamic" if dynamic else "static"] = {
                "steps": len(dts), "median_ms": statistics.median(dts), "mean_ms": statistics.fmean(dts),
                "p90_ms": float(np.percentile(dts, 90))}
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("clip")
    p.add_argument("--device", default="cuda")
    p.add_argument("--static", type=int, default=300, help="static steps (default 300)")
    p.add_argument("--dynamic", type=int, default=300, help="dynamic steps (default 300)")
    p.add_argument("--landmark-steps", type=int, default=200)
    p.add_argument("--skip", type=int, default=20, help="steps left out at the start of each stage (warm-up)")
    p.add_argument("--trace", type=int, default=3, help="steps of each stage whose host syncs are traced")
    p.add_argument("--profile", type=int, default=0, help="dynamic steps to run under torch.profiler (0: none)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json")
    args = p.parse_args(argv)

    import torch

    import lmgs
    import lmgs.train as tr
    from gpu_clip import _unpack_clip
    from lmgs.config import override
    from lmgs.presets import quick

    z = np.load(args.clip)
    clip = _unpack_clip(z, "train_")
    sets = {"train.static_steps": args.static, "train.dynamic_steps": args.dynamic,
            "train.landmark_steps": args.landmark_steps}
    if not np.isnan(z["budget_density"]):
        sets["train.budget_density"] = float(z["budget_density"])
    cfg = override(quick(), sets)
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    starts: list[tuple[int, bool, float]] = []
    traced: dict[str, list] = {"static": [], "dynamic": []}
    trace_at = set(range(args.skip, args.skip + args.trace))
    trace_at |= {args.static + k for k in trace_at}
    prof_at = range(args.static + args.skip + args.trace, args.static + args.skip + args.trace + args.profile)
    prof_box: dict = {}
    real_step = tr._step

    def step(run, k, i):
        dynamic = k >= args.static
        starts.append((k, dynamic, time.perf_counter()))
        if cuda and k in trace_at:
            torch.cuda.synchronize()
            with warnings.catch_warnings(record=True) as seen:
                warnings.simplefilter("always")
                torch.cuda.set_sync_debug_mode("warn")
                try:
                    real_step(run, k, i)
                finally:
                    torch.cuda.set_sync_debug_mode("default")
            where = collections.Counter(f"{Path(w.filename).name}:{w.lineno}" for w in seen
                                        if "synchroniz" in str(w.message))
            traced["dynamic" if dynamic else "static"].append({"step": k, "syncs": sum(where.values()),
                                                               "where": dict(where.most_common())})
            torch.cuda.synchronize()
            starts.append((-1, dynamic, 0.0))  # breaks the run of consecutive steps (the traced step is slower)
            return
        if args.profile and k == prof_at.start:
            from torch.profiler import ProfilerActivity, profile

            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
            prof_box["p"] = profile(activities=acts)
            prof_box["p"].__enter__()
        real_step(run, k, i)
        if args.profile and k == prof_at.stop - 1:
            if cuda:
                torch.cuda.synchronize()
            prof_box["p"].__exit__(None, None, None)
            prof_box["done"] = True
            starts.append((-1, dynamic, 0.0))

    tr._step = step
    t0 = time.perf_counter()
    stopped = report = None
    with tempfile.TemporaryDirectory() as work:
        try:
            _, report = tr.fit(clip, cfg, seed=args.seed, workdir=Path(work), progress=False, device=args.device)
        except tr.TrainingDiverged as e:  # a short schedule can trip the collapse check: the steps run still count
            stopped = str(e)
    if "p" in prof_box and "done" not in prof_box:  # stopped inside the profiled steps
        prof_box["p"].__exit__(None, None, None)
        prof_box["done"] = True
    if cuda:
        torch.cuda.synchronize()
    fit_s = time.perf_counter() - t0
    res = {
        "tree": str(Path(lmgs.__file__).resolve().parent.parent), "device": dev.type,
        "gpu": torch.cuda.get_device_name() if cuda else "", "torch": torch.__version__,
        "schedule": sets, "fit_s": fit_s, "stopped": stopped,
        "landmark_s": report.landmark_seconds if report else None, "n_gaussians": report.n_gaussians if report else None,
        "final_psnr": report.final_psnr if report else None,
        "per_step": _stage_times(starts, args.skip),
        "syncs_traced": traced,
    }
    if "done" in prof_box:
        ka = prof_box["p"].key_averages()
        counts = {name: 0 for name in ("cudaLaunchKernel", "cuLaunchKernel", "cudaStreamSynchronize",
                                       "cudaDeviceSynchronize", "cudaMemcpyAsync", "cudaEventSynchronize")}
        for e in ka:
            if e.key in counts:
                counts[e.key] += e.count
        res["profile"] = {"steps": args.profile, "runtime_calls": counts}
        keys = ("self_cuda_time_total", "self_cpu_time_total") if cuda else ("self_cpu_time_total",)
        res["profile"]["tables"] = [ka.table(sort_by=key, row_limit=30) for key in keys]
    text = json.dumps(res, indent=1)
    print(json.dumps({k: res[k] for k in ("tree", "fit_s", "stopped", "per_step")}, indent=1))
    for stage, rows in traced.items():
        for row in rows:
            print(stage, row["step"], row["syncs"], row["where"])
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
