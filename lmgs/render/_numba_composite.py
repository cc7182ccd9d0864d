"""Numba compositing kernels, vectorised across the pixels of a tile.

The loop order is Gaussian-major per tile (see ``design.md``): for each Gaussian of a
tile's front-to-back list, the pixels of every tile row its alpha >= 1/255 box touches
go through one loop that LLVM vectorises (16 float32 lanes with AVX-512): the body has
no branches (the per-pixel tests are selects), no call (its own exponential,
:func:`_exp_neg`, a polynomial: a libm ``exp`` call keeps a loop scalar), no
zero-division check (``error_model="numpy"``), and lets LLVM fuse multiply-adds
(``contract``). Each pixel still sees its Gaussians in the same order with the same
tests as the per-pixel definition.

The kernels run in the dtype of ``rows``: float32 for float32 inputs (16 lanes to an
AVX-512 register, a Gaussian's row is one 64-byte cache line) and float64 for float64
inputs (``gradcheck``). Constants come from :func:`consts` in that dtype, because a
Python float literal would promote float32 arithmetic to float64.

Tiles run in parallel with ``prange``; each tile writes only its own pixels and its own
rows of the per-intersection gradient buffer, which is reduced to Gaussians in a fixed
order, so the results are bitwise deterministic whatever the thread count.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

from lmgs.render._projection import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16
NF = 7  # features per Gaussian (rgb, camera z, normal)
GROW = 6 + NF  # gradient row: mx, my, a, b, c, opacity, features
# consts(): zero, one, half, 0.99 (alpha cap), 1/255 (alpha floor), 1e-4 (transmittance stop),
# 6 (sigma clamp before the exponential: above log(255) alpha is below 1/255 for any opacity)
_ZERO, _ONE, _HALF, _AMAX, _AMIN, _TMIN, _SMAX = range(7)


@functools.lru_cache(maxsize=None)
def _consts(dtype: np.dtype) -> np.ndarray:
    return np.array([0.0, 1.0, 0.5, ALPHA_MAX, ALPHA_MIN, T_MIN, 6.0], dtype=dtype)


def consts(dtype) -> np.ndarray:
    """The kernels' constants in ``dtype`` (index with the ``_ZERO`` ... ``_SMAX`` names); one
    array per dtype, made once (the kernels only read it)."""
    return _consts(np.dtype(dtype))


# exp(-s) for 0 <= s <= 6: s = n ln2 + r with n = round(s / ln2), |r| <= ln2 / 2, then
# exp(-s) = 2^-n exp(-r), 2^-n built from the bits of n (0 <= n <= 9) by multiplications
# that are exact, exp(-r) a Taylor polynomial (degree 7 in float32: truncation error
# 0.35^8/8! = 5e-9; degree 12 in float64: 2e-16), ln2 split in two for an exact r.
# Arithmetic, not selects, picks the powers of two (an inlined conditional expression
# trips a numba IR check).
_LN2_HI, _LN2_LO, _INV_LN2 = 0.693145751953125, 1.4286068203094173e-06, 1.4426950408889634


def _exp_neg(s):  # pragma: no cover - replaced by the overload in compiled code
    return math.exp(-s)


def _exp_neg_impl(ftype, degree: int):
    """The compiled ``exp(-s)`` in ``ftype`` (np.float32 or np.float64)."""
    c = tuple(ftype((-1.0) ** i / math.factorial(i)) for i in range(degree, -1, -1))  # Horner order
    inv_ln2, ln2_hi, ln2_lo, half, one = (ftype(v) for v in (_INV_LN2, _LN2_HI, _LN2_LO, 0.5, 1.0))
    q1, q2, q4, q8 = (ftype(1.0 - 2.0 ** -k) for k in (1, 2, 4, 8))  # 1 - 2^-k, exact

    @njit(inline="always")
    def pow2(p, n):  # p 2^-n for 0 <= n <= 15
        p = p * (one - ftype(n & 1) * q1)
        p = p * (one - ftype((n >> 1) & 1) * q2)
        p = p * (one - ftype((n >> 2) & 1) * q4)
        return p * (one - ftype((n >> 3) & 1) * q8)

    if degree == 7:
        def impl(s):
            n = np.int32(s * inv_ln2 + half)
            r = (s - ftype(n) * ln2_hi) - ftype(n) * ln2_lo
            p = ((((((c[0] * r + c[1]) * r + c[2]) * r + c[3]) * r + c[4]) * r + c[5]) * r + c[6]) * r + c[7]
            return pow2(p, n)
        return impl
    assert degree == 12

    def impl64(s):
        n = np.int32(s * inv_ln2 + half)
        r = (s - ftype(n) * ln2_hi) - ftype(n) * ln2_lo
        p = ((((((c[0] * r + c[1]) * r + c[2]) * r + c[3]) * r + c[4]) * r + c[5]) * r + c[6]) * r + c[7]
        p = ((((p * r + c[8]) * r + c[9]) * r + c[10]) * r + c[11]) * r + c[12]
        return pow2(p, n)
    return impl64


@overload(_exp_neg, inline="always")
def _exp_neg_overload(s):  # pragma: no cover - compiled
    if s == types.float32:
        return _exp_neg_impl(np.float32, 7)
    if s == types.float64:
        return _exp_neg_impl(np.float64, 12)
    return None


@functools.lru_cache(maxsize=64)
def _pixel_centres(n: int, dtype: np.dtype) -> np.ndarray:
    return (np.arange(n, dtype=np.float64) + 0.5).astype(dtype)


def pixel_centres(width: int, height: int, dtype) -> np.ndarray:
    """``i + 0.5`` for every pixel index of the image's larger side (at least a tile), in ``dtype``;
    one array per length and dtype, made once (the kernels only read it)."""
    return _pixel_centres(max(int(width), int(height), TILE), np.dtype(dtype))


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


# Per-chunk scratch: ONE flat array holding every per-pixel field of a tile, PIX apart,
# indexed with unsigned integers (``_U``). Every access in a pixel loop is then
# base + field + pixel with constant field distances, which LLVM proves disjoint
# (separate arrays would need runtime alias checks; signed indices add numba's
# wraparound select). The pixel loops run over a Gaussian's whole rows, ``u`` from
# ``r0`` to ``r1``: a trip count LLVM cannot fold (numba leaves LLVM's SLP vectoriser
# off, so a constant 16-trip loop would be unrolled and stay scalar).
PIX = TILE * TILE
F32_MAX_ISECT = 2**24  # the stop index is kept in the rows' dtype: float32 holds integers below 2**24 exactly
_U = np.uint64
F_T, F_STOP, F_X, F_Y, F_ACC = _U(0), _U(PIX), _U(2 * PIX), _U(3 * PIX), _U(4 * PIX)  # F_ACC: nf fields
B_T, B_LST, B_X, B_Y, B_G = _U(0), _U(PIX), _U(2 * PIX), _U(3 * PIX), _U(4 * PIX)  # B_G: NF + 1 fields
B_S = _U((5 + NF) * PIX)  # NF fields
B_SIZE = (5 + 2 * NF) * PIX


@njit(inline="always")
def _feature_back(st, field, u, wk, tl, inv, v):  # pragma: no cover - compiled
    """Feature ``v`` (at ``field`` in the scratch) of pixel ``u`` under a Gaussian of weight ``wk``,
    back to front: the Gaussian's feature gradient ``wk dL/dF`` and the feature's part of its
    alpha gradient; ``S`` (the features composited behind it) takes the Gaussian in."""
    gf = st[B_G + field + u]
    s_f = st[B_S + field + u]
    st[B_S + field + u] = s_f + wk * v
    return wk * gf, gf * (v * tl - s_f * inv)


@njit(inline="always")
def _bwd_rows(st, r0, r1, mxl, myl, ca, cb, cc, op, kf, cst, fv):  # pragma: no cover - compiled
    """One Gaussian over the tile pixels ``r0 <= u < r1`` (whole rows), back to front: updates
    ``T`` and ``S`` of those pixels and returns the Gaussian's 13 gradient sums over them
    (the caller allows reassociation, so LLVM vectorises the sums: partial sums per lane,
    added up at the end, in an order fixed by the compiled code)."""
    zero, one, half, amax, amin, smax = cst[0], cst[1], cst[2], cst[3], cst[4], cst[6]
    ha, hc = half * ca, half * cc
    g0 = g1 = g2 = g3 = g4 = g5 = g6 = g7 = g8 = g9 = g10 = g11 = g12 = zero
    for u in range(r0, r1):
        dx = mxl - st[B_X + u]
        dy = myl - st[B_Y + u]
        sig = (ha * dx) * dx + (cb * dx) * dy + (hc * dy) * dy
        e = _exp_neg(min(max(sig, zero), smax))
        raw = op * e
        al = min(amax, raw)
        ok = (sig >= zero) & (al >= amin) & (kf < st[B_LST + u])
        okf = one if ok else zero
        inv = one / (one - al)
        t_old = st[B_T + u]
        tl = t_old * inv
        st[B_T + u] = tl if ok else t_old
        wk = al * tl * okf
        g_al = st[B_G + _U(NF * PIX) + u] * inv
        # the features one by one (a loop would need an array for the sums g6..g12: scalars vectorise)
        d6, a6 = _feature_back(st, _U(0), u, wk, tl, inv, fv[0])
        d7, a7 = _feature_back(st, _U(PIX), u, wk, tl, inv, fv[1])
        d8, a8 = _feature_back(st, _U(2 * PIX), u, wk, tl, inv, fv[2])
        d9, a9 = _feature_back(st, _U(3 * PIX), u, wk, tl, inv, fv[3])
        d10, a10 = _feature_back(st, _U(4 * PIX), u, wk, tl, inv, fv[4])
        d11, a11 = _feature_back(st, _U(5 * PIX), u, wk, tl, inv, fv[5])
        d12, a12 = _feature_back(st, _U(6 * PIX), u, wk, tl, inv, fv[6])
        g6, g7, g8, g9, g10, g11, g12 = g6 + d6, g7 + d7, g8 + d8, g9 + d9, g10 + d10, g11 + d11, g12 + d12
        g_al = g_al + a6 + a7 + a8 + a9 + a10 + a11 + a12
        g_al = g_al * okf if raw <= amax else zero
        g_sig = -g_al * al
        g5 += g_al * e
        g0 += g_sig * (ca * dx + cb * dy)
        g1 += g_sig * (cb * dx + cc * dy)
        g2 += g_sig * half * dx * dx
        g3 += g_sig * dx * dy
        g4 += g_sig * half * dy * dy
    return g0, g1, g2, g3, g4, g5, g6, g7, g8, g9, g10, g11, g12


@njit(inline="always")
def _fwd_rows(st, r0, r1, mxl, myl, ha, cb, hc, op, kf, cst, fv):  # pragma: no cover - compiled
    """One Gaussian over the tile pixels ``r0 <= u < r1`` (whole rows): the lane body of
    :func:`forward`, with the features ``fv`` (a tuple: its length is a compile-time constant,
    so the feature loop unrolls inside the vectorised pixel loop)."""
    zero, one, amax, amin, tmin, smax = cst[0], cst[1], cst[3], cst[4], cst[5], cst[6]
    for u in range(r0, r1):
        dx = mxl - st[F_X + u]
        dy = myl - st[F_Y + u]
        sig = (ha * dx) * dx + (cb * dx) * dy + (hc * dy) * dy
        al = min(amax, op * _exp_neg(min(max(sig, zero), smax)))
        tl = st[F_T + u]
        tt = tl * (one - al)
        ok = (sig >= zero) & (al >= amin) & (tl > zero)
        use = ok & (tt >= tmin)
        w = al * tl if use else zero
        st[F_T + u] = tt if use else (-tl if ok else tl)
        st[F_STOP + u] = kf if use else st[F_STOP + u]
        for f in range(len(fv)):
            st[F_ACC + _U(f * PIX) + u] += w * fv[f]


@njit(parallel=True, cache=True, fastmath={"contract"}, error_model="numpy")
def forward(rows, ids, offsets, tile_order, tiles_w, width, height, nf, cst, centres):  # pragma: no cover
    """Front-to-back compositing of every tile.

    For pixel :math:`p` and its tile list :math:`i = 1..n` (front to back):
    :math:`\\alpha_i = \\min(0.99, o_i e^{-\\sigma_i})`,
    :math:`\\sigma_i = \\tfrac12 (a d_x^2 + c d_y^2) + b d_x d_y`, :math:`d = \\mu'_i - p`;
    skip when :math:`\\sigma_i < 0` or :math:`\\alpha_i < 1/255`; stop before the first
    :math:`i` with :math:`T_{i-1}(1-\\alpha_i) < 10^{-4}`;
    :math:`F_p = \\sum_i f_i \\alpha_i T_{i-1}`, :math:`T_i = \\prod_{j \\le i}(1-\\alpha_j)`.

    ``nf`` composites only the first ``nf`` features (3: colour alone; the weights, and so
    ``t_final`` and ``last``, do not depend on it). A stopped pixel keeps its transmittance
    negated; a tile leaves its list once every pixel has stopped (checked every 8 Gaussians).
    ``centres[i] = i + 0.5`` and ``cst`` (:func:`consts`) are in the dtype of ``rows``;
    ``nf`` is 7 or 3.

    Returns ``out [H, W, nf]``, ``t_final [H, W]``, ``alpha [H, W]`` (``1 - t_final``) and
    ``last [H, W]`` (one past the intersection index of the last composited Gaussian, the
    backward's start).
    """
    zero, one, half, amax, amin, tmin, smax = cst[0], cst[1], cst[2], cst[3], cst[4], cst[5], cst[6]
    out = np.zeros((height, width, nf), rows.dtype)
    t_final = np.ones((height, width), rows.dtype)
    alpha = np.zeros((height, width), rows.dtype)
    last = np.zeros((height, width), np.int64)
    for chunk in prange(tile_order.shape[0]):
        st = np.empty(4 * PIX + nf * PIX, rows.dtype)
        kbuf = np.empty(1, rows.dtype)  # an int in the dtype (an int plus a float32 is float64)
        for u in range(PIX):  # the pixel's column and row in its tile
            st[F_X + _U(u)] = centres[u % TILE] - half
            st[F_Y + _U(u)] = centres[u // TILE] - half
        for t in tile_order[chunk]:
            if t < 0:
                break
            start, end = offsets[t], offsets[t + 1]
            if start == end:
                continue
            ty = t // tiles_w
            x_lo, y_lo = (t - ty * tiles_w) * TILE, ty * TILE
            pw, ph = min(TILE, width - x_lo), min(TILE, height - y_lo)
            x0, y0 = centres[x_lo], centres[y_lo]
            kbuf[0] = start  # intersection indices are exact in float32 below 2**24
            fstart = kbuf[0]
            for j in range(TILE):
                for i in range(TILE):
                    u = _U(j * TILE + i)
                    st[F_T + u] = one if (j < ph and i < pw) else -one
                    st[F_STOP + u] = fstart
            for u in range(nf * PIX):
                st[F_ACC + _U(u)] = zero
            for k in range(start, end):
                g = ids[k]  # (no row view: views refcount the parent atomically, which threads contend on)
                j0, j1 = _span(rows[g, 1], rows[g, 15], y_lo, ph)
                i0, i1 = _span(rows[g, 0], rows[g, 14], x_lo, pw)
                if j0 == j1 or i0 == i1:
                    continue
                mxl, my = rows[g, 0] - x0, rows[g, 1] - y0
                ha, cb, hc, op = half * rows[g, 2], rows[g, 3], half * rows[g, 4], rows[g, 5]
                kbuf[0] = k + 1
                r0, r1 = _U((j0 - y_lo) * TILE), _U((j1 - y_lo) * TILE)
                if nf == NF:
                    fv7 = (rows[g, 7], rows[g, 8], rows[g, 9], rows[g, 10], rows[g, 11], rows[g, 12], rows[g, 13])
                    _fwd_rows(st, r0, r1, mxl, my, ha, cb, hc, op, kbuf[0], cst, fv7)
                else:
                    fv = (rows[g, 7], rows[g, 8], rows[g, 9])
                    _fwd_rows(st, r0, r1, mxl, my, ha, cb, hc, op, kbuf[0], cst, fv)
                if (k - start) % 8 == 7:
                    n_live = 0
                    for u in range(PIX):
                        n_live += 1 if st[F_T + _U(u)] > zero else 0
                    if n_live == 0:
                        break
            for j in range(ph):
                for i in range(pw):
                    u = _U(j * TILE + i)
                    for f in range(nf):
                        out[y_lo + j, x_lo + i, f] = st[F_ACC + _U(f * PIX) + u]
                    t_final[y_lo + j, x_lo + i] = abs(st[F_T + u])
                    alpha[y_lo + j, x_lo + i] = one - abs(st[F_T + u])
                    last[y_lo + j, x_lo + i] = int(st[F_STOP + u])
    return out, t_final, alpha, last


@njit(parallel=True, cache=True, fastmath={"reassoc", "contract"}, error_model="numpy")
def backward(rows, ids, offsets, tile_order, tiles_w, width, height, t_final, last, g_rgb, g_depth, g_normal, g_alpha,
             cst, centres, grad):  # pragma: no cover - compiled
    """Per-intersection gradients into ``grad [n_isect, 13]`` (in the dtype of ``rows``; every row is
    written, zero where a Gaussian adds nothing, so it may be a reused buffer), back to front per
    pixel, from the gradients of the feature images ``g_rgb [H, W, 3]``, ``g_depth [H, W, 1]``,
    ``g_normal [H, W, 3]`` and of the alpha image ``g_alpha [H, W]`` (each C-contiguous in the
    dtype of ``rows``). ``tile_order`` must deal every tile that has intersections.

    With :math:`T_{i-1} = T_i / (1-\\alpha_i)` recovered from the final transmittance and
    :math:`S_i = \\sum_{j>i} f_j \\alpha_j T_{j-1}`:

    .. math::
        \\partial F/\\partial f_i = \\alpha_i T_{i-1},\\quad
        \\partial L/\\partial \\alpha_i = \\sum_c g_c \\big(f_{ic} T_{i-1} - S_{ic}/(1-\\alpha_i)\\big)
            + g_A T_n/(1-\\alpha_i)

    (the alpha image is :math:`A = 1 - T_n`); through :math:`\\alpha_i = o_i e^{-\\sigma_i}`
    unless capped at 0.99, where the gradient is zero. Gaussian by Gaussian, back to front,
    over the same pixel rows as the forward (:func:`_bwd_rows`); a Gaussian's sums over one
    tile go to its own intersection row.
    """
    zero, one, half, amax, amin, smax = cst[0], cst[1], cst[2], cst[3], cst[4], cst[6]
    for chunk in prange(tile_order.shape[0]):
        st = np.empty(B_SIZE, rows.dtype)
        kbuf = np.empty(1, rows.dtype)
        for u in range(PIX):
            st[B_X + _U(u)] = centres[u % TILE] - half
            st[B_Y + _U(u)] = centres[u // TILE] - half
        for t in tile_order[chunk]:
            if t < 0:
                break
            start = offsets[t]
            if start == offsets[t + 1]:
                continue
            ty = t // tiles_w
            x_lo, y_lo = (t - ty * tiles_w) * TILE, ty * TILE
            pw, ph = min(TILE, width - x_lo), min(TILE, height - y_lo)
            x0, y0 = centres[x_lo], centres[y_lo]
            kmax = start
            for j in range(TILE):
                for i in range(TILE):
                    u = _U(j * TILE + i)
                    inside = j < ph and i < pw
                    py, px = min(y_lo + j, height - 1), min(x_lo + i, width - 1)
                    st[B_T + u] = t_final[py, px] if inside else one
                    kbuf[0] = last[py, px] if inside else start
                    st[B_LST + u] = kbuf[0]
                    kmax = max(kmax, last[py, px] if inside else start)
                    for f in range(3):
                        st[B_G + _U(f * PIX) + u] = g_rgb[py, px, f] if inside else zero
                        st[B_G + _U((f + 4) * PIX) + u] = g_normal[py, px, f] if inside else zero
                    st[B_G + _U(3 * PIX) + u] = g_depth[py, px, 0] if inside else zero
                    for f in range(NF):
                        st[B_S + _U(f * PIX) + u] = zero
                    st[B_G + _U(NF * PIX) + u] = g_alpha[py, px] * t_final[py, px] if inside else zero
            for k in range(kmax, offsets[t + 1]):  # behind every pixel's last Gaussian
                for c in range(GROW):
                    grad[k, c] = zero
            for k in range(kmax - 1, start - 1, -1):
                g = ids[k]  # (no row view: views refcount the parent atomically, which threads contend on)
                j0, j1 = _span(rows[g, 1], rows[g, 15], y_lo, ph)
                i0, i1 = _span(rows[g, 0], rows[g, 14], x_lo, pw)
                if j0 == j1 or i0 == i1:
                    for c in range(GROW):
                        grad[k, c] = zero
                    continue
                fv = (rows[g, 7], rows[g, 8], rows[g, 9], rows[g, 10], rows[g, 11], rows[g, 12], rows[g, 13])
                kbuf[0] = k
                r0, r1 = _U((j0 - y_lo) * TILE), _U((j1 - y_lo) * TILE)
                gk = _bwd_rows(st, r0, r1, rows[g, 0] - x0, rows[g, 1] - y0, rows[g, 2], rows[g, 3], rows[g, 4],
                               rows[g, 5], kbuf[0], cst, fv)
                for c in range(GROW):
                    grad[k, c] = gk[c]
    return grad


@njit(parallel=True, cache=True)
def reduce_grads(grad, ids, n, n_chunks):  # pragma: no cover - compiled
    """Sum per-intersection gradient rows into ``[n, 13]`` per-Gaussian rows, in intersection order.

    In parallel over ``n_chunks`` ranges of Gaussians: each range scans every intersection and
    adds those of its own Gaussians, so each sum runs in the same order whatever the count."""
    out = np.zeros((n, GROW), grad.dtype)
    n_chunks = max(1, min(n_chunks, n // 256))
    for r in prange(n_chunks):
        lo, hi = r * n // n_chunks, (r + 1) * n // n_chunks
        for k in range(ids.shape[0]):
            g = ids[k]
            if lo <= g < hi:
                for c in range(GROW):
                    out[g, c] += grad[k, c]
    return out
