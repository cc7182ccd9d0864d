"""The numba projection (forward and its hand-written backward) against torch autograd of
``project``, the definition, on random Gaussians with every branch of the formulas taken:
behind the camera, nearer than the near plane, off-screen (culled, and beyond the
field-of-view clamp of the Jacobian), zero quaternions, clamped log-scales, tied scales."""

from __future__ import annotations

import math

import pytest
import torch

from lmgs.render import _cpu, rasterize
from lmgs.render._projection import project
from lmgs.types import Camera


def _gaussians(n=400, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.5, 1.2, 1.0], dtype=dtype)
    means[:, 2] += 2.5
    means[:20, 2] = -torch.rand(20, generator=g, dtype=dtype) - 0.5  # behind the camera
    means[20:30, 2] = 0.005 + 0.004 * torch.rand(10, generator=g, dtype=dtype)  # nearer than 0.01
    means[30:40, 0] = 8.0 + torch.rand(10, generator=g, dtype=dtype)  # far off-screen, beyond the FOV clamp
    means[40:45, 1] = -9.0  # off-screen above
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[45:48] = 0.0  # zero norm: the identity
    log_scales = torch.randn(n, 3, generator=g, dtype=dtype) * 0.6 - 2.5
    log_scales[48:52, 0] = -40.0  # clamped below
    log_scales[52:54, 1] = 12.0  # clamped above (an axis of e^10 m) ...
    means[52:54] = torch.tensor([[2e4, -1e4, 1e5], [-3e4, 2e4, 1.2e5]], dtype=dtype)  # ... far away: ~10 px
    log_scales[54:58] = -2.0  # equal scales: the normal's argmin tie
    opacity_logits = torch.randn(n, generator=g, dtype=dtype) * 2
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return [means, quats, log_scales, opacity_logits, colors]


def _camera(dtype=torch.float64, rotated=False):
    w2c = torch.eye(4, dtype=dtype)
    if rotated:
        c, s = math.cos(0.3), math.sin(0.3)
        w2c = torch.tensor([[c, 0, s, 0.1], [0, 1, 0, -0.2], [-s, 0, c, 0.4], [0, 0, 0, 1]], dtype=dtype)
    return Camera(w2c, 60.0, 55.0, 33.0, 27.5, 64, 56)


def _torch_outputs(params, cam):
    p = project(*params, None, cam)
    return (p.means2d, torch.cat([p.conics, p.opacities[:, None], p.features], 1)), p


@pytest.mark.parametrize("rotated", [False, True])
def test_forward_equals_torch_projection(rotated):
    params, cam = _gaussians(seed=1), _camera(rotated=rotated)
    (m_ref, props_ref), p = _torch_outputs(params, cam)
    means2d, props, prep = _cpu.project_numba(*[t.detach() for t in params], cam)
    vis = p.radii > 0
    assert torch.equal(torch.from_numpy(prep.radii), p.radii)
    assert 0 < int(vis.sum()) < len(vis)
    torch.testing.assert_close(means2d, m_ref.detach(), atol=1e-10, rtol=1e-12)
    torch.testing.assert_close(props, props_ref.detach(), atol=1e-10, rtol=1e-12)
    torch.testing.assert_close(torch.from_numpy(prep.depths), p.depths, atol=1e-12, rtol=0)


