"""Numba CPU kernels of the tri-plane hash encoder (forward, backward to table and points).

Same definition as :meth:`lmgs.encoders.triplane.TriplaneEncoder.forward_torch`; kept apart
so the torch file reads as the definition. Work is split so no two threads write the same
memory: the forward and the point gradient run in parallel over points, the table gradient
in parallel over (plane, level) pairs, whose table slices are disjoint.
"""

from __future__ import annotations

import numba
import numpy as np

_PRIME_Y = np.int64(2654435761)
_PA = np.array([0, 1, 0], dtype=np.int64)
_PB = np.array([1, 2, 2], dtype=np.int64)


@numba.njit(inline="always", cache=True)
def _vertex(vx, vy, r, dense, T):
    if dense:
        return vx + vy * (r + 1)
    return (vx ^ (vy * _PRIME_Y)) & (T - 1)


@numba.njit(inline="always", cache=True)
def _cell(u, n, a, b, r, base, d, T):
    """Point ``n`` on plane ``(a, b)`` at resolution ``r``: the fractions ``tx, ty`` in its cell, the
    table rows ``i00, i10, i01, i11`` of the cell's corners and their bilinear weights
    ``w00, w10, w01, w11`` (one flat tuple: the same cell for the forward and both backwards)."""
    px = u[n, a] * r
    py = u[n, b] * r
    x0 = min(np.int64(np.floor(px)), r - 1)
    y0 = min(np.int64(np.floor(py)), r - 1)
    tx = px - x0
    ty = py - y0
    return (tx, ty, base + _vertex(x0, y0, r, d, T), base + _vertex(x0 + 1, y0, r, d, T),
            base + _vertex(x0, y0 + 1, r, d, T), base + _vertex(x0 + 1, y0 + 1, r, d, T),
            (1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty)


@numba.njit(parallel=True, cache=True, fastmath=False)
def triplane_forward(u, table, res, dense, offsets, T, out):
    """``out[n, p, l, :]`` = bilinear interpolation of the table at point ``n`` (zeroed here)."""
    N = u.shape[0]
    L = res.shape[0]
    F = table.shape[1]
    for n in numba.prange(N):
        for p in range(3):
            for lv in range(L):
                _, _, i00, i10, i01, i11, w00, w10, w01, w11 = _cell(u, n, _PA[p], _PB[p], res[lv], offsets[p, lv],
                                                                     dense[lv], T)
                for f in range(F):
                    out[n, p, lv, f] = w00 * table[i00, f] + w10 * table[i10, f] + w01 * table[i01, f] + w11 * table[i11, f]


@numba.njit(parallel=True, cache=True)
def triplane_backward_table(u, grad_out, res, dense, offsets, T, grad_table):
    """Accumulate :math:`\\partial L / \\partial \\text{table}` into ``grad_table`` (zeroed by the caller)."""
    N = u.shape[0]
    L = res.shape[0]
    F = grad_table.shape[1]
    for job in numba.prange(3 * L):
        p = job // L
        lv = job % L
        a = _PA[p]
        b = _PB[p]
        r = res[lv]
        base = offsets[p, lv]
        d = dense[lv]
        for n in range(N):
            _, _, i00, i10, i01, i11, w00, w10, w01, w11 = _cell(u, n, a, b, r, base, d, T)
            for f in range(F):
                g = grad_out[n, p, lv, f]
                grad_table[i00, f] += w00 * g
                grad_table[i10, f] += w10 * g
                grad_table[i01, f] += w01 * g
                grad_table[i11, f] += w11 * g


@numba.njit(parallel=True, cache=True)
def triplane_backward_points(u, table, grad_out, res, dense, offsets, T, grad_u):
    """:math:`\\partial L / \\partial u` through the bilinear weights (``grad_u`` zeroed by the caller)."""
    N = u.shape[0]
    L = res.shape[0]
    F = table.shape[1]
    for n in numba.prange(N):
        for p in range(3):
            a = _PA[p]
            b = _PB[p]
            for lv in range(L):
                r = res[lv]
                tx, ty, i00, i10, i01, i11, _, _, _, _ = _cell(u, n, a, b, r, offsets[p, lv], dense[lv], T)
                gx = 0.0
                gy = 0.0
                for f in range(F):
                    g = grad_out[n, p, lv, f]
                    t00 = table[i00, f]
                    t10 = table[i10, f]
                    t01 = table[i01, f]
                    t11 = table[i11, f]
                    gx += g * ((1 - ty) * (t10 - t00) + ty * (t11 - t01))
                    gy += g * ((1 - tx) * (t01 - t00) + tx * (t11 - t10))
                grad_u[n, a] += gx * r
                grad_u[n, b] += gy * r
