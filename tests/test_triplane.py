"""Tri-plane hash encoder: both paths against the naive per-point twin, value and gradient."""

import math

import pytest
import torch

from lmgs.config import TriplaneConfig
from lmgs.encoders.triplane import TriplaneEncoder, _triplane_encode_reference, level_resolutions
from lmgs.errors import InputError

# 4 levels (8, 16, 32, 64), table 2^9: the first two levels are dense, the last two hashed
SMALL = TriplaneConfig(n_levels=4, n_features=2, log2_table_size=9, base_resolution=8, finest_resolution=64)


def _encoder(cfg=SMALL, dtype=torch.float64):
    torch.manual_seed(0)
    enc = TriplaneEncoder(cfg, box_min=[-1.0, -2.0, 0.0], box_max=[1.0, 2.0, 3.0]).to(dtype)
    with torch.no_grad():
        enc.embeddings.normal_()
    return enc


def test_level_layout_has_dense_and_hashed_levels():
    res = level_resolutions(SMALL)
    assert res == [8, 16, 32, 64]
    enc = _encoder()
    assert enc.dense.tolist() == [(r + 1) ** 2 <= 512 for r in res] == [True, True, False, False]
    assert enc.out_dim == 3 * 4 * 2


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_matches_naive_loop_value_and_gradient(backend):
    enc = _encoder()
    g = torch.Generator().manual_seed(1)
    # inside the box, on its faces and outside it (clamped)
    x = torch.rand(12, 3, generator=g, dtype=torch.float64) * torch.tensor([2.4, 4.8, 3.6], dtype=torch.float64)
    x = x - torch.tensor([1.2, 2.4, 0.3], dtype=torch.float64)
    x[0] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)  # the far corner: u = 1 exactly
    x[1] = torch.tensor([-1.0, -2.0, 0.0], dtype=torch.float64)
    x.requires_grad_(True)
    out = enc(x, backend=backend)
    ref = _triplane_encode_reference(enc, x)
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)
    cot = torch.randn(out.shape, generator=g, dtype=torch.float64)
    gx, gt = torch.autograd.grad(out, [x, enc.embeddings], cot)
    rx, rt = torch.autograd.grad(ref, [x, enc.embeddings], cot)
    torch.testing.assert_close(gt, rt, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(gx, rx, rtol=1e-9, atol=1e-9)


def test_numba_path_passes_gradcheck():
    enc = _encoder(TriplaneConfig(n_levels=2, log2_table_size=6, base_resolution=4, finest_resolution=8))
    x = (torch.rand(4, 3, dtype=torch.float64) * 0.8 + 0.1) * torch.tensor([2.0, 4.0, 3.0], dtype=torch.float64)
    x = (x - torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64)).requires_grad_(True)
    # finite differences in the point coordinates (the table gradient is linear and checked above)
    assert torch.autograd.gradcheck(_with_table(enc, enc.embeddings.detach()), (x,))


def _with_table(enc, table):
    def f(p):
        from lmgs.encoders.triplane import _NumbaTriplane

        u = enc.normalize(p)
        return _NumbaTriplane.apply(u, table, enc.res, enc.dense, enc.offsets, enc.table_size)

    return f


def test_bilinear_on_a_dense_level_by_hand():
    # one level of resolution 4 on [0,1]^3: vertex (i, j) holds feature i + 10 j on every plane
    cfg = TriplaneConfig(n_levels=1, n_features=1, log2_table_size=8, base_resolution=4, finest_resolution=4)
    enc = TriplaneEncoder(cfg, box_min=[0, 0, 0], box_max=[1, 1, 1]).double()
    with torch.no_grad():
        for plane in range(3):
            for j in range(5):
                for i in range(5):
                    enc.embeddings[plane * 25 + i + 5 * j] = i + 10 * j
    p = torch.tensor([[0.3, 0.55, 0.9]], dtype=torch.float64)
    out = enc(p)[0]
    # bilinear interpolation of a linear function is exact: value = 4 u_a + 40 u_b
    expect = [4 * 0.3 + 40 * 0.55, 4 * 0.55 + 40 * 0.9, 4 * 0.3 + 40 * 0.9]
    assert torch.allclose(out, torch.tensor(expect, dtype=torch.float64))


def test_hash_matches_instant_ngp_formula():
    cfg = TriplaneConfig(n_levels=1, n_features=1, log2_table_size=4, base_resolution=8, finest_resolution=8)
    enc = TriplaneEncoder(cfg, box_min=[0, 0, 0], box_max=[1, 1, 1]).double()
    with torch.no_grad():
        enc.embeddings.copy_(torch.arange(48, dtype=torch.float64)[:, None])
    # point exactly on vertex (3, 5) of the xy plane: its feature is the table entry h(3, 5)
    p = torch.tensor([[3 / 8, 5 / 8, 0.0]], dtype=torch.float64)
    h = (3 ^ (5 * 2654435761)) % 16
    assert float(enc(p)[0, 0].detach()) == pytest.approx(h)


def test_input_errors():
    enc = TriplaneEncoder(SMALL)
    with pytest.raises(InputError):
        enc(torch.zeros(4, 2))
    with pytest.raises(InputError):
        TriplaneEncoder(SMALL, box_min=[0, 0, 0], box_max=[1, 0, 1])
    assert not math.isnan(float(enc(torch.full((1, 3), 1e6)).sum().detach()))