@pytest.mark.parametrize("rotated", [False, True])
def test_backward_equals_torch_autograd(rotated):
    """Random cotangents on every output (culled Gaussians included: a loss on ``means2d`` or the
    conics reaches them too); gradients to every input equal torch autograd's."""
    params = [t.requires_grad_() for t in _gaussians(seed=2)]
    cam = _camera(rotated=rotated)
    (m_ref, props_ref), _ = _torch_outputs(params, cam)
    g = torch.Generator().manual_seed(3)
    gm, gp = torch.randn(m_ref.shape, generator=g, dtype=m_ref.dtype), torch.randn(props_ref.shape, generator=g,
                                                                                     dtype=m_ref.dtype)
    ref = torch.autograd.grad((m_ref * gm).sum() + (props_ref * gp).sum(), params)
    means2d, props = _cpu.project_autograd(*params, cam)
    got = torch.autograd.grad((means2d * gm).sum() + (props * gp).sum(), params)
    # Behind the near plane the projection uses z = 1, a constant: the gradient to a mean has no
    # camera-z component (mc = R m + t, so dL/dmc = R dL/dm), while x and y still receive one.
    rot, t = cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3]
    behind = (params[0].detach() @ rot.T + t)[:, 2] < 0.01
    assert 20 <= int(behind.sum()) < len(behind)
    for which, grads in (("numba", got), ("torch", ref)):
        g_cam = grads[0] @ rot.T
        assert g_cam[behind, 2].abs().max() < 1e-12, which
        assert g_cam[behind, :2].abs().min() > 0, which
        assert g_cam[~behind, 2].abs().max() > 1e-3, which
    for name, a, b in zip(("means", "quats", "log_scales", "opacity_logits", "colors"), got, ref):
        assert b.abs().max() > 0, name
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10, msg=lambda m: f"{name}: {m}")
    assert torch.all(got[1][45:48] == 0)  # zero quaternions
    assert torch.all(got[2][48:52, 0] == 0) and torch.all(got[2][52:54, 1] == 0)  # clamped scales


def test_gradcheck():
    params = [t[:40].clone().requires_grad_() for t in _gaussians(seed=4)]
    cam = _camera(rotated=True)
    params[2].data[:3] = params[2].data[:3].clamp(-29.0, 9.0)  # keep finite differences off the clamp bounds

    def f(*ps):
        return _cpu.project_autograd(*ps, cam)

    assert torch.autograd.gradcheck(f, params, eps=1e-6, atol=1e-7, rtol=1e-6)


def test_float32_inputs_give_float32_outputs_and_gradients():
    """float32 inputs project and composite in float32 kernels (their own ``exp`` polynomial
    and constants); image and gradients equal the float64 run's to float32 precision."""
    base = _gaussians(n=100, seed=5)
    runs = []
    for dtype in (torch.float32, torch.float64):
        params = [t.to(dtype).requires_grad_() for t in base]
        out = rasterize(*params, _camera(dtype=dtype), backend="numba")
        loss = out.rgb.sum() + out.depth.sum()
        runs.append((out, torch.autograd.grad(loss, params)))
    (o32, g32), (o64, g64) = runs
    assert o32.rgb.dtype == torch.float32 and o32.means2d.dtype == torch.float32
    assert o64.alpha.max() > 0.5 and o64.rgb.std() > 0.01  # a picture, not an empty frame
    for name in ("rgb", "depth", "alpha", "means2d"):
        torch.testing.assert_close(getattr(o32, name).double(), getattr(o64, name), atol=2e-4, rtol=1e-4,
                                   msg=lambda m, name=name: f"{name}: {m}")
    for name, a, b in zip(("means", "quats", "log_scales", "opacity_logits", "colors"), g32, g64):
        assert a.dtype == torch.float32, name
        scale = b.abs().max()
        assert scale > 0 and (a.double() - b).abs().max() < 2e-3 * scale, name


def test_a_camera_needing_a_gradient_goes_through_the_torch_projection():
    """The numba projection gives no gradient to the camera: with ``world_to_camera`` requiring
    one, the numba backend projects in torch; image and gradients (the camera's included)
    equal the dense reference."""
    from lmgs.render._reference import _rasterize

    g = torch.Generator().manual_seed(6)
    p = [torch.randn(60, 3, generator=g, dtype=torch.float64) * 0.4 + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64),
         torch.randn(60, 4, generator=g, dtype=torch.float64), torch.randn(60, 3, generator=g, dtype=torch.float64) * 0.5 - 3.0,
         torch.randn(60, generator=g, dtype=torch.float64), torch.rand(60, 3, generator=g, dtype=torch.float64)]
    grads = []
    for fn, kw in ((rasterize, {"backend": "numba"}), (_rasterize, {})):
        params = [t.clone().requires_grad_() for t in p]
        w2c = _camera(rotated=True).world_to_camera.clone().requires_grad_()
        cam = Camera(w2c, 60.0, 55.0, 33.0, 27.5, 64, 56)
        out = fn(*params, cam, **kw)
        grads.append((out.rgb.detach(), *torch.autograd.grad(out.rgb.sum() + 0.5 * out.depth.sum(), [*params, w2c])))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
    assert grads[0][-1].abs().max() > 0
