"""The Geometry Regularizer's terms on hand-computed cases."""

import math

import pytest
import torch

from lmgs import losses


def _normals():
    # 2x2 image: a rendered normal equal to the reference (error 0), one at 90 degrees (error 1),
    # one at 60 degrees (error 1 - cos 60 = 0.5, and unnormalised: the loss normalises it), one masked out
    ref = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]])
    s60 = math.sin(math.radians(60))
    rend = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], [[3 * s60, 0.0, 3 * 0.5], [0.0, 1.0, 0.0]]])
    mask = torch.tensor([[True, True], [True, False]])
    return rend, ref, mask


def test_normal_loss_is_the_papers_sum_or_a_per_pixel_mean():
    rend, ref, mask = _normals()
    assert float(losses.normal_loss(rend, ref, mask)) == pytest.approx(1.5, abs=1e-6)  # 0 + 1 + 0.5
    assert float(losses.normal_loss(rend, ref, mask, "mean")) == pytest.approx(0.5, abs=1e-6)
    empty = torch.zeros(2, 2, dtype=torch.bool)
    assert float(losses.normal_loss(rend, ref, empty, "mean")) == 0.0  # no surface: no term, not NaN
    with pytest.raises(ValueError, match="reduce"):
        losses.normal_loss(rend, ref, mask, "max")


def test_scale_invariant_depth_hand_case():
    ref = torch.tensor([[1.0, 2.0], [4.0, 0.0]])  # ref 0: no surface there
    mask = torch.ones(2, 2, dtype=torch.bool)
    # a depth off by one global scale costs nothing
    assert float(losses.scale_invariant_depth(ref * 3.7, ref, mask)) == pytest.approx(0.0, abs=1e-6)
    # delta = log(D / ref) = (0, log 2, 0) on the three valid pixels: mean(delta^2) - mean(delta)^2
    d = ref * torch.tensor([[1.0, 2.0], [1.0, 1.0]])
    l2 = math.log(2.0)
    assert float(losses.scale_invariant_depth(d, ref, mask)) == pytest.approx(l2**2 / 3 - (l2 / 3) ** 2, rel=1e-5)


def test_geometry_weights_the_two_terms_and_masks_by_alpha():
    rend, ref_n, _ = _normals()
    ref_d = torch.tensor([[1.0, 2.0], [4.0, 3.0]])
    depth = (ref_d * torch.tensor([[1.0, 2.0], [1.0, 1.0]]))[..., None]
    alpha = torch.tensor([[1.0, 1.0], [1.0, 0.2]])[..., None]  # the last pixel: the render has no surface
    mask = alpha[..., 0] > 0.5
    si = float(losses.scale_invariant_depth(depth[..., 0], ref_d, mask))
    got = losses.geometry(depth, rend, alpha, ref_d, ref_n, lambda_d=0.3, lambda_n=0.01)
    assert float(got) == pytest.approx(0.3 * si + 0.01 * 1.5, rel=1e-5)
    got = losses.geometry(depth, rend, alpha, ref_d, ref_n, lambda_d=0.3, lambda_n=0.01, normal_reduce="mean")
    assert float(got) == pytest.approx(0.3 * si + 0.01 * 0.5, rel=1e-5)


