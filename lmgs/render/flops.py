"""Floating-point work of the compositing kernels, and the CPU's fp32 peak, for ``bench raster``.

The kernels (:mod:`lmgs.render._numba_composite`) run, for every tile intersection whose
alpha >= 1/255 box meets the tile, one vectorised loop over the 16 pixels of each tile row
the box spans. A *lane* is one pixel of such a row: its work is the same whether or not the
Gaussian contributes there (the tests are selects). Counting lanes over the tile lists gives
the kernels' work exactly, except that the forward leaves a tile early once every pixel has
stopped (so the forward count is an upper bound on what ran) and the backward starts each
tile at its last contributing intersection.

Floating-point operations per lane, counted from the kernels' source (a fused multiply-add
counts 2, a division, min, max or int/float conversion 1, compares and selects 0):

* forward: offsets 2, sigma 8, clamp 2, exp 38 (range reduction 8, degree-7 polynomial 14,
  the power of two 16), alpha 2, transmittance 2, weight 1: 55, plus 2 per composited
  feature (7, or 3 for ``render_mode="RGB"``);
* backward: offsets 2, sigma 8, clamp 2, exp 38, alpha 2, 1 / (1 - alpha) 2, T 1, weight 2,
  dL/dalpha 1 + 5 per feature, the feature gradient 2 and the suffix sum 2 per feature
  (9 x 7 = 63), cap 1, dL/dsigma 2, opacity 2, mean 10, conic 11: 147.
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

TILE = 16
FWD_FLOPS_BASE = 55
FWD_FLOPS_PER_FEATURE = 2
BWD_FLOPS = 147


def fwd_flops_per_lane(n_features: int) -> int:
    """Forward floating-point operations per lane when compositing ``n_features`` features."""
    return FWD_FLOPS_BASE + FWD_FLOPS_PER_FEATURE * n_features


def lanes(rows: np.ndarray, ids: np.ndarray, offsets: np.ndarray, tiles_w: int, width: int, height: int) -> int:
    """Pixel lanes the kernels run over the tile lists (see the module docstring).

    Args:
        rows: ``[N, 16]`` per-Gaussian rows (mean at 0, 1; box half-widths at 14, 15).
        ids, offsets: the tile lists (``ids[offsets[t]:offsets[t + 1]]`` for tile ``t``).
        tiles_w: tiles per image row; ``width``, ``height``: image size.

    Returns:
        ``16 x`` the number of (intersection, tile row) pairs where the Gaussian's box meets
        the tile in both directions.
    """
    if ids.shape[0] == 0:
        return 0
    tile = np.repeat(np.arange(offsets.shape[0] - 1), np.diff(offsets))
    ty, tx = tile // tiles_w, tile % tiles_w
    r = rows[ids].astype(np.float64)
    y_rows = _span_len(r[:, 1], r[:, 15], ty * TILE, np.minimum(TILE, height - ty * TILE))
    x_cols = _span_len(r[:, 0], r[:, 14], tx * TILE, np.minimum(TILE, width - tx * TILE))
    return int(TILE * np.where(x_cols > 0, y_rows, 0).sum())


def _span_len(m, ext, lo, n):
    """Count of pixel centres ``i + 0.5``, ``lo <= i < lo + n``, within ``m +- ext`` (as the kernels' ``_span``)."""
    a = np.clip(m - ext - 0.5, lo - 1.0, lo + n + 1.0)
    b = np.clip(m + ext - 0.5, lo - 1.0, lo + n + 1.0)
    i0 = np.maximum(lo, np.ceil(a))
    i1 = np.minimum(lo + n, np.floor(b) + 1)
    return np.where(ext < 0, 0, np.maximum(i1 - i0, 0))


def simd_fp32_lanes(flags: set[str]) -> int:
    """fp32 lanes of the widest vector unit the CPU flags name (AVX-512: 16, AVX2: 8, else SSE: 4)."""
    if "avx512f" in flags:
        return 16
    if "avx2" in flags:
        return 8
    return 4


def cpu_peak_gflops(cores: int, cpuinfo: str | None = None) -> dict:
    """fp32 peak of ``cores`` cores: cores x SIMD lanes x 2 (a fused multiply-add) x clock.

    One vector FMA per core per cycle at the width of the widest unit: what an AMD Zen 4
    core does with its two 256-bit FMA pipes (or one 512-bit op), a lower bound on Intel
    cores with two 512-bit FMA units. The clock is the ``cpu MHz`` of ``/proc/cpuinfo``
    (under a hypervisor: the nominal clock), ``cpuinfo`` its text (read when None).

    Returns:
        ``{"gflops": peak, "cores": ..., "lanes": ..., "ghz": ...}`` (gflops NaN when the
        clock is unknown).
    """
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo", encoding="utf-8") as fh:
                cpuinfo = fh.read()
        except OSError:
            cpuinfo = ""
    m = re.search(r"^cpu MHz\s*:\s*([0-9.]+)", cpuinfo, re.MULTILINE)
    ghz = float(m.group(1)) / 1e3 if m else math.nan
    f = re.search(r"^flags\s*:\s*(.*)$", cpuinfo, re.MULTILINE)
    n_lanes = simd_fp32_lanes(set(f.group(1).split()) if f else set())
    return {"gflops": cores * n_lanes * 2 * ghz, "cores": cores, "lanes": n_lanes, "ghz": ghz}


def usable_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1
