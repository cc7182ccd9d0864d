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


@numba.njit(parallel=True, cache=True, fastmath=False)
def triplane_forward(u, table, res, dense, offsets, T, out):
    """``out[n, p, l, :]`` = bilinear interpolation of the table at point ``n`` (zeroed here)."""
    N = u.shape[0]
    L = res.shape[0]
    F = table.shape[1]
    for n in numba.prange(N):
        for p in range(3):
            a = _PA[p]
            b = _PB[p]
            for lv in range(L):
                r = res[lv]
                px = u[n, a] * r
                py = u[n, b] * r
                x0 = min(np.int64(np.floor(px)), r - 1)
                y0 = min(np.int64(np.floor(py)), r - 1)
                tx = px - x0
                ty = py - y0
                base = offsets[p, lv]
                d = dense[lv]
                i00 = base + _vertex(x0, y0, r, d, T)
                i10 = base + _vertex(x0 + 1, y0, r, d, T)
                i01 = base + _vertex(x0, y0 + 1, r, d, T)
                i11 = base + _vertex(x0 + 1, y0 + 1, r, d, T)
                w00 = (1 - tx) * (1 - ty)
                w10 = tx * (1 - ty)
                w01 = (1 - tx) * ty
                w11 = tx * ty
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
            px = u[n, a] * r
            py = u[n, b] * r
            x0 = min(np.int64(np.floor(px)), r - 1)
            y0 = min(np.int64(np.floor(py)), r - 1)
            tx = px - x0
            ty = py - y0
            i00 = base + _vertex(x0, y0, r, d, T)
            i10 = base + _vertex(x0 + 1, y0, r, d, T)
            i01 = base + _vertex(x0, y0 + 1, r, d, T)
            i11 = base + _vertex(x0 + 1, y0 + 1, r, d, T)
            for f in range(F):
                g = grad_out[n, p, lv, f]
                grad_table[i00, f] += (1 - tx) * (1 - ty) * g
                grad_table[i10, f] += tx * (1 - ty) * g
                grad_table[i01, f] += (1 - tx) * ty * g
                grad_table[i11, f] += tx * ty * g


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
                px = u[n, a] * r
                py = u[n, b] * r
                x0 = min(np.int64(np.floor(px)), r - 1)
                y0 = min(np.int64(np.floor(py)), r - 1)
                tx = px - x0
                ty = py - y0
                base = offsets[p, lv]
                d = dense[lv]
                i00 = base + _vertex(x0, y0, r, d, T)
                i10 = base + _vertex(x0 + 1, y0, r, d, T)
                i01 = base + _vertex(x0, y0 + 1, r, d, T)
                i11 = base + _vertex(x0 + 1, y0 + 1, r, d, T)
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
