"""The numba rasterizer's parallel parts give the same bits whatever the thread or chunk count:
the depth sort, the tile binning, the per-Gaussian gradient sums, the tile deal of the
compositing kernels, and whole renders with their gradients (the backward's reused buffer
too); float32 inputs project as their float64 copies; ``bench raster --threads`` rows."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from lmgs.render import _cpu, rasterize
from lmgs.render import _numba_composite as C
from lmgs.render import _numba_kernels as K
from lmgs.render import _numba_projection as NP
from lmgs.render.bench import head_scene


def _rects(rng, n, tiles_w, tiles_h):
    x0, y0 = rng.integers(0, tiles_w, n), rng.integers(0, tiles_h, n)
    return np.stack([x0, np.minimum(x0 + rng.integers(0, 4, n), tiles_w), y0,
                     np.minimum(y0 + rng.integers(0, 3, n), tiles_h)], 1).astype(np.int64)


@pytest.mark.parametrize("n", [0, 3, 20_000, 70_001])
def test_parallel_depth_sort_is_the_stable_argsort_for_any_chunk_count(n):
    rng = np.random.default_rng(n)
    d = rng.normal(size=n) * 10.0 ** rng.integers(-3, 3, size=n)
    d[: n // 2] = np.round(d[: n // 2], 2)  # many ties
    if n > 3:
        d[1], d[2] = 0.0, -0.0
    vis = rng.random(n) < 0.9
    ids = np.flatnonzero(vis)
    want = ids[np.argsort(d[ids], kind="stable")]
    for n_chunks in (1, 2, 3, 16):
        assert np.array_equal(K.depth_order(d, vis, n_chunks), want)
        assert np.array_equal(K._depth_order_parallel(d, vis, n_chunks, 100), want)
    near = 0.6 + 1e-3 * rng.random(n)  # the head scenes' depths: the high bytes all equal (skipped passes)
    assert np.array_equal(K._depth_order_parallel(near, vis, 5, 100), ids[np.argsort(near[ids], kind="stable")])


def test_binning_and_gradient_sums_are_the_same_for_any_chunk_count():
    rng = np.random.default_rng(1)
    n, tiles_w, tiles_h = 5000, 9, 6
    rects = _rects(rng, n, tiles_w, tiles_h)
    order = rng.permutation(n)[: n - 300].astype(np.int64)
    offsets, ids = K.bin_tiles(rects, order, tiles_w * tiles_h, tiles_w, 1)
    grad = (rng.normal(size=(ids.shape[0], C.GROW)) * 10.0 ** rng.integers(-4, 4, (ids.shape[0], 1)))
    grad = grad.astype(np.float32)
    want = np.zeros((n, C.GROW), np.float32)
    np.add.at(want, ids, grad)  # sequential, in intersection order
    for n_chunks in (1, 2, 7, 16):
        o2, i2 = K.bin_tiles(rects, order, tiles_w * tiles_h, tiles_w, n_chunks)
        assert np.array_equal(o2, offsets) and np.array_equal(i2, ids)
        assert np.array_equal(C.reduce_grads(grad, ids, n, n_chunks), want)


def test_the_backward_writes_every_gradient_row_of_a_reused_buffer():
    params, cam = head_scene(3000, 64, seed=7, requires_grad=False)
    p = [t.requires_grad_() for t in params]
    out = rasterize(*p, cam, backend="numba")
    torch.autograd.grad(out.rgb.sum(), p)  # makes this thread's buffer
    grads = []
    for fill in (np.nan, 0.0):
        assert _cpu._SCRATCH.grad
        for buf in _cpu._SCRATCH.grad.values():
            buf[:] = fill
        out = rasterize(*p, cam, backend="numba")
        grads.append(torch.autograd.grad(out.rgb.sum() + out.alpha.sum(), p))
    for a, b in zip(*grads):
        assert torch.equal(a, b)


def test_tiles_are_dealt_once_each_and_balanced():
    rng = np.random.default_rng(3)
    counts = rng.integers(0, 200, 300) * (rng.random(300) < 0.7)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    for n_chunks in (1, 3, 16):
        order = K.balance_tiles(offsets, n_chunks)
        assert order.shape[0] == n_chunks
        dealt = order[order >= 0]
        assert np.array_equal(np.sort(dealt), np.flatnonzero(counts))  # every busy tile once, no empty one
        for row in order:
            row = row[row >= 0]
            assert np.all(np.diff(row) > 0)
        cost = np.where(counts > 0, counts + K.TILE_COST, 0)
        loads = [cost[row[row >= 0]].sum() for row in order]
        assert max(loads) <= np.mean(loads) + cost.max()
    assert np.array_equal(K.balance_tiles(np.zeros(5, np.int64), 4), np.full((4, 1), -1))


def _render_and_grads(params, cam):
    params = [t.detach().clone().requires_grad_() for t in params]
    out = rasterize(*params, cam, torch.tensor([0.2, 0.3, 0.4], dtype=params[0].dtype), backend="numba")
    w = torch.linspace(-1.0, 1.0, out.rgb.numel(), dtype=out.rgb.dtype).view_as(out.rgb)
    loss = (out.rgb * w).sum() + out.alpha.sum() + 0.3 * out.depth.sum() + 0.7 * out.normal.sum()
    loss.backward()
    with torch.no_grad():
        rgb_only = rasterize(*params, cam, None, backend="numba", render_mode="RGB")
    return [out.rgb, out.alpha, out.depth, out.normal, out.means2d.grad, *(t.grad for t in params), rgb_only.rgb]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_renders_and_gradients_are_the_same_bits_for_any_thread_count(monkeypatch, dtype):
    """Chunk counts as 1, 3 and 16 threads would choose them (run on the threads there are), and
    numba really on 1 and on every thread it has: the same bits."""
    params, cam = head_scene(20_000, 128, seed=5, requires_grad=False)
    params = [t.to(dtype) for t in params]
    prev = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        want = _render_and_grads(params, cam)
    finally:
        numba.set_num_threads(prev)
    assert _cpu._threads() == prev
    got = [_render_and_grads(params, cam)]
    for p in (1, 3, 16):
        monkeypatch.setattr(_cpu, "_threads", lambda p=p: p)
        got.append(_render_and_grads(params, cam))
    for g in got:
        for a, b in zip(g, want):
            assert torch.equal(a, b)


def test_float32_parameters_project_as_their_float64_copies():
    params, cam = head_scene(2000, 96, seed=6, requires_grad=False)
    f32 = tuple(t.numpy() for t in params)
    f64 = tuple(a.astype(np.float64) for a in f32)
    g_rows = np.random.default_rng(0).normal(size=(2000, 2 + NP.NPROP)).astype(np.float32)
    outs = []
    for arrays in (f32, f64):  # float32 outputs, and float64 ones rounded to float32 here
        dt = arrays[0].dtype
        rows, m2, props = np.empty((2000, K.ROW), dt), np.empty((2000, 2), dt), np.empty((2000, NP.NPROP), dt)
        res = NP.project_forward(*arrays, *_cpu._camera_args(cam), rows, m2, props)
        grads = NP.project_backward(*arrays[:4], *_cpu._camera_args(cam), g_rows.astype(dt))
        outs.append([*(a.astype(np.float32) for a in (rows, m2, props, *grads)), *res])  # res: depths, radii, rects
    for a, b in zip(*outs):
        assert a.dtype == b.dtype and np.array_equal(a, b)


def test_projection_gradients_read_the_compositor_rows_in_place():
    per_g = torch.randn(50, 2 + NP.NPROP)
    rows = _cpu._grad_rows(per_g[:, 0:2], per_g[:, 2:])
    assert np.shares_memory(rows, per_g.numpy()) and np.array_equal(rows, per_g.numpy())
    a, b = torch.randn(50, 2), torch.randn(50, NP.NPROP)
    assert np.array_equal(_cpu._grad_rows(a, b), torch.cat([a, b], 1).numpy())
    assert _cpu._grad_rows(a.double(), b).dtype == np.float64


def test_bench_scaling_rows(capsys):
    from lmgs.render import bench_scaling as bench

    cpus = bench.os.cpu_count() or 1
    out = bench.scaling([48], [300], [1, cpus + 1], repeats=1, wait_too=True)
    rows = out["scaling"]
    assert [r["threads"] for r in rows] == [1, cpus + 1, cpus + 1, cpus + 1]
    assert "OMP_WAIT_POLICY=ACTIVE" in rows[2]["note"] and f"GOMP_SPINCOUNT={bench.SHORT_SPIN}" in rows[3]["note"]
    assert rows[0]["speedup"] == 1.0 and rows[0]["note"] == ""
    assert "oversubscribed" in rows[1]["note"] and rows[1]["numba_threads"] == cpus + 1
    for r in rows:
        assert r["kernel_ms"] > 0 and r["fwd_bwd_ms"] >= r["kernel_ms"]
        assert r["other_ms"] == pytest.approx(r["fwd_bwd_ms"] - r["kernel_ms"], rel=0.5, abs=1.0)
    table = bench.scaling_text(rows)
    assert table.splitlines()[0].startswith("scene") and "0k@48" in table
    with pytest.raises(Exception):
        bench.thread_counts("1,two")
    assert bench.thread_counts("16,1,2,2") == [1, 2, 16]
