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


_BIN_SCRIPT = r"""
import json, torch
from lmgs.render._projection import N_FEATURES, project
from lmgs.render.bench import head_scene
from lmgs.render import _triton
g = torch.Generator().manual_seed(1)
cases = []
params, cam = head_scene(400, 40)
p = project(*[t.detach() for t in params], None, cam)
cases.append(("head", p.means2d, p.conics, p.opacities, p.features, p.radii, p.depths, 47, 35))
n, w, h = 1000, 100, 90
m2 = torch.rand(n, 2, generator=g) * torch.tensor([w + 60.0, h + 60.0]) - 30.0
radii = torch.randint(0, 40, (n,), generator=g, dtype=torch.int32)
radii[::7] = 0
radii[5] = 1000  # every tile
depths = torch.randint(-3, 4, (n,), generator=g).float() * 0.5  # ties, negative depths
depths[::11] = -0.0
rows = [torch.randn(n, 3, generator=g), torch.rand(n, generator=g), torch.randn(n, N_FEATURES, generator=g)]
cases.append(("random", m2, *rows, radii, depths, w, h))
cases.append(("random f64", m2.double(), *[r.double() for r in rows], radii, depths.double(), w, h))
cases.append(("culled", m2, *rows, torch.zeros_like(radii), depths, w, h))
sparse = torch.tensor([[150.0, 150.0], [40.0, 100.0], [180.0, 20.0], [60.0, 61.0]])  # long runs of empty tiles
cases.append(("sparse", sparse, *[r[:4] for r in rows], torch.tensor([3, 5, 2, 1], dtype=torch.int32), depths[:4],
              200, 190))
cases.append(("empty", m2[:0], *[r[:0] for r in rows], radii[:0], depths[:0], w, h))
out = {}
for name, m2, con, op, feat, rad, dep, w, h in cases:
    par, fts, ids, offsets, tiles_w, n_tiles = _triton.bin_tiles(m2, con, op, feat, rad, dep, w, h)
    ref_ids, ref_offsets = _triton.bin_tiles_reference(m2, rad, dep, w, h)
    total = int(ref_offsets[-1])
    want_par = torch.cat([m2, con, op[:, None], torch.zeros(len(op), 2, dtype=op.dtype)], 1).float()
    want_fts = torch.cat([feat, torch.zeros(len(op), _triton.FP - N_FEATURES, dtype=feat.dtype)], 1).float()
    out[name] = {"pairs": total, "tiles": n_tiles, "offsets": bool(torch.equal(offsets, ref_offsets)),
                 "ids": bool(torch.equal(ids[:total], ref_ids)), "params": bool(torch.equal(par, want_par)),
                 "feats": bool(torch.equal(fts, want_fts))}
# float64 inputs that are float32 values: the same binning (depth ranks instead of bits), images and gradients
def run(dtype):
    ps = [t.detach().to(dtype).requires_grad_() for t in (p.means2d, p.conics, p.opacities, p.features)]
    feat, alpha = _triton.composite(*ps, p.radii, p.depths.to(dtype), 47, 35)
    gen = torch.Generator().manual_seed(0)
    ((feat * torch.randn(feat.shape, generator=gen).to(dtype)).sum()
     + (alpha * torch.randn(alpha.shape, generator=gen).to(dtype)).sum()).backward()
    return [feat, alpha] + [q.grad for q in ps]
a, b = run(torch.float32), run(torch.float64)
out["f64 equals f32"] = [y.dtype == torch.float64 and torch.equal(x.double(), y) for x, y in zip(a, b)]
def grads(dense):  # the cotangents of a plain sum are expanded (stride 0): read through their strides
    ps = [t.detach().clone().requires_grad_() for t in (p.means2d, p.conics, p.opacities, p.features)]
    feat, alpha = _triton.composite(*ps, p.radii, p.depths, 47, 35)
    ((feat * torch.ones_like(feat)).sum() + (alpha * torch.ones_like(alpha)).sum() if dense
     else feat.sum() + alpha.sum()).backward()
    return [q.grad for q in ps]
out["expanded cotangents"] = [torch.equal(x, y) for x, y in zip(grads(True), grads(False))]
print(json.dumps(out))
"""


