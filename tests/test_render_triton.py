"""The Triton compositor against the numba one, on the CPU through Triton's interpreter.

``TRITON_INTERPRET=1`` runs the kernels' code with numpy, program by program, so the
arithmetic, masks, stop rule and gradient formulas are checked on a machine without a GPU
(slowly: small scenes). Skipped where Triton is not installed (torch's CPU wheels do not
bring it); the same kernels compiled for CUDA are held to the numba path by
``test_cuda_paths_match_cpu``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("triton")

_SCRIPT = r"""
import json, sys, torch
from lmgs.render.bench import head_scene
from lmgs.render._projection import project
from lmgs.render import _cpu, _triton
n, res = int(sys.argv[1]), int(sys.argv[2])
params, cam = head_scene(n, res)
if len(sys.argv) > 3:
    cam = type(cam)(cam.world_to_camera, cam.fx, cam.fy, cam.cx, cam.cy, res + 7, res - 5)
    res_w, res_h = res + 7, res - 5
else:
    res_w = res_h = res
params = [t.detach() for t in params]
params[2], params[3] = params[2] + 1.5, params[3] + 3.0  # wide, opaque splats: many pixels reach the stop
def run(comp):
    ps = [t.clone().requires_grad_() for t in params]
    p = project(*ps, None, cam)
    p.means2d.retain_grad()
    feat, alpha = comp(p.means2d, p.conics, p.opacities, p.features, p.radii, p.depths, res_w, res_h)
    g = torch.Generator().manual_seed(0)
    ((feat * torch.randn(feat.shape, generator=g)).sum() + (alpha * torch.randn(alpha.shape, generator=g)).sum()
     ).backward()
    return feat.detach(), alpha.detach(), [q.grad for q in ps], p.means2d.grad
a, b = run(_cpu.composite), run(_triton.composite)
rel = lambda x, y: float((x - y).norm() / x.norm())
print(json.dumps({"feat": float((a[0] - b[0]).abs().max()), "alpha": float((a[1] - b[1]).abs().max()),
                  "opaque": float((a[1] > 0.999).float().mean()), "grads": [rel(x, y) for x, y in zip(a[2], b[2])],
                  "means2d": rel(a[3], b[3])}))
"""


@pytest.mark.parametrize("n,res,odd", [(300, 48, False), (1500, 40, True)])
def test_triton_kernels_match_numba_in_the_interpreter(n, res, odd):
    """A head-like scene (opaque enough that most pixels stop early, so the stop rule is
    exercised) at a square size and at a size that is no multiple of the 16-pixel tile:
    outputs within 1e-5 and every gradient within 1e-5 relative of the numba compositor
    (measured: about 1e-6 and 1e-6)."""
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONHASHSEED="0")
    args = [sys.executable, "-c", _SCRIPT, str(n), str(res)] + (["odd"] if odd else [])
    proc = subprocess.run(args, capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r["opaque"] > 0.05, r  # pixels whose compositing stopped (transmittance near 1e-4) are there
    assert r["feat"] < 1e-5 and r["alpha"] < 1e-5, r
    assert max(r["grads"]) < 1e-5 and r["means2d"] < 1e-5, r
