"""The vectorised compositing kernels' parts: their exponential against numpy's, the lane
count of ``bench raster`` against a brute-force count, the fp32 peak formula, and the
float64 fallback for tile lists too long for a float32 stop index."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from numba import njit

from lmgs.render import _numba_composite as C
from lmgs.render import _numba_kernels as K
from lmgs.render import flops, rasterize
from lmgs.render._reference import _rasterize
from lmgs.types import Camera


@njit(cache=False)
def _exp_all(x):
    out = np.empty_like(x)
    for i in range(x.size):
        out[i] = C._exp_neg(x[i])
    return out


@pytest.mark.parametrize("dtype,rtol", [(np.float32, 2e-7), (np.float64, 5e-16)])
def test_exp_polynomial_matches_numpy_on_the_kernels_range(dtype, rtol):
    """exp(-s) for 0 <= s <= 6 (the kernels clamp sigma there) to about one unit in the last place."""
    x = np.concatenate([np.linspace(0.0, 6.0, 200_001), [0.0, math.log(2.0) / 2, math.log(255.0), 6.0]]).astype(dtype)
    got = _exp_all(x)
    assert got.dtype == dtype
    want = np.exp(-x.astype(np.float64))
    assert np.max(np.abs(got / want - 1.0)) < rtol


def _brute_force_lanes(rows, ids, offsets, tiles_w, width, height):
    n = 0
    for t in range(offsets.shape[0] - 1):
        ty, tx = divmod(t, tiles_w)
        xs = np.arange(tx * 16, min(tx * 16 + 16, width)) + 0.5
        for k in range(offsets[t], offsets[t + 1]):
            mx, my, ex, ey = (float(rows[ids[k], c]) for c in (0, 1, 14, 15))
            if ex < 0 or not np.any(np.abs(xs - mx) <= ex):
                continue
            for y in range(ty * 16, min(ty * 16 + 16, height)):
                n += 16 * int(abs(y + 0.5 - my) <= ey)
    return n


def test_lanes_hand_counted_and_brute_force():
    rows = np.zeros((3, 16), np.float32)
    rows[0, [0, 1, 14, 15]] = [16.0, 8.0, 3.0, 3.0]  # columns 13..18 (two tiles), rows 5..10
    rows[1, [0, 1, 14, 15]] = [40.0, 40.0, 2.0, 2.0]  # outside the 32x32 image's tiles it is listed in
    rows[2, [0, 1, 14, 15]] = [5.0, 5.0, -1.0, -1.0]  # no box (transparent)
    ids = np.array([0, 0, 1, 2, 0], np.int64)
    offsets = np.array([0, 1, 2, 4, 5], np.int64)  # tiles 0, 1, 2, 3 of a 2 x 2 grid
    # tile 0: 6 rows; tile 1: 6 rows; tile 2: Gaussians 1 and 2 add nothing; tile 3 (rows 16..31): none
    assert flops.lanes(rows, ids, offsets, 2, 32, 32) == 16 * 12
    g = np.random.default_rng(3)
    n, w, h = 60, 45, 37
    rows = np.zeros((n, 16), np.float32)
    rows[:, 0], rows[:, 1] = g.uniform(-5, w + 5, n), g.uniform(-5, h + 5, n)
    rows[:, 14], rows[:, 15] = g.uniform(-1, 9, n), g.uniform(-1, 9, n)
    tiles_w, n_tiles = 3, 9
    lists = [g.choice(n, size=g.integers(0, 20), replace=False) for _ in range(n_tiles)]
    ids = np.concatenate(lists).astype(np.int64)
    offsets = np.concatenate([[0], np.cumsum([len(x) for x in lists])]).astype(np.int64)
    assert flops.lanes(rows, ids, offsets, tiles_w, w, h) == _brute_force_lanes(rows, ids, offsets, tiles_w, w, h) > 0


def test_fp32_peak_is_cores_lanes_fma_clock():
    info = "processor\t: 0\ncpu MHz\t\t: 2500.000\nflags\t\t: fpu sse avx avx2 fma\n"
    assert flops.cpu_peak_gflops(2, info) == {"gflops": 2 * 8 * 2 * 2.5, "cores": 2, "lanes": 8, "ghz": 2.5}
    assert flops.cpu_peak_gflops(4, info.replace("fma", "fma avx512f"))["gflops"] == 4 * 16 * 2 * 2.5
    assert math.isnan(flops.cpu_peak_gflops(1, "flags : sse\n")["gflops"])
    assert flops.fwd_flops_per_lane(7) - flops.fwd_flops_per_lane(3) == 4 * flops.FWD_FLOPS_PER_FEATURE


def test_float32_inputs_past_the_stop_index_limit_composite_in_float64(monkeypatch):
    """With more intersections than a float32 stop index holds exactly, the rows go to float64;
    the image still equals the dense reference (forward and gradients)."""
    seen = []
    forward = C.forward

    def spy(rows, *a):
        seen.append(rows.dtype)
        return forward(rows, *a)

    monkeypatch.setattr(C, "F32_MAX_ISECT", 1)
    monkeypatch.setattr(C, "forward", spy)
    g = torch.Generator().manual_seed(4)
    p = [torch.randn(40, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0]), torch.randn(40, 4, generator=g),
         torch.randn(40, 3, generator=g) * 0.5 - 3.0, torch.randn(40, generator=g), torch.rand(40, 3, generator=g)]
    p = [t.requires_grad_() for t in p]
    cam = Camera(torch.eye(4), 40.0, 42.0, 20.3, 15.8, 40, 32)
    out, ref = rasterize(*p, cam, backend="numba"), _rasterize(*p, cam)
    assert seen == [np.float64]
    torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-5, rtol=0)
    ga = torch.autograd.grad(out.rgb.sum() + out.alpha.sum(), p)
    gb = torch.autograd.grad(ref.rgb.sum() + ref.alpha.sum(), p)
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_depth_order_is_a_stable_argsort_of_the_visible():
    rng = np.random.default_rng(0)
    for n in (0, 1, 7, 5000):
        d = rng.normal(size=n) * 10.0 ** rng.integers(-3, 3, size=n)
        d[: n // 3] = np.round(d[: n // 3], 1)  # many ties, and equal depths of both signs
        if n > 3:
            d[1], d[2] = 0.0, -0.0
        vis = rng.random(n) < 0.8
        ids = np.flatnonzero(vis)
        want = ids[np.argsort(d[ids], kind="stable")]
        assert np.array_equal(K.depth_order(d, vis), want)


def test_bin_tiles_lists_each_tiles_gaussians_front_to_back():
    rng = np.random.default_rng(1)
    n, tiles_w, tiles_h = 3000, 7, 5
    x0, y0 = rng.integers(0, tiles_w, n), rng.integers(0, tiles_h, n)
    rects = np.stack([x0, np.minimum(x0 + rng.integers(0, 4, n), tiles_w), y0,
                      np.minimum(y0 + rng.integers(0, 3, n), tiles_h)], 1).astype(np.int64)
    order = rng.permutation(n)[: n - 100].astype(np.int64)
    offsets, ids = K.bin_tiles(rects, order, tiles_w * tiles_h, tiles_w, 3)
    for n_chunks in (1, 2, 5):
        o2, i2 = K.bin_tiles(rects, order, tiles_w * tiles_h, tiles_w, n_chunks)
        assert np.array_equal(o2, offsets) and np.array_equal(i2, ids)
    for t in range(tiles_w * tiles_h):
        tx, ty = t % tiles_w, t // tiles_w
        want = [g for g in order if rects[g, 0] <= tx < rects[g, 1] and rects[g, 2] <= ty < rects[g, 3]]
        assert ids[offsets[t]:offsets[t + 1]].tolist() == want


def test_reduce_grads_sums_in_intersection_order():
    rng = np.random.default_rng(2)
    ids = rng.integers(0, 900, 20000).astype(np.int64)
    grad = (rng.normal(size=(20000, C.GROW)) * 10.0 ** rng.integers(-4, 4, (20000, 1))).astype(np.float32)
    want = np.zeros((1000, C.GROW), np.float32)
    np.add.at(want, ids, grad)  # sequential, in index order
    for n_chunks in (1, 2, 3):
        assert np.array_equal(C.reduce_grads(grad, ids, 1000, n_chunks), want)
