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
