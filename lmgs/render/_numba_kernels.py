"""Numba kernels of the CPU rasterizer: tile binning, forward and backward compositing.

All arrays are float64 (the per-Gaussian inputs are few; float64 keeps the forward and
the hand-written backward exact enough for ``gradcheck``). Tiles are processed in
parallel with ``prange``; each tile writes only to its own pixels and to its own slice of
the per-intersection gradient buffer, and the buffer is reduced to Gaussians in a fixed
sequential order, so the results are bitwise deterministic whatever the thread count.

Per-Gaussian row layout (``rows[g]``; intersection ``k`` of a tile reads ``rows[ids[k]]``)::

    0 mx, 1 my, 2 a, 3 b, 4 c (conic), 5 opacity, 6 log(255 * opacity), 7..13 features (7),
    14, 15 half-widths in x and y of the box outside which alpha < 1/255
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
ROW = 7 + NF + 2  # + the pixel box half-widths (ext_x, ext_y)
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
def gaussian_rows(means2d, conics, opac, feats):  # pragma: no cover - compiled
    """Per-Gaussian rows ``[N, 16]`` (see the module docstring); the kernels read
    ``rows[ids[k]]`` for intersection ``k`` (a gathered copy costs more in page faults)."""
    n = means2d.shape[0]
    rows = np.empty((n, ROW), np.float64)
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
    # pixel that can contribute, with a margin against rounding.
    thr = math.log(255.0 * op) if op > 0 else -1.0
    rows[g, 6] = thr
    det = a * c - b * b
    if thr + 1e-6 > 0 and det > 0:
        rows[g, 14] = math.sqrt(2.0 * (thr + 1e-6) * c / det) * (1.0 + 1e-9) + 1e-6
        rows[g, 15] = math.sqrt(2.0 * (thr + 1e-6) * a / det) * (1.0 + 1e-9) + 1e-6
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


@njit(inline="always")
def _span(m, ext, lo, n):  # pragma: no cover - compiled
    """Pixel indices ``[i0, i1)`` of ``lo..lo+n-1`` whose centres ``i + 0.5`` lie in ``m +- ext``."""
    if ext < 0.0:
        return lo, lo
    a = min(max(m - ext - 0.5, lo - 1.0), lo + n + 1.0)
    b = min(max(m + ext - 0.5, lo - 1.0), lo + n + 1.0)
    i0 = max(lo, int(math.ceil(a)))
    i1 = min(lo + n, int(math.floor(b)) + 1)
    return i0, max(i0, i1)


@njit(inline="always")
def _row_span(dy, ca, cb, cc, thr, mx, i0, i1):  # pragma: no cover - compiled
    """Narrow ``[i0, i1)`` to the pixels of one row with ``sigma <= thr`` (plus a margin).

    For fixed :math:`d_y`, :math:`\\sigma(d_x) = \\tfrac12 a d_x^2 + b d_y d_x + \\tfrac12 c d_y^2`
    is below ``thr`` between the roots :math:`d_x = (-b d_y \\pm \\sqrt{b^2 d_y^2 - a(c d_y^2 - 2 thr)})/a`.
    Every pixel that can contribute stays inside; the exact test is still done per pixel.
    """
    disc = (cb * dy) * (cb * dy) - ca * (cc * dy * dy - 2.0 * thr)
    if disc < 0.0 or ca <= 0.0:
        return i0, i0
    sq = math.sqrt(disc)
    dx_hi = (-cb * dy + sq) / ca
    dx_lo = (-cb * dy - sq) / ca
    margin = 1e-6 * (1.0 + abs(dx_hi) + abs(dx_lo))
    # dx = mx - (px + 0.5)  =>  px = mx - 0.5 - dx
    a = min(max(mx - 0.5 - dx_hi - margin, i0 - 1.0), i1 + 1.0)
    b = min(max(mx - 0.5 - dx_lo + margin, i0 - 1.0), i1 + 1.0)
    r0 = max(i0, int(math.ceil(a)))
    r1 = min(i1, int(math.floor(b)) + 1)
    return r0, max(r0, r1)


@njit(parallel=True, cache=True)
def forward(rows, ids, offsets, tile_order, tiles_w, width, height, nf=NF):  # pragma: no cover - compiled
    """Front-to-back compositing of every tile.

    For pixel :math:`p` and its tile list :math:`i = 1..n` (front to back):
    :math:`\\alpha_i = \\min(0.99, o_i e^{-\\sigma_i})`,
    :math:`\\sigma_i = \\tfrac12 (a d_x^2 + c d_y^2) + b d_x d_y`, :math:`d = \\mu'_i - p`;
    skip when :math:`\\sigma_i < 0` or :math:`\\alpha_i < 1/255`; stop before the first
    :math:`i` with :math:`T_{i-1}(1-\\alpha_i) < 10^{-4}`;
    :math:`F_p = \\sum_i f_i \\alpha_i T_{i-1}`, :math:`T_i = \\prod_{j \\le i}(1-\\alpha_j)`.

    The loop runs Gaussian by Gaussian over only the pixels of the tile inside its
    alpha >= 1/255 box, with per-pixel state; each pixel still sees its Gaussians in the
    same front-to-back order, so this equals the per-pixel loop operation for operation.

    ``nf`` composites only the first ``nf`` features (3: colour alone, for rendering a
    trained model; the weights, and so ``t_final`` and ``last``, do not depend on it).

    Returns ``out [H, W, nf]``, ``t_final [H, W]`` and ``last [H, W]`` (one past the
    intersection index of the last composited Gaussian, the backward's start).
    """
    out = np.zeros((height, width, nf), np.float64)
    t_final = np.ones((height, width), np.float64)
    last = np.zeros((height, width), np.int64)
    n_chunks = tile_order.shape[0]
    for chunk in prange(n_chunks):
        T = np.empty(TILE * TILE, np.float64)
        acc = np.empty((TILE * TILE, nf), np.float64)
        stop = np.empty(TILE * TILE, np.int64)
        done = np.empty(TILE * TILE, np.bool_)
        for t in tile_order[chunk]:
            if t < 0:
                break
            ty = t // tiles_w
            tx = t - ty * tiles_w
            start = offsets[t]
            end = offsets[t + 1]
            if start == end:
                continue
            x_lo = tx * TILE
            y_lo = ty * TILE
            pw = min(TILE, width - x_lo)
            ph = min(TILE, height - y_lo)
            T[:] = 1.0
            acc[:, :] = 0.0
            stop[:] = start
            done[:] = False
            n_done = 0
            for k in range(start, end):
                g = ids[k]  # (no row view: views refcount the parent atomically, which threads contend on)
                mx = rows[g, 0]
                my = rows[g, 1]
                ca = rows[g, 2]
                cb = rows[g, 3]
                cc = rows[g, 4]
                op = rows[g, 5]
                thr = rows[g, 6] + 1e-6
                i0, i1 = _span(mx, rows[g, 14], x_lo, pw)
                j0, j1 = _span(my, rows[g, 15], y_lo, ph)
                for py in range(j0, j1):
                    dy = my - (py + 0.5)
                    row = (py - y_lo) * TILE - x_lo
                    r0, r1 = _row_span(dy, ca, cb, cc, thr, mx, i0, i1)
                    for px in range(r0, r1):
                        l = row + px
                        if done[l]:
                            continue
                        dx = mx - (px + 0.5)
                        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        # alpha < 1/255 <=> sigma > log(255 o): a cheap pre-test with a margin
                        if sigma < 0.0 or sigma > thr:
                            continue
                        alpha = min(ALPHA_MAX, op * math.exp(-sigma))
                        if alpha < ALPHA_MIN:
                            continue
                        tl = T[l]
                        test_t = tl * (1.0 - alpha)
                        if test_t < T_MIN:
                            done[l] = True
                            n_done += 1
                            continue
                        w = alpha * tl
                        for f in range(nf):
                            acc[l, f] += w * rows[g, 7 + f]
                        T[l] = test_t
                        stop[l] = k + 1
                if n_done == pw * ph:
                    break
            for py in range(y_lo, y_lo + ph):
                for px in range(x_lo, x_lo + pw):
                    l = (py - y_lo) * TILE + px - x_lo
                    for f in range(nf):
                        out[py, px, f] = acc[l, f]
                    t_final[py, px] = T[l]
                    last[py, px] = stop[l]
    return out, t_final, last


@njit(parallel=True, cache=True)
def backward(rows, ids, offsets, tile_order, tiles_w, width, height, t_final, last, g_out, g_alpha):  # pragma: no cover
    """Per-intersection gradients ``[n_isect, 13]``, back to front per pixel.

    With :math:`T_{i-1} = T_i / (1-\\alpha_i)` recovered from the final transmittance and
    :math:`S_i = \\sum_{j>i} f_j \\alpha_j T_{j-1}`:

    .. math::
        \\partial F/\\partial f_i = \\alpha_i T_{i-1},\\quad
        \\partial L/\\partial \\alpha_i = \\sum_c g_c \\big(f_{ic} T_{i-1} - S_{ic}/(1-\\alpha_i)\\big)
            + g_A T_n/(1-\\alpha_i)

    (the alpha image is :math:`A = 1 - T_n`); through :math:`\\alpha_i = o_i e^{-\\sigma_i}`
    unless capped at 0.99, where the gradient is zero. Gaussian by Gaussian, back to front,
    over the same pixel boxes as the forward; each row of the result is written by one
    tile only, summed over its pixels in a fixed order.
    """
    n_isect = ids.shape[0]
    grad = np.zeros((n_isect, GROW), np.float64)
    for chunk in prange(tile_order.shape[0]):
        T = np.empty(TILE * TILE, np.float64)
        S = np.empty((TILE * TILE, NF), np.float64)
        G = np.empty((TILE * TILE, NF + 1), np.float64)  # g_out and g_alpha * T_n
        lst = np.empty(TILE * TILE, np.int64)
        gk = np.empty(GROW, np.float64)
        for t in tile_order[chunk]:
            if t < 0:
                break
            ty = t // tiles_w
            tx = t - ty * tiles_w
            start = offsets[t]
            end = offsets[t + 1]
            if start == end:
                continue
            x_lo = tx * TILE
            y_lo = ty * TILE
            pw = min(TILE, width - x_lo)
            ph = min(TILE, height - y_lo)
            S[:, :] = 0.0
            kmax = start
            for py in range(y_lo, y_lo + ph):
                for px in range(x_lo, x_lo + pw):
                    l = (py - y_lo) * TILE + px - x_lo
                    T[l] = t_final[py, px]
                    lst[l] = last[py, px]
                    kmax = max(kmax, lst[l])
                    for f in range(NF):
                        G[l, f] = g_out[py, px, f]
                    G[l, NF] = g_alpha[py, px] * t_final[py, px]
            for k in range(kmax - 1, start - 1, -1):
                g = ids[k]  # (no row view: views refcount the parent atomically, which threads contend on)
                mx = rows[g, 0]
                my = rows[g, 1]
                ca = rows[g, 2]
                cb = rows[g, 3]
                cc = rows[g, 4]
                op = rows[g, 5]
                thr = rows[g, 6] + 1e-6
                i0, i1 = _span(mx, rows[g, 14], x_lo, pw)
                j0, j1 = _span(my, rows[g, 15], y_lo, ph)
                gk[:] = 0.0
                for py in range(j0, j1):
                    dy = my - (py + 0.5)
                    row = (py - y_lo) * TILE - x_lo
                    r0, r1 = _row_span(dy, ca, cb, cc, thr, mx, i0, i1)
                    for px in range(r0, r1):
                        l = row + px
                        if k >= lst[l]:
                            continue
                        dx = mx - (px + 0.5)
                        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        if sigma < 0.0 or sigma > thr:
                            continue
                        gauss = math.exp(-sigma)
                        raw = op * gauss
                        alpha = min(ALPHA_MAX, raw)
                        if alpha < ALPHA_MIN:
                            continue
                        inv = 1.0 / (1.0 - alpha)
                        tl = T[l] * inv
                        T[l] = tl
                        w = alpha * tl
                        g_al = G[l, NF] * inv
                        for f in range(NF):
                            fv = rows[g, 7 + f]
                            gf = G[l, f]
                            gk[6 + f] += w * gf
                            g_al += gf * (fv * tl - S[l, f] * inv)
                            S[l, f] += w * fv
                        if raw <= ALPHA_MAX:
                            gk[5] += g_al * gauss
                            g_sig = -g_al * alpha
                            gk[0] += g_sig * (ca * dx + cb * dy)
                            gk[1] += g_sig * (cb * dx + cc * dy)
                            gk[2] += g_sig * 0.5 * dx * dx
                            gk[3] += g_sig * dx * dy
                            gk[4] += g_sig * 0.5 * dy * dy
                for c in range(GROW):
                    grad[k, c] = gk[c]
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
