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


SORT_CHUNK = 8192  # keys per parallel range of the depth sort, at least


def depth_order(depths: np.ndarray, visible: np.ndarray, n_chunks: int = 1) -> np.ndarray:
    """Ids of the ``visible`` Gaussians sorted by ``depths`` (float64), front to back; equal
    depths keep index order (a stable sort, the same order as ``np.argsort(kind="stable")``).

    An LSD radix sort over the depths' bits, 8 bits a pass (a float64 made an unsigned key
    whose order is the floats' order); passes in which every key has the same byte are skipped.
    In parallel over up to ``n_chunks`` contiguous ranges of at least ``SORT_CHUNK`` keys (in
    one thread below two such ranges): each range counts its keys' digits, and its keys go
    after those of the ranges before it with the same digit, so every pass is the sequential
    stable pass whatever the chunk count.
    """
    if min(n_chunks, depths.shape[0] // SORT_CHUNK) < 2:
        return _depth_order_serial(depths, visible)
    return _depth_order_parallel(depths, visible, n_chunks, SORT_CHUNK)


@njit(cache=True)
def _depth_order_serial(depths, visible):  # pragma: no cover - compiled
    """:func:`depth_order` in one thread."""
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
def _depth_order_parallel(depths, visible, n_chunks, min_chunk):  # pragma: no cover - compiled
    """:func:`depth_order` over up to ``n_chunks`` ranges of at least ``min_chunk`` keys."""
    n = depths.shape[0]
    nc = max(1, min(n_chunks, n // min_chunk))
    seen = np.zeros(nc + 1, np.int64)
    for c in prange(nc):
        for g in range(c * n // nc, (c + 1) * n // nc):
            seen[c + 1] += 1 if visible[g] else 0
    for c in range(nc):
        seen[c + 1] += seen[c]
    m = seen[nc]
    keys = np.empty(m, np.uint64)
    ids = np.empty(m, np.int64)
    bits = depths.view(np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    for c in prange(nc):
        j = seen[c]
        for g in range(c * n // nc, (c + 1) * n // nc):
            if visible[g]:
                b = bits[g] if depths[g] != 0.0 else np.uint64(0)  # -0.0 ties with 0.0
                keys[j] = ~b if b & sign else b | sign
                ids[j] = g
                j += 1
    nc = max(1, min(n_chunks, m // min_chunk))
    hist = np.zeros((nc, 8, 256), np.int64)  # per range: its keys' digits (the ranges move between passes)
    for c in prange(nc):
        for i in range(c * m // nc, (c + 1) * m // nc):
            k = keys[i]
            for d in range(8):
                hist[c, d, (k >> np.uint64(8 * d)) & np.uint64(255)] += 1
    keys2 = np.empty_like(keys)
    ids2 = np.empty_like(ids)
    pos = np.empty((nc, 256), np.int64)
    first = True
    for d in range(8):
        skip = False
        for v in range(256):
            tot = 0
            for c in range(nc):
                tot += hist[c, d, v]
            if tot == m:
                skip = True
        if skip:
            continue
        shift = np.uint64(8 * d)
        if not first and nc > 1:  # this digit's counts per range of the current arrangement
            for c in prange(nc):
                for v in range(256):
                    hist[c, d, v] = 0
                for i in range(c * m // nc, (c + 1) * m // nc):
                    hist[c, d, (keys[i] >> shift) & np.uint64(255)] += 1
        first = False
        run = 0
        for v in range(256):
            for c in range(nc):
                pos[c, v] = run
                run += hist[c, d, v]
        for c in prange(nc):
            for i in range(c * m // nc, (c + 1) * m // nc):
                v = (keys[i] >> shift) & np.uint64(255)
                q = pos[c, v]
                keys2[q] = keys[i]
                ids2[q] = ids[i]
                pos[c, v] = q + 1
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


TILE_COST = 16  # a tile's fixed cost (loading and writing its pixels) in intersections, for balance_tiles


@njit(cache=True)
def balance_tiles(offsets, n_chunks):  # pragma: no cover - compiled
    """The non-empty tiles dealt to ``n_chunks`` parallel chunks ``[n_chunks, m]`` (padded with -1),
    each chunk's tiles in increasing order, by their cost (``TILE_COST`` plus their intersection
    count): greedily, the costliest tile first, each to the chunk with the least cost so far (the
    first such). Every pixel's result is the same whatever the assignment."""
    n_tiles = offsets.shape[0] - 1
    cost = np.empty(n_tiles, np.int64)
    for t in range(n_tiles):
        n_t = offsets[t + 1] - offsets[t]
        cost[t] = n_t + TILE_COST if n_t > 0 else 0
    by_cost = np.argsort(-cost, kind="mergesort")
    load = np.zeros(n_chunks, np.int64)
    count = np.zeros(n_chunks, np.int64)
    chunk_of = np.full(n_tiles, -1, np.int64)
    for t in by_cost:
        if cost[t] == 0:
            break
        c = 0
        for r in range(1, n_chunks):
            if load[r] < load[c]:
                c = r
        chunk_of[t] = c
        load[c] += cost[t]
        count[c] += 1
    out = np.full((n_chunks, max(1, count.max())), -1, np.int64)
    count[:] = 0
    for t in range(n_tiles):
        c = chunk_of[t]
        if c >= 0:
            out[c, count[c]] = t
            count[c] += 1
    return out
