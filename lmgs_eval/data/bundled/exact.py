"""Arithmetic whose bits do not depend on the CPU: what the generator uses in place of the
library calls that pick their kernels by instruction set.

A bundled subject must be the same bytes on every host (its manifest's sha256 is what records
are matched on), and its files keep full-precision floats (``transforms_*.json``) and
thresholded or rounded images, so one last bit decides. Three kinds of call do not give the
same last bit everywhere:

* numpy's float64 ``sin``, ``cos`` and ``exp`` run SVML / AVX-512F kernels on an AVX-512 CPU
  and the C library (glibc) elsewhere. Here they are glibc's, called through :mod:`math`
  (:func:`sin`, :func:`cos`, :func:`exp`): the same bits numpy gives on an AVX2 CPU (checked on
  10^6 arguments), on every CPU.
* numpy's matrix products and ``linalg.inv`` run OpenBLAS, whose kernels differ by CPU
  (Haswell, SkylakeX, ...). :func:`matmul`, :func:`matvec3` and :func:`inv4` are written out
  with IEEE operations in a fixed order and an exactly rounded fused multiply-add (LLVM's
  ``llvm.fma``: the FMA instruction, or libm's ``fma`` where there is none, rounded alike);
  the order is the one OpenBLAS's Haswell kernels use (gemm: one product, then fused
  multiply-adds over k; gemv (3 x 3): ``fma(a2, x2, fma(a0, x0, a1 x1))``; getrf/getrs:
  OpenBLAS's left-looking ``getf2`` and the triangular solves, plain sums, multiplied by
  reciprocal pivots), so the numbers equal those an AVX2 host's numpy gave (checked on 10^4
  random matrices and on the default builds).
* ``numpy.linalg.norm`` of a vector and ``numpy.convolve`` call BLAS ``ddot``:
  :func:`norm3` and :func:`box5` add in ddot's order.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic


def _apply(fn, x) -> np.ndarray:
    a = np.asarray(x, np.float64)
    return np.fromiter(map(fn, a.ravel().tolist()), np.float64, a.size).reshape(a.shape)


def sin(x) -> np.ndarray:
    """``sin`` of a float64 array by the C library (numpy's own kernels differ on AVX-512)."""
    return _apply(math.sin, x)


def cos(x) -> np.ndarray:
    """``cos`` of a float64 array by the C library."""
    return _apply(math.cos, x)


def exp(x) -> np.ndarray:
    """``exp`` of a float64 array by the C library."""
    return _apply(math.exp, x)


def sinc(x) -> np.ndarray:
    """``numpy.sinc`` (``sin(pi x) / (pi x)``, 1 at 0) with :func:`sin`."""
    y = np.pi * np.where(np.asarray(x, np.float64) == 0, 1.0e-20, x)
    return sin(y) / y


@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (IEEE fusedMultiplyAdd)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


@njit(cache=True, fastmath=False)
def _matmul(a, b):
    n, k = a.shape
    m = b.shape[1]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            acc = a[i, 0] * b[0, j]
            for t in range(1, k):
                acc = _fma(a[i, t], b[t, j], acc)
            out[i, j] = acc
    return out


def matmul(a, b) -> np.ndarray:
    """``a @ b`` for 2-D float64 arrays, as OpenBLAS's Haswell dgemm rounds it, on any CPU."""
    a = np.ascontiguousarray(a, np.float64)
    b = np.ascontiguousarray(b, np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[0] or a.shape[1] < 1:
        raise ValueError(f"matmul: shapes {a.shape} and {b.shape}")
    return _matmul(a, b)


@njit(cache=True, fastmath=False)
def _matvec3(a, x):
    out = np.empty(a.shape[0])
    for i in range(a.shape[0]):
        out[i] = _fma(a[i, 2], x[2], _fma(a[i, 0], x[0], a[i, 1] * x[1]))
    return out


def matvec3(a, x) -> np.ndarray:
    """``a @ x`` for an ``[N, 3]`` matrix and a 3-vector, as OpenBLAS's Haswell dgemv rounds it."""
    a = np.ascontiguousarray(a, np.float64)
    x = np.ascontiguousarray(x, np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or x.shape != (3,):
        raise ValueError(f"matvec3: shapes {a.shape} and {x.shape}")
    return _matvec3(a, x)


@njit(cache=True, fastmath=False)
def _inv(m):
    n = m.shape[0]
    a = m.copy()  # a[row, col]; LU in place (OpenBLAS getf2: left-looking, column by column)
    ipiv = np.zeros(n, np.int64)
    for j in range(n):
        for i in range(j):  # earlier row swaps, applied to this column
            ip = ipiv[i]
            if ip != i:
                t = a[i, j]
                a[i, j] = a[ip, j]
                a[ip, j] = t
        for i in range(1, j):  # U part: b_i -= L[i, :i] . b[:i] (ddot, plain sums)
            d = 0.0
            for k in range(i):
                d = d + a[i, k] * a[k, j]
            a[i, j] = a[i, j] - d
        if j > 0:  # b[j:] -= L[j:, :j] b[:j] (dgemv's tail rows: plain sums)
            for r in range(j, n):
                d = a[r, 0] * a[0, j]
                for k in range(1, j):
                    d = d + a[r, k] * a[k, j]
                a[r, j] = a[r, j] - d
        jp = j
        best = abs(a[j, j])
        for r in range(j + 1, n):
            if abs(a[r, j]) > best:
                best = abs(a[r, j])
                jp = r
        ipiv[j] = jp
        piv = a[jp, j]
        if piv == 0.0:
            raise ZeroDivisionError("singular matrix")
        rec = 1.0 / piv
        if jp != j:
            for k in range(j + 1):
                t = a[j, k]
                a[j, k] = a[jp, k]
                a[jp, k] = t
        for r in range(j + 1, n):
            a[r, j] = a[r, j] * rec
    x = np.eye(n)  # getrs: the pivots, then L (unit) forward, U backward by reciprocal pivots
    for i in range(n):
        ip = ipiv[i]
        if ip != i:
            for c in range(n):
                t = x[i, c]
                x[i, c] = x[ip, c]
                x[ip, c] = t
    for c in range(n):
        for i in range(n):
            for k in range(i + 1, n):
                x[k, c] = x[k, c] - x[i, c] * a[k, i]
        for i in range(n - 1, -1, -1):
            x[i, c] = x[i, c] * (1.0 / a[i, i])
            for k in range(i):
                x[k, c] = x[k, c] - x[i, c] * a[k, i]
    return x


def inv4(m) -> np.ndarray:
    """The inverse of a 4 x 4 matrix, as numpy's ``linalg.inv`` gives it with OpenBLAS's Haswell
    kernels (LU with partial pivoting), on any CPU."""
    m = np.ascontiguousarray(m, np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"inv4: shape {m.shape}")
    try:
        return _inv(m)
    except ZeroDivisionError:
        raise np.linalg.LinAlgError("Singular matrix") from None


def norm3(v) -> float:
    """Euclidean length of a 3-vector, summed in BLAS ddot's order."""
    x, y, z = (float(c) for c in np.asarray(v, np.float64))
    return math.sqrt((x * x + y * y) + z * z)


def box5(s: np.ndarray) -> np.ndarray:
    """``numpy.convolve(s, ones(5) / 5, "same")`` (``len(s) >= 5``) with ddot's left-to-right sums."""
    s = np.asarray(s, np.float64)
    p = np.concatenate([np.zeros(2), s, np.zeros(2)]) * 0.2
    out = p[0 : len(s)].copy()
    for k in range(1, 5):
        out = out + p[k : k + len(s)]
    return out