def test_triton_binning_kernels_match_the_torch_binning_in_the_interpreter():
    """``bin_tiles`` (packing, tile rectangles, pair keys, one stable sort, tile ranges in
    Triton kernels) gives the same tile lists as the torch-op binning it replaced, bit for
    bit: a projected head at an odd size, and random Gaussians with culled ones, one covering
    every tile, off-image ones, equal, negative and signed-zero depths (over several programs
    of each kernel), float64 inputs (depth ranks instead of the float32 bits), none visible and
    none at all. Float64 inputs holding float32 values give the float32 images and gradients,
    and expanded cotangents (a plain ``sum()``) the gradients of dense ones."""
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONHASHSEED="0")
    proc = subprocess.run([sys.executable, "-c", _BIN_SCRIPT], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(r.pop("f64 equals f32")) and all(r.pop("expanded cotangents")), r
    for name, c in r.items():
        assert c["offsets"] and c["ids"] and c["params"] and c["feats"], (name, c)
    assert r["random"]["pairs"] > 2 * 1024 and r["head"]["pairs"] > 0, r  # several programs of the range kernel
    assert r["culled"]["pairs"] == 0 and r["empty"]["pairs"] == 0, r


_PROJ_SCRIPT = r"""
import json, math, torch
from lmgs.render import _cpu, _triton, _triton_projection
from lmgs.types import Camera
def gaussians(n, seed, dtype):  # every branch: behind, too near, off-screen, zero quaternions, clamps, ties
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.5, 1.2, 1.0], dtype=dtype)
    means[:, 2] += 2.5
    means[:20, 2] = -torch.rand(20, generator=g, dtype=dtype) - 0.5
    means[20:30, 2] = 0.005 + 0.004 * torch.rand(10, generator=g, dtype=dtype)
    means[30:40, 0] = 8.0 + torch.rand(10, generator=g, dtype=dtype)
    means[40:45, 1] = -9.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[45:48] = 0.0
    log_scales = torch.randn(n, 3, generator=g, dtype=dtype) * 0.6 - 2.5
    log_scales[48:52, 0] = -40.0
    log_scales[52:54, 1] = 12.0
    means[52:54] = torch.tensor([[2e4, -1e4, 1e5], [-3e4, 2e4, 1.2e5]], dtype=dtype)
    log_scales[54:58] = -2.0
    return [means, quats, log_scales, torch.randn(n, generator=g, dtype=dtype) * 2,
            torch.rand(n, 3, generator=g, dtype=dtype)]
def camera(rotated):
    w2c = torch.eye(4)
    if rotated:
        c, s = math.cos(0.3), math.sin(0.3)
        w2c = torch.tensor([[c, 0, s, 0.1], [0, 1, 0, -0.2], [-s, 0, c, 0.4], [0, 0, 0, 1]])
    return Camera(w2c, 60.0, 55.0, 33.0, 27.5, 64, 56)
rel = lambda x, y: float((x - y).norm() / max(float(y.norm()), 1e-30))
out = {}
for dtype in (torch.float64, torch.float32):
    for rotated in (False, True):
        params, cam = gaussians(400, 1 + rotated, dtype), camera(rotated)
        a = [t.clone().requires_grad_() for t in params]
        b = [t.clone().requires_grad_() for t in params]
        box = []
        m2, props = _triton_projection._Project.apply(*a, cam, box, True)
        m2_ref, props_ref = _cpu.project_autograd(*b, cam)
        _, _, prep = _cpu.project_numba(*params, cam)
        pk = box[0]
        rects = torch.from_numpy(prep.rects)
        nx, ny = rects[:, 1] - rects[:, 0], rects[:, 3] - rects[:, 2]
        info_ref = torch.stack([nx * ny, rects[:, 0], rects[:, 2], nx]).to(torch.int32)
        # the packing equals _prepare_kernel's from (means2d, props), and the binning follows
        par, fts, ids, offsets, _, _ = _triton.bin_tiles(m2.detach(), props[:, :3].detach(), props[:, 3].detach(),
                                                         props[:, 4:].detach(), pk.radii, props[:, 7].detach(), 64, 56)
        tiles_w, _, n_tiles = _triton.tile_grid(64, 56)
        ids2, offsets2 = _triton.bin_info(pk.info, n_tiles, tiles_w)
        g = torch.Generator().manual_seed(7)
        gm = torch.randn(m2.shape, generator=g, dtype=dtype)
        gp = torch.randn(props.shape, generator=g, dtype=dtype)
        ga = torch.autograd.grad((m2 * gm).sum() + (props * gp).sum(), a)
        gb = torch.autograd.grad((m2_ref * gm).sum() + (props_ref * gp).sum(), b)
        # cotangents as column views of one buffer (how the compositor's backward gives them)
        rows = torch.cat([gm, gp], 1)
        ctx_like = _triton_projection._Project.apply(*a, cam, [], True)
        gc = torch.autograd.grad(ctx_like, a, (rows[:, :2], rows[:, 2:]))
        out[f"{dtype} rotated={rotated}"] = {
            "culled": int((pk.radii == 0).sum()), "n": len(pk.radii),
            "means2d": rel(m2.detach(), m2_ref.detach()), "props": rel(props.detach(), props_ref.detach()),
            "dtypes": m2.dtype == props.dtype == dtype and all(x.dtype == dtype for x in ga),
            "radii": bool(torch.equal(pk.radii, torch.from_numpy(prep.radii))),
            "rects": bool(torch.equal(pk.info[:4], info_ref)),
            "params": bool(torch.equal(pk.params, par)), "feats": bool(torch.equal(pk.feats, fts)),
            "tiles": bool(torch.equal(ids, ids2) and torch.equal(offsets, offsets2)),
            "grad zero": bool(torch.equal(pk.grad, torch.zeros_like(pk.grad))),
            "grads": [rel(x, y) for x, y in zip(ga, gb)],
            "strided": [bool(torch.equal(x, y)) for x, y in zip(ga, gc)]}
print(json.dumps(out))
"""


def test_triton_projection_matches_numba_in_the_interpreter():
    """The Triton projection kernels against the numba projection (``project_forward``,
    ``project_backward``; tests hold those equal to torch autograd of ``project``) on Gaussians
    taking every branch (behind the camera, nearer than the near plane, off-screen and beyond the
    Jacobian's clamp, zero quaternions, clamped and tied log-scales), float64 and float32, two
    cameras: ``means2d`` and ``props`` within 1e-12 relative in float64 (the same float64
    arithmetic) and 1e-6 in float32, the radii and tile rectangles equal, the packed rows, features
    and tile lists bit for bit those ``bin_tiles`` makes from ``(means2d, props)``, and every
    gradient from random cotangents within 1e-12 / 1e-6 relative of numba's (cotangents given as
    column views of one buffer, as the compositor gives them, read through their strides)."""
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONHASHSEED="0")
    proc = subprocess.run([sys.executable, "-c", _PROJ_SCRIPT], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    for name, c in r.items():
        tol = 1e-12 if "float64" in name else 1e-6
        assert 0 < c["culled"] < c["n"], (name, c)
        assert c["means2d"] < tol and c["props"] < tol and max(c["grads"]) < tol, (name, c)
        assert c["dtypes"] and c["radii"] and c["rects"] and c["params"] and c["feats"] and c["tiles"], (name, c)
        assert c["grad zero"] and all(c["strided"]), (name, c)


_RASTER_SCRIPT = r"""
import importlib, json, sys, torch
from lmgs.render.bench import head_scene
R = importlib.import_module("lmgs.render.rasterize")
R._choose_backend = lambda backend, device: backend  # the triton branch on CPU tensors (the interpreter)
n, res, odd = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "odd"
params, cam = head_scene(n, res)
params = [t.detach() for t in params]
params[2], params[3] = params[2] + 1.5, params[3] + 3.0  # wide, opaque splats: the stop rule is reached
params[0][:8, 2] = -0.3  # behind the camera
params[0][8:12, 2] = 0.005  # nearer than the near plane
params[0][12:20, 0] += 0.6  # off-screen (and beyond the Jacobian's clamp)
if odd:
    cam = type(cam)(cam.world_to_camera, cam.fx, cam.fy, cam.cx, cam.cy, res + 7, res - 5)
g = torch.Generator().manual_seed(1)
sh = 0.3 * torch.randn(n, 9, 3, generator=g)
bg = torch.tensor([0.2, 0.3, 0.4])
OUTS = ("rgb", "alpha", "depth", "normal")
def run(backend, mode, colors, twice=False):
    ps = [t.clone().requires_grad_() for t in params[:4]] + [colors.clone().requires_grad_()]
    out = R.rasterize(*ps, cam, bg, backend=backend, render_mode=mode)
    gen = torch.Generator().manual_seed(0)
    loss = sum((getattr(out, k) * torch.randn(getattr(out, k).shape, generator=gen)).sum() for k in OUTS
               if getattr(out, k) is not None)
    loss.backward(retain_graph=twice)
    grads = [p.grad.clone() for p in ps] + [out.means2d.grad.clone()]
    again = None
    if twice:  # a second backward through the same graph: the same gradients again
        for p in ps:
            p.grad = None
        out.means2d.grad = None
        loss.backward()
        again = [p.grad for p in ps] + [out.means2d.grad]
    with torch.no_grad():
        plain = R.rasterize(*ps, cam, bg, backend=backend, render_mode=mode)
    return out, grads, again, plain
rel = lambda x, y: float((x - y).norm() / y.norm())
res_ = {}
for mode in ("RGB+D+N", "RGB"):
    for colors in ("plain", "sh"):
        c = params[4] if colors == "plain" else sh
        a, ga, _, _ = run("numba", mode, c)
        b, gb, again, plain = run("triton", mode, c, twice=mode == "RGB+D+N")
        res_[f"{mode} {colors}"] = {
            "outs": {k: float((getattr(a, k) - getattr(b, k)).detach().abs().max()) for k in OUTS
                     if getattr(a, k) is not None},
            "none": [k for k in OUTS if (getattr(a, k) is None) != (getattr(b, k) is None)],
            "means2d": float((a.means2d - b.means2d).detach().abs().max()),
            "radii": bool(torch.equal(a.radii, b.radii)), "visible": int(b.visible.sum()), "n": n,
            "grads": [rel(y, x) for x, y in zip(ga, gb)],
            "again": None if again is None else [bool(torch.equal(x, y)) for x, y in zip(gb, again)],
            "no_grad": [bool(torch.equal(getattr(b, k), getattr(plain, k))) for k in OUTS + ("radii", "means2d")
                        if getattr(b, k) is not None],
            "opaque": float((b.alpha > 0.999).float().mean())}
# a camera that needs a gradient: the torch projection and the Triton compositor
ps = [t.clone().requires_grad_() for t in params]
w2c = cam.world_to_camera.clone().requires_grad_()
out = R.rasterize(*ps, type(cam)(w2c, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height), bg, backend="triton")
out.rgb.sum().backward()
res_["camera grad"] = bool(w2c.grad is not None and torch.isfinite(w2c.grad).all() and w2c.grad.abs().sum() > 0)
empty = R.rasterize(*[t[:0] for t in params], cam, bg, backend="triton")
res_["empty"] = bool((empty.alpha == 0).all() and empty.radii.shape == (0,))
print(json.dumps(res_))
"""


@pytest.mark.parametrize("n,res,odd", [(300, 40, False), (600, 40, True)])
def test_triton_backend_matches_numba_in_the_interpreter(n, res, odd):
    """``rasterize(..., backend="triton")`` (the Triton projection, binning and compositing) against
    the numba backend, run through the interpreter on CPU tensors: a head-like scene with
    Gaussians behind the camera, nearer than the near plane and off-screen, at a square size
    and one that is no multiple of the tile, in both render modes, with plain and SH colours.
    Every output within 1e-5 (radii equal), every parameter's gradient and ``means2d.grad``
    within 1e-5 relative; a second backward through the same graph gives the same gradients,
    a call without a gradient the same outputs; a camera needing a gradient takes the torch
    projection; no Gaussians at all render an empty image."""
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONHASHSEED="0")
    args = [sys.executable, "-c", _RASTER_SCRIPT, str(n), str(res), "odd" if odd else "square"]
    proc = subprocess.run(args, capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r.pop("camera grad") and r.pop("empty"), r
    for name, c in r.items():
        assert not c["none"] and c["radii"] and 0 < c["visible"] < c["n"] - 12, (name, c)
        assert max(c["outs"].values()) < 1e-5 and c["means2d"] < 1e-5, (name, c)
        assert max(c["grads"]) < 1e-5, (name, c)
        assert c["again"] is None or all(c["again"]), (name, c)
        assert all(c["no_grad"]), (name, c)
    assert r["RGB+D+N plain"]["opaque"] > 0.05, r
