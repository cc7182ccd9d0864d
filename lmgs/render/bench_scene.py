"""What the rasterizer benchmarks share: the benchmark scene and the fresh worker process a row is measured in.

:func:`head_scene` is the scene of ``lmgs-eval bench raster`` (and of the GPU scripts under ``benchmarks/``);
:func:`worker_row` runs ``python -m lmgs.render.bench --worker`` for one row, so that each row's peak memory
and thread settings are its own.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

FAST = "numba"  # the backend the benchmarks time as the fast CPU path


def head_scene(n: int, res: int, seed: int = 0, requires_grad: bool = True):
    """A head-sized blob of ``n`` Gaussians 0.6 m in front of a camera, ``res x res`` image.

    Centres lie near the surface of an ellipsoid of semi-axes 9 x 12 x 10 cm (a head) and
    inside it; the focal length is 1.5 x ``res``, so the head spans about 60 % of the
    image height; scales are log-normal around 1.5 pixels at 256 px (a 3-sigma radius of
    a few pixels), anisotropic, random rotations, opacities mostly 0.3-0.9.

    Returns ``(params, camera)`` with params ``(means, quats, log_scales, opacity_logits, colors)``.
    """
    import torch

    from lmgs.types import Camera

    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    shell = 1.0 - 0.15 * torch.rand(n, 1, generator=g) ** 2
    means = d * shell * torch.tensor([0.09, 0.12, 0.10]) + torch.tensor([0.0, 0.0, 0.6])
    quats = torch.randn(n, 4, generator=g)
    sigma_world = 1.5 * 0.6 / (1.5 * 256)  # 1.5 px at 256 px
    log_scales = math.log(sigma_world) + 0.4 * torch.randn(n, 3, generator=g)
    opacity_logits = 0.5 + torch.randn(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    cam = Camera(torch.eye(4), 1.5 * res, 1.5 * res, res / 2, res / 2, res, res)
    params = [means, quats, log_scales, opacity_logits, colors]
    for t in params:
        t.requires_grad_(requires_grad)
    return params, cam


def on_device(params, cam, device: str):
    """The scene's leaf tensors and camera on ``device`` (leaves again, needing a gradient as before)."""
    if device == "cpu":
        return params, cam
    return [t.detach().to(device).requires_grad_(t.requires_grad) for t in params], cam.to(device)


def worker_row(backend: str, res: int, n: int, repeats: int, device: str = "cpu", threads: int | None = None,
                omp_env: dict | None = None) -> dict:
    """One row measured in a fresh worker process; with ``threads``, a scaling row (:func:`lmgs.render.bench_scaling.measure_scaling`)
    in a worker whose numba, OpenMP and MKL thread counts are ``threads`` from its start (and ``omp_env``
    in its environment)."""
    env = dict(os.environ)
    if threads is not None:
        env.update(NUMBA_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    env.update(omp_env or {})
    cmd = [sys.executable, "-m", "lmgs.render.bench", "--worker",
           json.dumps([backend, res, n, repeats, device, threads])]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark worker {backend} {res} {n} (threads {threads}) failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
