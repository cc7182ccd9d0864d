"""Numba kernels of the CPU rasterizer before compositing: per-Gaussian rows and tile binning
(the projection is :mod:`lmgs.render._numba_projection`, the compositing
:mod:`lmgs.render._numba_composite`).

Per-Gaussian row layout (``rows[g]``; intersection ``k`` of a tile reads ``rows[ids[k]]``)::

    0 mx, 1 my, 2 a, 3 b, 4 c (conic), 5 opacity, 6 log(255 * opacity), 7..13 features (7),
    14, 15 half-widths in x and y of the box outside which alpha < 1/255
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

TILE = 16
NF = 7  # features per Gaussian
ROW = 7 + NF + 2  # + the pixel box half-widths (ext_x, ext_y)


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
def gaussian_rows(means2d, conics, opac, feats):  # pragma: no cover - compiled
    """Per-Gaussian rows ``[N, 16]`` in the dtype of ``means2d`` (see the module docstring); the
    kernels read ``rows[ids[k]]`` for intersection ``k`` (a gathered copy costs more in page faults)."""
    n = means2d.shape[0]
    rows = np.empty((n, ROW), means2d.dtype)
    for g in range(n):
        for f in range(NF):
            rows[g, 7 + f] = feats[g, f]
        _fill_row(rows, g, means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opac[g])
    return rows


@njit(inline="always")
def _fill_row(rows, g, mx, my, a, b, c, op):  # pragma: no cover - compiled
    """Row ``g`` except its features: mean, conic, opacity, the alpha threshold and the pixel box."""
    rows[g, 0] = mx
    rows[g, 1] = my
    rows[g, 2] = a
    rows[g, 3] = b
    rows[g, 4] = c
    rows[g, 5] = op
    # Pixels with sigma > log(255 o) have alpha < 1/255. Since
    # min over dy of d^T conic d = dx^2 / cov_xx, that region lies outside
    # |dx| <= sqrt(2 thr cov_xx) (and likewise in y): a box holding every
    # pixel that can contribute, with a margin against rounding (float32 rows
    # round the half-widths to 6e-8 relative: the margin is 1e-6 relative).
    thr = math.log(255.0 * op) if op > 0 else -1.0
    rows[g, 6] = thr
    det = a * c - b * b
    if thr + 1e-6 > 0 and det > 0:
        rows[g, 14] = math.sqrt(2.0 * (thr + 1e-6) * c / det) * (1.0 + 1e-6) + 1e-6
        rows[g, 15] = math.sqrt(2.0 * (thr + 1e-6) * a / det) * (1.0 + 1e-6) + 1e-6
    else:
        rows[g, 14] = -1.0
        rows[g, 15] = -1.0
