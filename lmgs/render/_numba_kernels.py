"""Numba kernels of the CPU rasterizer before compositing: per-Gaussian rows, the no-autograd
projection and tile binning (the compositing itself is :mod:`lmgs.render._numba_composite`).

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


@njit(parallel=True, cache=True)
def project_rows(means, quats, log_scales, opacity_logits, colors, w2c, fx, fy, cx, cy, width, height,
                 near, eps2d, ls_min, ls_max):  # pragma: no cover - compiled
    """No-autograd twin of ``_projection.project`` + :func:`gaussian_rows` + ``tile_rects``, in float64.

    Every formula is the torch projection's (see :mod:`lmgs.render._projection`), one
    Gaussian at a time; used when nothing needs a gradient (rendering a trained model).

    Returns:
        ``rows [N, ROW]``, ``depths [N]`` (camera z, 1 behind the near plane),
        ``radii [N]`` int32 (0 = culled), ``rects [N, 4]`` int64 tile ranges, ``means2d [N, 2]``.
    """
    n = means.shape[0]
    rows = np.empty((n, ROW), np.float64)
    depths = np.empty(n, np.float64)
    radii = np.zeros(n, np.int32)
    rects = np.zeros((n, 4), np.int64)
    means2d = np.empty((n, 2), np.float64)
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    for g in prange(n):
        qw, qx, qy, qz = quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if qn > 1e-12:
            qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        else:
            qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        r = np.empty((3, 3))
        r[0, 0] = 1 - 2 * (qy * qy + qz * qz)
        r[0, 1] = 2 * (qx * qy - qw * qz)
        r[0, 2] = 2 * (qx * qz + qw * qy)
        r[1, 0] = 2 * (qx * qy + qw * qz)
        r[1, 1] = 1 - 2 * (qx * qx + qz * qz)
        r[1, 2] = 2 * (qy * qz - qw * qx)
        r[2, 0] = 2 * (qx * qz - qw * qy)
        r[2, 1] = 2 * (qy * qz + qw * qx)
        r[2, 2] = 1 - 2 * (qx * qx + qy * qy)
        ls = np.empty(3)
        k = 0
        for i in range(3):
            ls[i] = min(max(log_scales[g, i], ls_min), ls_max)
            if ls[i] < ls[k]:  # argmin, first index on ties (torch's)
                k = i
        rc = np.empty((3, 3))  # rot_cw @ R: columns are the Gaussian's axes in camera space
        mc = np.empty(3)
        for i in range(3):
            mc[i] = w2c[i, 0] * means[g, 0] + w2c[i, 1] * means[g, 1] + w2c[i, 2] * means[g, 2] + w2c[i, 3]
            for j in range(3):
                rc[i, j] = w2c[i, 0] * r[0, j] + w2c[i, 1] * r[1, j] + w2c[i, 2] * r[2, j]
        in_front = mc[2] >= near
        z = mc[2] if in_front else 1.0
        x, y = mc[0], mc[1]
        tx = z * min(max(x / z, -lim_xn), lim_xp)
        ty = z * min(max(y / z, -lim_yn), lim_yp)
        j00, j02 = fx / z, -fx * tx / (z * z)
        j11, j12 = fy / z, -fy * ty / (z * z)
        m0 = np.empty(3)
        m1 = np.empty(3)
        for j in range(3):
            s = math.exp(ls[j])
            m0[j] = (j00 * rc[0, j] + j02 * rc[2, j]) * s
            m1[j] = (j11 * rc[1, j] + j12 * rc[2, j]) * s
        a = m0[0] * m0[0] + m0[1] * m0[1] + m0[2] * m0[2] + eps2d
        b = m0[0] * m1[0] + m0[1] * m1[1] + m0[2] * m1[2]
        c = m1[0] * m1[0] + m1[1] * m1[1] + m1[2] * m1[2] + eps2d
        det = a * c - b * b
        ok = in_front and det > 0
        det_s = det if ok else 1.0
        mx = fx * x / z + cx
        my = fy * y / z + cy
        means2d[g, 0] = mx
        means2d[g, 1] = my
        mid = 0.5 * (a + c)
        lam = mid + math.sqrt(max(mid * mid - det, 0.1))
        radius = math.ceil(3.0 * math.sqrt(lam))
        on_img = (mx + radius > 0) and (mx - radius < width) and (my + radius > 0) and (my - radius < height)
        if ok and on_img and radius > 0:
            radii[g] = np.int32(radius)
            rects[g, 0] = np.int64(min(max(math.floor((mx - radius) / TILE), 0.0), tw))
            rects[g, 1] = np.int64(min(max(math.ceil((mx + radius) / TILE), 0.0), tw))
            rects[g, 2] = np.int64(min(max(math.floor((my - radius) / TILE), 0.0), th))
            rects[g, 3] = np.int64(min(max(math.ceil((my + radius) / TILE), 0.0), th))
        nx, ny, nz = rc[0, k], rc[1, k], rc[2, k]
        if nx * mc[0] + ny * mc[1] + nz * mc[2] > 0:  # face the camera
            nx, ny, nz = -nx, -ny, -nz
        rows[g, 7] = colors[g, 0]
        rows[g, 8] = colors[g, 1]
        rows[g, 9] = colors[g, 2]
        rows[g, 10] = z
        rows[g, 11] = nx
        rows[g, 12] = ny
        rows[g, 13] = nz
        depths[g] = z
        _fill_row(rows, g, mx, my, c / det_s, -b / det_s, a / det_s, 1.0 / (1.0 + math.exp(-opacity_logits[g])))
    return rows, depths, radii, rects, means2d