@pytest.mark.parametrize("reduce", ["sum", "mean"])
@pytest.mark.parametrize("case", ["random", "one pixel", "no surface"])
def test_geometry_as_masked_sums_equals_the_gathered_terms(reduce, case):
    """``gather=False`` (no read-back on a GPU) gives the value and the gradients of the gathered terms,
    down to the hand cases where the depth term has fewer than two pixels."""
    g = torch.Generator().manual_seed(3)
    h, w = 24, 20
    ref_d = 0.5 + torch.rand(h, w, generator=g)
    ref_d[:3] = 0.0  # no reference surface on the top rows
    ref_n = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    alpha = torch.rand(h, w, 1, generator=g)
    if case == "one pixel":
        alpha = torch.zeros(h, w, 1)
        alpha[10, 7] = 0.9
    elif case == "no surface":
        alpha = torch.zeros(h, w, 1)
    depth0 = (ref_d * (1 + 0.2 * torch.rand(h, w, generator=g)) + 0.1)[..., None]
    normal0 = torch.randn(h, w, 3, generator=g)
    out = []
    for gather in (True, False):
        depth, normal = depth0.clone().requires_grad_(), normal0.clone().requires_grad_()
        loss = losses.geometry(depth, normal, alpha, ref_d, ref_n, 0.3, 0.02, reduce, gather=gather)
        loss.backward()
        out.append((loss.detach(), depth.grad, normal.grad))
    (la, da, na), (lb, db, nb) = out
    torch.testing.assert_close(lb, la, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(db, da, rtol=1e-4, atol=1e-8)
    torch.testing.assert_close(nb, na, rtol=1e-4, atol=1e-8)
    if case == "random":
        assert float(la) > 0 and float(da.abs().max()) > 0
    else:
        assert float(da.abs().max()) == 0.0  # fewer than two pixels: no depth term


@pytest.mark.parametrize("gather", [True, False])
def test_a_term_of_weight_zero_adds_exactly_nothing(gather):
    """A zero weight (the normal term on derived priors, ``train.derived_normal_weight = 0``) leaves the
    term out: the value and the depth's gradient are the bits of computing it times zero, the normals
    get none, and they may be absent."""
    g = torch.Generator().manual_seed(5)
    h, w = 24, 20
    ref_d = 0.5 + torch.rand(h, w, generator=g)
    ref_n = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    alpha = torch.rand(h, w, 1, generator=g)
    depth0 = (ref_d * (1 + 0.2 * torch.rand(h, w, generator=g)))[..., None]
    normal0 = torch.randn(h, w, 3, generator=g)
    depth = depth0.clone().requires_grad_()
    mask = (alpha[..., 0] > 0.5) & (ref_d > 0)
    want = (0.3 * losses.scale_invariant_depth(depth[..., 0], ref_d, mask, gather)
            + 0.0 * losses.normal_loss(normal0, ref_n, mask, "mean", gather))
    want.backward()
    want_grad = depth.grad.clone()
    depth.grad = None
    normal = normal0.clone().requires_grad_()
    got = losses.geometry(depth, normal, alpha, ref_d, ref_n, 0.3, 0.0, "mean", gather=gather)
    got.backward()
    assert float(got.detach()) > 0 and torch.equal(got.detach(), want.detach())
    assert torch.equal(depth.grad, want_grad) and normal.grad is None
    depth.grad = None
    alone = losses.geometry(depth, None, alpha, ref_d, None, 0.3, 0.0, "mean", gather=gather)
    alone.backward()
    assert torch.equal(alone.detach(), want.detach()) and torch.equal(depth.grad, want_grad)
    # both weights zero: a zero that still reaches the depth (so a caller's backward has a graph)
    nothing = losses.geometry(depth, None, alpha, ref_d, None, 0.0, 0.0, gather=gather)
    assert float(nothing.detach()) == 0.0 and nothing.requires_grad


def _ssim_3dgs(img, ref):
    """3DGS's ``ssim`` as its training code writes it: each statistic a padded depthwise
    convolution with the 11-tap Gaussian (sigma 1.5), differentiated by autograd."""
    import torch.nn.functional as F

    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
    g = torch.exp(-((torch.arange(11, dtype=x.dtype) - 5) ** 2) / (2 * 1.5**2))
    w = (g[:, None] * g[None, :] / g.sum() ** 2).expand(3, 1, 11, 11)

    def blur(t):
        return F.conv2d(t, w, padding=5, groups=3)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean()


@pytest.mark.parametrize("path", ["numba", "torch"])  # the CPU's kernels; the torch ops a GPU runs
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ssim_and_its_closed_form_gradient_are_the_3dgs_loss(dtype, path, monkeypatch):
    if path == "torch":
        monkeypatch.setattr(losses, "_on_numba", lambda t: False)
    g = torch.Generator().manual_seed(0)
    img = torch.rand(37, 29, 3, generator=g, dtype=dtype, requires_grad=True)
    ref = (img.detach() * 0.7 + 0.3 * torch.rand(37, 29, 3, generator=g, dtype=dtype)).requires_grad_()
    ours, theirs = losses.ssim(img, ref), _ssim_3dgs(img, ref)
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(ours, theirs, **tol)
    torch.testing.assert_close(losses.ssim_autograd(img, ref), theirs, **tol)  # the form the benchmark times
    got = torch.autograd.grad(ours, (img, ref))
    want = torch.autograd.grad(theirs, (img, ref))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, **tol)
    if dtype == torch.float64:  # and against finite differences, on windows that need no padding
        x = torch.rand(1, 3, 19, 23, generator=g, dtype=dtype, requires_grad=True)
        y = torch.rand(1, 3, 19, 23, generator=g, dtype=dtype, requires_grad=True)
        assert torch.autograd.gradcheck(losses._SSIMMap.apply, (x, y))


