"""Numba kernels of the CPU rasterizer: tile binning, forward and backward compositing.

All arrays are float64 (the per-Gaussian inputs are few; float64 keeps the forward and
the hand-written backward exact enough for ``gradcheck``). Tiles are processed in
parallel with ``prange``; each tile writes only to its own pixels and to its own slice of
the per-intersection gradient buffer, and the buffer is reduced to Gaussians in a fixed
sequential order, so the results are bitwise deterministic whatever the thread count.

Per-intersection row layout (``data[k]``, ``k`` in the tile's sorted range)::

    0 mx, 1 my, 2 a, 3 b, 4 c (conic), 5 opacity, 6 log(255 * opacity), 7..13 features (7)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
NF = 7  # features per Gaussian
ROW = 7 + NF
GROW = 6 + NF  # gradient row: mx, my, a, b, c, opacity, features


@njit(cache=True)
def bin_tiles(rects, order, n_tiles, tiles_w):  # pragma: no cover - compiled
    """Sorted per-tile Gaussian lists.

    Args:
        rects: ``[N, 4]`` int64 half-open tile ranges ``(x0, x1, y0, y1)``.
        order: ``[M]`` int64 Gaussian ids sorted front to back (visible ones only).

    Returns:
        ``offsets [n_tiles + 1]`` and ``ids [n_isect]``: tile ``t`` holds
        ``ids[offsets[t]:offsets[t + 1]]``, front to back.
    """
    counts = np.zeros(n_tiles + 1, np.int64)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(rects[g, 2], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 1]):
                counts[ty * tiles_w + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int64)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(rects[g, 2], rects[g, 3]):
            for tx in range(rects[g, 0], rects[g, 1]):
                t = ty * tiles_w + tx
                ids[fill[t]] = g
                fill[t] += 1
    return offsets, ids


@njit(cache=True)
def gather(ids, means2d, conics, opac, feats):  # pragma: no cover - compiled
    """Per-intersection rows (see the module docstring), contiguous per tile."""
    n = ids.shape[0]
    data = np.empty((n, ROW), np.float64)
    for k in range(n):
        g = ids[k]
        data[k, 0] = means2d[g, 0]
        data[k, 1] = means2d[g, 1]
        data[k, 2] = conics[g, 0]
        data[k, 3] = conics[g, 1]
        data[k, 4] = conics[g, 2]
        data[k, 5] = opac[g]
        data[k, 6] = math.log(255.0 * opac[g]) if opac[g] > 0 else -1.0
        for c in range(NF):
            data[k, 7 + c] = feats[g, c]
    return data


@njit(parallel=True, cache=True)
def forward(data, offsets, tile_order, tiles_w, width, height):  # pragma: no cover - compiled
    """Front-to-back compositing of every tile.

    For pixel :math:`p` and its tile list :math:`i = 1..n` (front to back):
    :math:`\\alpha_i = \\min(0.99, o_i e^{-\\sigma_i})`,
    :math:`\\sigma_i = \\tfrac12 (a d_x^2 + c d_y^2) + b d_x d_y`, :math:`d = \\mu'_i - p`;
    skip when :math:`\\sigma_i < 0` or :math:`\\alpha_i < 1/255`; stop before the first
    :math:`i` with :math:`T_{i-1}(1-\\alpha_i) < 10^{-4}`;
    :math:`F_p = \\sum_i f_i \\alpha_i T_{i-1}`, :math:`T_i = \\prod_{j \\le i}(1-\\alpha_j)`.

    Returns ``out [H, W, 7]``, ``t_final [H, W]`` and ``last [H, W]`` (one past the
    intersection index of the last composited Gaussian, the backward's start).
    """
    out = np.zeros((height, width, NF), np.float64)
    t_final = np.ones((height, width), np.float64)
    last = np.zeros((height, width), np.int64)
    for it in prange(tile_order.shape[0]):
        t = tile_order[it]
        ty = t // tiles_w
        tx = t - ty * tiles_w
        start = offsets[t]
        end = offsets[t + 1]
        if start == end:
            continue
        for py in range(ty * TILE, min(ty * TILE + TILE, height)):
            fy = py + 0.5
            for px in range(tx * TILE, min(tx * TILE + TILE, width)):
                fx = px + 0.5
                T = 1.0
                stop = start
                f0 = f1 = f2 = f3 = f4 = f5 = f6 = 0.0
                for k in range(start, end):
                    dx = data[k, 0] - fx
                    dy = data[k, 1] - fy
                    sigma = 0.5 * (data[k, 2] * dx * dx + data[k, 4] * dy * dy) + data[k, 3] * dx * dy
                    # alpha < 1/255 <=> sigma > log(255 o): a cheap exact-with-margin pre-test
                    if sigma < 0.0 or sigma > data[k, 6] + 1e-6:
                        continue
                    alpha = min(ALPHA_MAX, data[k, 5] * math.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    test_t = T * (1.0 - alpha)
                    if test_t < T_MIN:
                        break
                    w = alpha * T
                    f0 += w * data[k, 7]
                    f1 += w * data[k, 8]
                    f2 += w * data[k, 9]
                    f3 += w * data[k, 10]
                    f4 += w * data[k, 11]
                    f5 += w * data[k, 12]
                    f6 += w * data[k, 13]
                    T = test_t
                    stop = k + 1
                out[py, px, 0] = f0
                out[py, px, 1] = f1
                out[py, px, 2] = f2
                out[py, px, 3] = f3
                out[py, px, 4] = f4
                out[py, px, 5] = f5
                out[py, px, 6] = f6
                t_final[py, px] = T
                last[py, px] = stop
    return out, t_final, last


@njit(parallel=True, cache=True)
def backward(data, offsets, tile_order, tiles_w, width, height, t_final, last, g_out, g_alpha):  # pragma: no cover
    """Per-intersection gradients ``[n_isect, 13]``, back to front per pixel.

    With :math:`T_{i-1} = T_i / (1-\\alpha_i)` recovered from the final transmittance and
    :math:`S_i = \\sum_{j>i} f_j \\alpha_j T_{j-1}`:

    .. math::
        \\partial F/\\partial f_i = \\alpha_i T_{i-1},\\quad
        \\partial L/\\partial \\alpha_i = \\sum_c g_c \\big(f_{ic} T_{i-1} - S_{ic}/(1-\\alpha_i)\\big)
            + g_A T_n/(1-\\alpha_i)

    (the alpha image is :math:`A = 1 - T_n`); through :math:`\\alpha_i = o_i e^{-\\sigma_i}`
    unless capped at 0.99, where the gradient is zero.
    """
    n_isect = data.shape[0]
    grad = np.zeros((n_isect, GROW), np.float64)
    for it in prange(tile_order.shape[0]):
        t = tile_order[it]
        ty = t // tiles_w
        tx = t - ty * tiles_w
        start = offsets[t]
        if start == offsets[t + 1]:
            continue
        for py in range(ty * TILE, min(ty * TILE + TILE, height)):
            fy = py + 0.5
            for px in range(tx * TILE, min(tx * TILE + TILE, width)):
                fx = px + 0.5
                tn = t_final[py, px]
                T = tn
                ga = g_alpha[py, px]
                g0 = g_out[py, px, 0]
                g1 = g_out[py, px, 1]
                g2 = g_out[py, px, 2]
                g3 = g_out[py, px, 3]
                g4 = g_out[py, px, 4]
                g5 = g_out[py, px, 5]
                g6 = g_out[py, px, 6]
                s0 = s1 = s2 = s3 = s4 = s5 = s6 = 0.0
                for k in range(last[py, px] - 1, start - 1, -1):
                    dx = data[k, 0] - fx
                    dy = data[k, 1] - fy
                    sigma = 0.5 * (data[k, 2] * dx * dx + data[k, 4] * dy * dy) + data[k, 3] * dx * dy
                    if sigma < 0.0 or sigma > data[k, 6] + 1e-6:
                        continue
                    gauss = math.exp(-sigma)
                    raw = data[k, 5] * gauss
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    inv = 1.0 / (1.0 - alpha)
                    T = T * inv
                    w = alpha * T
                    grad[k, 6] += w * g0
                    grad[k, 7] += w * g1
                    grad[k, 8] += w * g2
                    grad[k, 9] += w * g3
                    grad[k, 10] += w * g4
                    grad[k, 11] += w * g5
                    grad[k, 12] += w * g6
                    f0 = data[k, 7]
                    f1 = data[k, 8]
                    f2 = data[k, 9]
                    f3 = data[k, 10]
                    f4 = data[k, 11]
                    f5 = data[k, 12]
                    f6 = data[k, 13]
                    g_al = (
                        g0 * (f0 * T - s0 * inv)
                        + g1 * (f1 * T - s1 * inv)
                        + g2 * (f2 * T - s2 * inv)
                        + g3 * (f3 * T - s3 * inv)
                        + g4 * (f4 * T - s4 * inv)
                        + g5 * (f5 * T - s5 * inv)
                        + g6 * (f6 * T - s6 * inv)
                        + ga * tn * inv
                    )
                    s0 += w * f0
                    s1 += w * f1
                    s2 += w * f2
                    s3 += w * f3
                    s4 += w * f4
                    s5 += w * f5
                    s6 += w * f6
                    if raw <= ALPHA_MAX:
                        grad[k, 5] += g_al * gauss
                        g_sig = -g_al * alpha
                        grad[k, 0] += g_sig * (data[k, 2] * dx + data[k, 3] * dy)
                        grad[k, 1] += g_sig * (data[k, 3] * dx + data[k, 4] * dy)
                        grad[k, 2] += g_sig * 0.5 * dx * dx
                        grad[k, 3] += g_sig * dx * dy
                        grad[k, 4] += g_sig * 0.5 * dy * dy
    return grad


@njit(cache=True)
def reduce_grads(grad, ids, n):  # pragma: no cover - compiled
    """Sum per-intersection gradient rows into ``[n, 13]`` per-Gaussian rows, in order."""
    out = np.zeros((n, GROW), np.float64)
    for k in range(ids.shape[0]):
        g = ids[k]
        for c in range(GROW):
            out[g, c] += grad[k, c]
    return out
