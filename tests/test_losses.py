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