def _head_over_background(h, w, shift=(0.0, 0.0)):
    """A blob of Gaussians rendered by the CPU rasterizer over a background, as a training step
    composites a head: ``(params, render function, background, frame)``."""
    from lmgs.render import rasterize
    from lmgs.types import Camera

    g = torch.Generator().manual_seed(1)
    n = 150
    means = torch.randn(n, 3, generator=g) * 0.12 + torch.tensor([shift[0], shift[1], 3.0])
    params = [means, torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g) * 0.3 - 3.3,
              torch.randn(n, generator=g), torch.rand(n, 3, generator=g)]
    params = [p.requires_grad_() for p in params]
    cam = Camera(torch.eye(4), 120.0, 120.0, w / 2, h / 2, w, h)
    bg = torch.rand(h, w, 3, generator=g)
    frame = (bg * 0.8 + 0.2 * torch.rand(h, w, 3, generator=g)).clamp(0, 1)

    def render():
        out = rasterize(*params, cam, None, backend="numba", render_mode="RGB")
        return out.rgb + (1 - out.alpha) * bg, out.alpha[..., 0] > 0

    return params, render, bg, frame


@pytest.mark.parametrize("shift", [(0.0, 0.0), (-0.9, 0.6)])  # a head in the middle; one cut by the frame's corner
def test_the_loss_over_the_box_around_the_head_is_the_full_frame_loss(shift):
    params, render, bg, frame = _head_over_background(96, 120, shift)
    img, cover = render()
    assert 0.05 < cover.float().mean() < 0.5  # the head covers part of the frame, so the box is a crop
    assert torch.equal(img[~cover], bg[~cover])  # the render is its background where nothing covers it
    full = losses.photometric(img, frame, 0.2)
    want = torch.autograd.grad(full, params)
    box = losses.CoveredPhotometric(0.2)
    for _ in range(2):  # the background's terms from the tables made on the first call, then kept
        img, cover = render()
        value = box(img, frame, bg, cover, key=7)
        torch.testing.assert_close(value, full, rtol=1e-6, atol=0)
        for a, b in zip(torch.autograd.grad(value, params), want):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7 * float(b.abs().max()))
    nothing = torch.zeros(96, 120, dtype=torch.bool)  # a frame nothing covers: the full-frame loss
    torch.testing.assert_close(box(bg.clone().requires_grad_(), frame, bg, nothing, key=8), losses.photometric(bg, frame, 0.2))


def test_the_cpu_ssim_kernels_give_the_same_bits_on_any_thread_count():
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one thread on this host")
    g = torch.Generator().manual_seed(3)
    img = torch.rand(40, 33, 3, generator=g, requires_grad=True)
    ref = torch.rand(40, 33, 3, generator=g)
    runs = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        before = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            value = losses.ssim(img, ref)
            runs.append((value.detach(), torch.autograd.grad(value, img)[0]))
        finally:
            numba.set_num_threads(before)
    assert all(torch.equal(a, b) for a, b in zip(*runs))
