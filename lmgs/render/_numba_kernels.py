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
def depth_order(depths, visible):  # pragma: no cover - compiled
    """Ids of the ``visible`` Gaussians sorted by ``depths`` (float64), front to back; equal
    depths keep index order (a stable sort, the same order as ``np.argsort(kind="stable")``).

    An LSD radix sort over the depths' bits, 8 bits a pass (a float64 made an unsigned key
    whose order is the floats' order); passes in which every key has the same byte are skipped.
    """
    n = depths.shape[0]
    m = 0
    for g in range(n):
        m += 1 if visible[g] else 0
    keys = np.empty(m, np.uint64)
    ids = np.empty(m, np.int64)
    bits = depths.view(np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    j = 0
    for g in range(n):
        if visible[g]:
            b = bits[g] if depths[g] != 0.0 else np.uint64(0)  # -0.0 ties with 0.0
            keys[j] = ~b if b & sign else b | sign
            ids[j] = g
            j += 1
    hist = np.zeros((8, 256), np.int64)
    for i in range(m):
        k = keys[i]
        for d in range(8):
            hist[d, (k >> np.uint64(8 * d)) & np.uint64(255)] += 1
    keys2 = np.empty_like(keys)
    ids2 = np.empty_like(ids)
    pos = np.empty(256, np.int64)
    for d in range(8):
        skip = False
        for v in range(256):
            if hist[d, v] == m:
                skip = True
        if skip:
            continue
        run = 0
        for v in range(256):
            pos[v] = run
            run += hist[d, v]
        shift = np.uint64(8 * d)
        for i in range(m):
            v = (keys[i] >> shift) & np.uint64(255)
            q = pos[v]
            keys2[q] = keys[i]
            ids2[q] = ids[i]
            pos[v] = q + 1
        keys, keys2 = keys2, keys
        ids, ids2 = ids2, ids
    return ids


@njit(parallel=True, cache=True)
def bin_tiles(rects, order, n_tiles, tiles_w, n_chunks):  # pragma: no cover - compiled
    """Sorted per-tile Gaussian lists.

    Args:
        rects: ``[N, 4]`` int64 half-open tile ranges ``(x0, x1, y0, y1)``.
        order: ``[M]`` int64 Gaussian ids sorted front to back (visible ones only).
        n_chunks: parallel chunks (the numba thread count; the result does not depend on it).

    Returns:
        ``offsets [n_tiles + 1]`` and ``ids [n_isect]``: tile ``t`` holds
        ``ids[offsets[t]:offsets[t + 1]]``, front to back.

    A counting sort by tile, in parallel over contiguous chunks of ``order``: each chunk
    counts its intersections per tile, chunk ``c`` of tile ``t`` then starts after those of
    chunks ``< c``, so the lists are those of the sequential sort whatever the chunk count.
    """
    m = order.shape[0]
    n_chunks = max(1, min(n_chunks, m // 256))
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for k in range(c * m // n_chunks, (c + 1) * m // n_chunks):
            g = order[k]
            for ty in range(rects[g, 2], rects[g, 3]):
                for tx in range(rects[g, 0], rects[g, 1]):
                    counts[c, ty * tiles_w + tx] += 1
    offsets = np.empty(n_tiles + 1, np.int64)
    run = 0
    for t in range(n_tiles):
        offsets[t] = run
        for c in range(n_chunks):
            n_ct = counts[c, t]
            counts[c, t] = run  # now the chunk's next slot in tile t
            run += n_ct
    offsets[n_tiles] = run
    ids = np.empty(run, np.int64)
    for c in prange(n_chunks):
        for k in range(c * m // n_chunks, (c + 1) * m // n_chunks):
            g = order[k]
            for ty in range(rects[g, 2], rects[g, 3]):
                for tx in range(rects[g, 0], rects[g, 1]):
                    t = ty * tiles_w + tx
                    ids[counts[c, t]] = g
                    counts[c, t] += 1
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
