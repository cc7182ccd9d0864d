"""The GPU path when gsplat is not installed, in Triton: the EWA projection and tile compositing.

:func:`rasterize_triton` is the ``"triton"`` backend of :func:`lmgs.render.rasterize`: the
projection kernels (:class:`_Project`, below the compositor) write the compositor's packed rows
directly, and :class:`_CompositePacked` bins and composites them. :func:`composite` composites
the outputs of torch's :func:`lmgs.render._projection.project` instead (the path when the camera
needs a gradient): same inputs and result as :func:`lmgs.render._cpu.composite`. Both give the
image's definition: each 16x16 tile composites its Gaussians front to back,

.. math::
    \\alpha_i = \\min(0.99,\\ o_i e^{-\\sigma_i}),\\quad
    \\sigma_i = \\tfrac12 (a d_x^2 + c d_y^2) + b d_x d_y,\\quad d = \\mu'_i - p,

skipping :math:`\\sigma_i < 0` and :math:`\\alpha_i < 1/255`, and stopping before the first
Gaussian that would take the transmittance below :math:`10^{-4}`.

Binning (:func:`bin_tiles`) is on the device, three small Triton kernels around one
``cumsum`` and one sort, with one host synchronisation (the number of (tile, Gaussian) pairs,
which sizes their buffers): ``_prepare_kernel`` packs each Gaussian's float32 row and features
and computes its tile rectangle and a depth key; ``_keys_kernel`` writes every pair of its
rectangle, in Gaussian order, with the key ``tile * 2**32 + depth key``; one stable sort
orders them by tile and then front to back (equal depths keep index order, as the CPU path);
``_ranges_kernel`` gathers the sorted Gaussian ids and writes each tile's range. The forward
saves the packed rows, the tile lists and its final transmittance; the backward reuses them
and reads the cotangents through their strides, so it launches one zero fill and its kernel
(none on the projection kernels' path: their forward leaves the gradient buffer zeroed).

One Triton program per tile holds its 256 pixels and walks its range in chunks of
``BLOCK_G`` Gaussians: a ``[256, BLOCK_G]`` block of alphas, an inclusive ``cumprod`` of
``1 - alpha`` along the chunk for the transmittance (a Gaussian is kept when the product
up to and including it is still at least :math:`10^{-4}`: the product only falls, so this
is exactly the stop rule), and the weighted features as one ``tl.dot`` with the chunk's
features (float32 throughout, ``input_precision="ieee"``: no TF32). A tile stops when every
pixel has stopped.

The backward walks the same chunks front to back again, with the same tests, and needs no
per-pixel stop index: with :math:`w_i = \\alpha_i T_{i-1}`, :math:`F = \\sum_i w_i f_i` and
:math:`A = 1 - T_n`,

.. math::
    \\frac{\\partial L}{\\partial \\alpha_i} = T_{i-1}\\, g\\cdot f_i
        - \\frac{R_i - g_A T_n}{1 - \\alpha_i},\\qquad
    R_i = \\sum_{j>i} w_j\\, g\\cdot f_j = g\\cdot F - \\sum_{j\\le i} w_j\\, g\\cdot f_j,

(:math:`g = \\partial L/\\partial F`, :math:`g_A = \\partial L/\\partial A`), zero where the
alpha is capped at 0.99. Each program sums its pixels' contributions to a Gaussian and adds
them to the Gaussian's gradient with atomics (so the order of those float32 sums, and their
last bits, vary from run to run, as gsplat's do).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import triton
import triton.language as tl

from lmgs.render._projection import (ALPHA_MAX, ALPHA_MIN, EPS2D, LOG_SCALE_MAX, LOG_SCALE_MIN, N_FEATURES,
                                     NEAR_PLANE, T_MIN, TILE, tile_rects)
from lmgs.types import Camera

FP = 16  # feature columns composited (7 used, zero-padded: tl.dot wants 16 or more)
PARAMS = 8  # per-Gaussian row: mx, my, conic a, b, c, opacity, two pads
GROW = 16  # per-Gaussian gradient row: the 6 parameters (columns 0-5), the 7 features (6-12), pads
BLOCK_G = 16  # Gaussians per chunk
NUM_WARPS = 8
BLOCK_N = 128  # Gaussians per program of the binning kernels
BLOCK_P = 1024  # sorted pairs per program of the range kernel
MAX_PAIRS = 2**31 - 1  # pair positions and tile offsets are int32

_AMAX = tl.constexpr(ALPHA_MAX)
_AMIN = tl.constexpr(ALPHA_MIN)
_TMIN = tl.constexpr(T_MIN)
_TILE = tl.constexpr(TILE)
_INV_TILE = tl.constexpr(1.0 / TILE)  # a power of two: multiplying is dividing, exactly
_PIX = tl.constexpr(TILE * TILE)
_NF = tl.constexpr(N_FEATURES)
_GROW = tl.constexpr(GROW)
_SIGN = tl.constexpr(-(2**31))  # the int32 sign bit
_LOW = tl.constexpr(2**32)  # a pair's key: tile * 2**32 + depth key (32 bits, unsigned)
_BIG = tl.constexpr(1e9)  # above any tile count: clamps a rectangle before it becomes an integer


@triton.jit
def _prepare_kernel(means_ptr, conics_ptr, opac_ptr, feat_ptr, radii_ptr, depth_ptr, params_ptr, feats_ptr,
                    info_ptr, n, tiles_w, tiles_h, DEPTH_BITS: tl.constexpr, BLOCK_N: tl.constexpr,
                    FP: tl.constexpr):
    """Per Gaussian: its float32 compositing row and features, its tile rectangle and a depth key.

    ``info`` is int32 ``[5, n]``: tile count, first tile column, first tile row, columns, and the
    depth key, an int32 whose bits read as unsigned order the Gaussians by depth: the float32
    depth's bits (positive: sign bit set; negative: all bits flipped; -0 as +0) when
    ``DEPTH_BITS``, else ``depth_ptr`` holds int32 ranks already. The rectangle is
    :func:`lmgs.render._projection.tile_rects`'s, in float64 like it.
    """
    i = tl.program_id(0) * BLOCK_N + tl.arange(0, BLOCK_N)
    m = i < n
    mx = tl.load(means_ptr + 2 * i, mask=m, other=0.0)
    my = tl.load(means_ptr + 2 * i + 1, mask=m, other=0.0)
    row = params_ptr + i * 8
    tl.store(row + 0, mx.to(tl.float32), mask=m)
    tl.store(row + 1, my.to(tl.float32), mask=m)
    for c in tl.static_range(3):
        tl.store(row + 2 + c, tl.load(conics_ptr + 3 * i + c, mask=m, other=0.0).to(tl.float32), mask=m)
    tl.store(row + 5, tl.load(opac_ptr + i, mask=m, other=0.0).to(tl.float32), mask=m)
    tl.store(row + 6, tl.zeros([BLOCK_N], tl.float32), mask=m)
    tl.store(row + 7, tl.zeros([BLOCK_N], tl.float32), mask=m)
    cols = tl.arange(0, FP)
    f = tl.load(feat_ptr + i[:, None] * _NF + cols[None, :], mask=m[:, None] & (cols[None, :] < _NF), other=0.0)
    tl.store(feats_ptr + i[:, None] * FP + cols[None, :], f.to(tl.float32), mask=m[:, None])

    r = tl.load(radii_ptr + i, mask=m, other=0)
    if DEPTH_BITS:
        dkey = depth_key(tl.load(depth_ptr + i, mask=m, other=0.0))
    else:
        dkey = tl.load(depth_ptr + i, mask=m, other=0)
    store_tile_info(info_ptr, i, m, n, mx.to(tl.float64), my.to(tl.float64), r, dkey, tiles_w, tiles_h, True)


@triton.jit
def depth_key(d):
    """float32 depths as int32 keys whose bits, read as unsigned, order them: positive depths get
    the sign bit set, negative ones all bits flipped, -0 is +0."""
    b = tl.where(d == 0.0, 0.0, d).to(tl.int32, bitcast=True)
    return tl.where(b < 0, ~b, b ^ _SIGN)


@triton.jit
def store_tile_info(info_ptr, i, m, n, xd, yd, r, dkey, tiles_w, tiles_h, WITH_KEY: tl.constexpr):
    """``info [5, n]`` of Gaussians ``i`` (where ``m``): the tile count, first tile column, first
    tile row and columns of the rectangle :func:`lmgs.render._projection.tile_rects` gives for the
    float64 mean ``(xd, yd)`` and int32 radius ``r`` (0: culled, no tiles), and the depth key
    (not written unless ``WITH_KEY``)."""
    rd = r.to(tl.float64)
    x0 = tl.minimum(tl.minimum(tl.maximum(tl.floor((xd - rd) * _INV_TILE), 0.0), _BIG).to(tl.int32), tiles_w)
    x1 = tl.minimum(tl.minimum(tl.maximum(tl.ceil((xd + rd) * _INV_TILE), 0.0), _BIG).to(tl.int32), tiles_w)
    y0 = tl.minimum(tl.minimum(tl.maximum(tl.floor((yd - rd) * _INV_TILE), 0.0), _BIG).to(tl.int32), tiles_h)
    y1 = tl.minimum(tl.minimum(tl.maximum(tl.ceil((yd + rd) * _INV_TILE), 0.0), _BIG).to(tl.int32), tiles_h)
    vis = r > 0
    x0 = tl.where(vis, x0, 0)
    y0 = tl.where(vis, y0, 0)
    nx = tl.where(vis, x1 - x0, 0)
    cnt = tl.maximum(nx * tl.where(vis, y1 - y0, 0), 0)
    tl.store(info_ptr + i, cnt, mask=m)
    tl.store(info_ptr + n + i, x0, mask=m)
    tl.store(info_ptr + 2 * n + i, y0, mask=m)
    tl.store(info_ptr + 3 * n + i, nx, mask=m)
    if WITH_KEY:
        tl.store(info_ptr + 4 * n + i, dkey, mask=m)


@triton.jit
def _keys_kernel(info_ptr, ends_ptr, keys_ptr, gid_ptr, n, tiles_w, BLOCK_N: tl.constexpr):
    """Each Gaussian's (tile, Gaussian) pairs at its place ``ends[i] - count[i]`` of the pair
    buffer (Gaussians in index order, each one's tiles row by row): key ``tile * 2**32 +``
    its depth key read as unsigned, and its index."""
    i = tl.program_id(0) * BLOCK_N + tl.arange(0, BLOCK_N)
    m = i < n
    cnt = tl.load(info_ptr + i, mask=m, other=0)
    x0 = tl.load(info_ptr + n + i, mask=m, other=0)
    y0 = tl.load(info_ptr + 2 * n + i, mask=m, other=0)
    nx = tl.maximum(tl.load(info_ptr + 3 * n + i, mask=m, other=1), 1)
    dk = tl.load(info_ptr + 4 * n + i, mask=m, other=0).to(tl.int64)
    low = tl.where(dk < 0, dk + _LOW, dk)
    start = tl.load(ends_ptr + i, mask=m, other=0) - cnt
    top = tl.max(cnt, axis=0)
    j = 0
    while j < top:
        live = j < cnt
        q = j // nx
        tile = (y0 + q) * tiles_w + x0 + (j - q * nx)
        tl.store(keys_ptr + start + j, tile.to(tl.int64) * _LOW + low, mask=live)
        tl.store(gid_ptr + start + j, i, mask=live)
        j += 1


@triton.jit
def _ranges_kernel(skeys_ptr, perm_ptr, gid_ptr, ids_ptr, offsets_ptr, total, n_tiles, BLOCK_P: tl.constexpr):
    """From the sorted keys and the sort's permutation: the Gaussian of each sorted pair, and
    ``offsets[t]``, the first pair of tile ``t`` or later (``total`` past the last pair's tile).
    Each offset is written by one program: the pair at which the tile changes, or the last."""
    p = tl.program_id(0) * BLOCK_P + tl.arange(0, BLOCK_P)
    m = p < total
    tl.store(ids_ptr + p, tl.load(gid_ptr + tl.load(perm_ptr + p, mask=m, other=0), mask=m, other=0), mask=m)
    tile = (tl.load(skeys_ptr + p, mask=m, other=0) >> 32).to(tl.int32)
    prev = (tl.load(skeys_ptr + p - 1, mask=m & (p > 0), other=-_LOW) >> 32).to(tl.int32)
    gap = tl.where(m, tile - prev, 0)  # tiles prev + 1 .. tile start at p
    tail = tl.where(m & (p == total - 1), n_tiles - tile, 0)  # tiles after the last pair's: at total
    end = p * 0 + total
    top = tl.max(tl.maximum(gap, tail), axis=0)
    j = 0
    while j < top:
        tl.store(offsets_ptr + prev + 1 + j, p, mask=j < gap)
        tl.store(offsets_ptr + tile + 1 + j, end, mask=j < tail)
        j += 1


@triton.jit
def _pixels(tile, tiles_w, width, height):
    """Pixel indices of a tile (row-major 16x16), their columns and rows, whether each is
    inside the image, and their centres."""
    ty = tile // tiles_w
    tx = tile - ty * tiles_w
    pix = tl.arange(0, _PIX)
    px = tx * _TILE + pix % _TILE
    py = ty * _TILE + pix // _TILE
    inside = (px < width) & (py < height)
    return py * width + px, px, py, inside, px.to(tl.float32) + 0.5, py.to(tl.float32) + 0.5


@triton.jit
def _chunk(params_ptr, feat_ptr, ids_ptr, k0, end, fx, fy, T, done, BLOCK_G: tl.constexpr, FP: tl.constexpr):
    """The chunk of Gaussians ``k0 .. k0 + BLOCK_G`` of a tile: their ids, what the pixels keep.

    Returns ``g, valid, dx, dy, e, raw, al, P, f``: ``al`` the kept alphas (zero where skipped,
    stopped or done), ``P`` the transmittance after each Gaussian before the stop test
    (``T * cumprod(1 - alpha)``), ``e = exp(-sigma)``, ``raw = o * e``, ``f`` the features.
    """
    k = k0 + tl.arange(0, BLOCK_G)
    valid = k < end
    g = tl.load(ids_ptr + k, mask=valid, other=0)
    row = params_ptr + g * 8
    mx = tl.load(row + 0, mask=valid, other=0.0)
    my = tl.load(row + 1, mask=valid, other=0.0)
    ca = tl.load(row + 2, mask=valid, other=0.0)
    cb = tl.load(row + 3, mask=valid, other=0.0)
    cc = tl.load(row + 4, mask=valid, other=0.0)
    op = tl.load(row + 5, mask=valid, other=0.0)
    dx = mx[None, :] - fx[:, None]
    dy = my[None, :] - fy[:, None]
    sigma = 0.5 * (ca[None, :] * dx * dx + cc[None, :] * dy * dy) + cb[None, :] * dx * dy
    e = tl.exp(-tl.maximum(sigma, 0.0))
    raw = op[None, :] * e
    al = tl.minimum(raw, _AMAX)
    keep = (sigma >= 0) & (al >= _AMIN) & valid[None, :] & (done[:, None] == 0)
    al = tl.where(keep, al, 0.0)
    P = T[:, None] * tl.cumprod(1.0 - al, axis=1)
    al = tl.where(P >= _TMIN, al, 0.0)
    cols = tl.arange(0, FP)
    f = tl.load(feat_ptr + g[:, None] * FP + cols[None, :], mask=valid[:, None], other=0.0)
    return g, valid, dx, dy, e, raw, al, P, f


@triton.jit
def _advance(T, done, al, P):
    """Transmittance after the chunk's kept Gaussians, and which pixels have stopped."""
    T = tl.minimum(T, tl.min(tl.where(al > 0, P, 1.0), axis=1))
    done = done | (tl.min(P, axis=1) < _TMIN)
    return T, done


@triton.jit
def _forward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, out_ptr, alpha_ptr, tfinal_ptr, width, height,
                    tiles_w, BLOCK_G: tl.constexpr, FP: tl.constexpr):
    """One tile: features ``out [H*W, 7]`` and ``alpha = 1 - T`` in the outputs' dtype (stored from
    float32), and the float32 final transmittance ``T`` the backward reads."""
    tile = tl.program_id(0)
    lin, px, py, inside, fx, fy = _pixels(tile, tiles_w, width, height)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    T = tl.full([_PIX], 1.0, tl.float32)
    done = inside == 0
    acc = tl.zeros([_PIX, FP], tl.float32)
    k0 = start
    while (k0 < end) & (tl.max((done == 0).to(tl.int32), axis=0) > 0):
        g, valid, dx, dy, e, raw, al, P, f = _chunk(params_ptr, feat_ptr, ids_ptr, k0, end, fx, fy, T, done,
                                                    BLOCK_G, FP)
        w = al * (P / (1.0 - al))
        acc += tl.dot(w, f, input_precision="ieee")
        T, done = _advance(T, done, al, P)
        k0 += BLOCK_G
    cols = tl.arange(0, FP)
    tl.store(out_ptr + lin[:, None] * _NF + cols[None, :], acc, mask=inside[:, None] & (cols[None, :] < _NF))
    tl.store(alpha_ptr + lin, 1.0 - T, mask=inside)
    tl.store(tfinal_ptr + lin, T, mask=inside)


@triton.jit
def _backward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, out_ptr, tfinal_ptr, grgb_ptr, gdep_ptr, gnrm_ptr,
                     galpha_ptr, grad_ptr, width, height, tiles_w, gr_sy, gr_sx, gr_sc, gd_sy, gd_sx, gn_sy, gn_sx,
                     gn_sc, ga_sy, ga_sx, HAS_RGB: tl.constexpr, HAS_DEPTH: tl.constexpr, HAS_NORMAL: tl.constexpr,
                     HAS_ALPHA: tl.constexpr, BLOCK_G: tl.constexpr, FP: tl.constexpr):
    """One tile's gradients, added with atomics to ``grad [N, 16]`` (row: the 6 parameters, then the
    7 features). The cotangents of the features, ``grgb [H, W, 3]``, ``gdep [H, W, 1]`` and
    ``gnrm [H, W, 3]`` (often views of one ``[H, W, 7]``), and ``galpha [H, W, 1]`` are read
    through their strides (any layout, expanded ones included) and dtype; one left out
    (``HAS_*`` false: its pointer is not read) is zero."""
    tile = tl.program_id(0)
    lin, px, py, inside, fx, fy = _pixels(tile, tiles_w, width, height)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    cols = tl.arange(0, FP)
    c2 = cols[None, :]
    in2 = inside[:, None]
    pmask = in2 & (c2 < _NF)
    gvec = tl.zeros([_PIX, FP], tl.float32)  # [PIX, FP]
    if HAS_RGB:
        gvec += tl.load(grgb_ptr + py[:, None] * gr_sy + px[:, None] * gr_sx + c2 * gr_sc, mask=in2 & (c2 < 3),
                        other=0.0).to(tl.float32)
    if HAS_DEPTH:
        gvec += tl.load(gdep_ptr + py[:, None] * gd_sy + px[:, None] * gd_sx + c2 * 0, mask=in2 & (c2 == 3),
                        other=0.0).to(tl.float32)
    if HAS_NORMAL:
        gvec += tl.load(gnrm_ptr + py[:, None] * gn_sy + px[:, None] * gn_sx + (c2 - 4) * gn_sc,
                        mask=in2 & (c2 >= 4) & (c2 < _NF), other=0.0).to(tl.float32)
    feat = tl.load(out_ptr + lin[:, None] * _NF + cols[None, :], mask=pmask, other=0.0).to(tl.float32)
    total = tl.sum(gvec * feat, axis=1)
    if HAS_ALPHA:
        ga_t = (tl.load(galpha_ptr + py * ga_sy + px * ga_sx, mask=inside, other=0.0).to(tl.float32)
                * tl.load(tfinal_ptr + lin, mask=inside, other=1.0))
    else:
        ga_t = tl.zeros([_PIX], tl.float32)
    T = tl.full([_PIX], 1.0, tl.float32)
    done = inside == 0
    prefix = tl.zeros([_PIX], tl.float32)
    k0 = start
    while (k0 < end) & (tl.max((done == 0).to(tl.int32), axis=0) > 0):
        g, valid, dx, dy, e, raw, al, P, f = _chunk(params_ptr, feat_ptr, ids_ptr, k0, end, fx, fy, T, done,
                                                    BLOCK_G, FP)
        t_before = P / (1.0 - al)
        w = al * t_before
        gf = tl.dot(gvec, tl.trans(f), input_precision="ieee")  # [PIX, BLOCK_G]: g . f_k
        contrib = w * gf
        rest = total[:, None] - (tl.cumsum(contrib, axis=1) + prefix[:, None])
        d_al = tl.where(al > 0, t_before * gf - (rest - ga_t[:, None]) / (1.0 - al), 0.0)
        prefix += tl.sum(contrib, axis=1)
        d_raw = tl.where(raw < _AMAX, d_al, 0.0)
        d_sigma = -d_raw * raw
        ca = tl.load(params_ptr + g * 8 + 2, mask=valid, other=0.0)
        cb = tl.load(params_ptr + g * 8 + 3, mask=valid, other=0.0)
        cc = tl.load(params_ptr + g * 8 + 4, mask=valid, other=0.0)
        grow = grad_ptr + g * _GROW
        tl.atomic_add(grow + 0, tl.sum(d_sigma * (ca[None, :] * dx + cb[None, :] * dy), axis=0), mask=valid)
        tl.atomic_add(grow + 1, tl.sum(d_sigma * (cc[None, :] * dy + cb[None, :] * dx), axis=0), mask=valid)
        tl.atomic_add(grow + 2, tl.sum(d_sigma * 0.5 * dx * dx, axis=0), mask=valid)
        tl.atomic_add(grow + 3, tl.sum(d_sigma * dx * dy, axis=0), mask=valid)
        tl.atomic_add(grow + 4, tl.sum(d_sigma * 0.5 * dy * dy, axis=0), mask=valid)
        tl.atomic_add(grow + 5, tl.sum(d_raw * e, axis=0), mask=valid)
        d_f = tl.dot(tl.trans(w), gvec, input_precision="ieee")  # [BLOCK_G, FP]
        tl.atomic_add(grow[:, None] + 6 + cols[None, :], d_f, mask=valid[:, None] & (cols[None, :] < _NF))
        T, done = _advance(T, done, al, P)
        k0 += BLOCK_G


def tile_grid(width: int, height: int) -> tuple[int, int, int]:
    """``(tiles_w, tiles_h, n_tiles)`` of a ``width x height`` image."""
    tiles_w, tiles_h = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    return tiles_w, tiles_h, tiles_w * tiles_h


def bin_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
              radii: torch.Tensor, depths: torch.Tensor, width: int, height: int):
    """The kernels' inputs, packed and binned on the device with one host synchronisation.

    Returns ``params`` (float32 ``[N, 8]``: mean, conic, opacity, pads), ``feats`` (float32
    ``[N, 16]``: the 7 features, zero-padded), ``ids`` (int32 Gaussian indices, tile by tile,
    front to back, equal depths in index order), ``offsets`` (int32 ``[n_tiles + 1]``: tile
    ``t`` holds ``ids[offsets[t]:offsets[t+1]]``), ``tiles_w`` and ``n_tiles``.

    Work per call: ``_prepare_kernel``, then :func:`bin_info` (``torch.cumsum`` of the tile
    counts, reading the pair count back (the synchronisation: it sizes the pair buffers),
    ``_keys_kernel``, one stable ``torch.sort`` of the int64 keys, ``_ranges_kernel``); for
    depths other than float32 a stable ``argsort`` gives the depth keys first (two more torch
    calls). Equal to :func:`bin_tiles_reference`.
    """
    dev, n = means2d.device, means2d.shape[0]
    tiles_w, tiles_h, n_tiles = tile_grid(width, height)
    params = torch.empty(n, PARAMS, dtype=torch.float32, device=dev)
    feats = torch.empty(n, FP, dtype=torch.float32, device=dev)
    info = torch.empty(5, n, dtype=torch.int32, device=dev)
    if n:
        radii, depths = radii.to(dev), depths.to(dev)
        bits = depths.dtype == torch.float32
        if not bits:  # the depth key is the rank of a stable sort
            dkey = torch.empty(n, dtype=torch.int32, device=dev)
            rank_depths(depths, dkey)
        _prepare_kernel[(triton.cdiv(n, BLOCK_N),)](
            means2d.contiguous(), conics.contiguous(), opacities.contiguous(), features.contiguous(),
            radii.contiguous(), depths.contiguous() if bits else dkey, params, feats, info, n, tiles_w, tiles_h,
            DEPTH_BITS=bits, BLOCK_N=BLOCK_N, FP=FP)
    ids, offsets = bin_info(info, n_tiles, tiles_w)
    return params, feats, ids, offsets, tiles_w, n_tiles


def rank_depths(depths: torch.Tensor, out: torch.Tensor) -> None:
    """``out[i]`` (int32): the rank of ``depths[i]`` in a stable sort, the depth key of depths that
    are not float32 (two torch calls)."""
    n = depths.shape[0]
    out[torch.argsort(depths, stable=True)] = torch.arange(n, dtype=torch.int32, device=out.device)


def bin_info(info: torch.Tensor, n_tiles: int, tiles_w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ids, offsets)`` (see :func:`bin_tiles`) from the per-Gaussian tile rectangles and depth
    keys ``info`` (int32 ``[5, N]``, as ``_prepare_kernel`` writes it): ``torch.cumsum`` of the
    counts, the read-back of the pair count (the one host synchronisation), ``_keys_kernel``,
    one stable sort, ``_ranges_kernel``."""
    dev, n = info.device, info.shape[1]
    offsets = torch.empty(n_tiles + 1, dtype=torch.int32, device=dev)
    total = 0
    if n:
        ends = torch.cumsum(info[0], 0)  # int64
        total = int(ends[-1])  # the host synchronisation
    if total > MAX_PAIRS:
        raise ValueError(f"{total} (tile, Gaussian) pairs: more than int32 offsets hold")
    if total == 0:
        return torch.zeros(1, dtype=torch.int32, device=dev), offsets.zero_()
    keys = torch.empty(total, dtype=torch.int64, device=dev)
    gid = torch.empty(total, dtype=torch.int32, device=dev)
    _keys_kernel[(triton.cdiv(n, BLOCK_N),)](info, ends, keys, gid, n, tiles_w, BLOCK_N=BLOCK_N)
    keys, perm = torch.sort(keys, stable=True)  # by tile, then depth; pairs were written in index order
    ids = torch.empty(total, dtype=torch.int32, device=dev)
    _ranges_kernel[(triton.cdiv(total, BLOCK_P),)](keys, perm, gid, ids, offsets, total, n_tiles, BLOCK_P=BLOCK_P)
    return ids, offsets


def bin_tiles_reference(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width: int, height: int):
    """The binning in torch ops (the tests' reference and the benchmark's baseline for
    :func:`bin_tiles`): ``(ids, offsets)``. Each Gaussian's tile rectangle expands into (tile,
    Gaussian) pairs keyed ``tile * N + depth rank`` (ranks from a stable argsort), one sort, and
    ``searchsorted`` for the tiles' ranges: about 60 torch calls and one host synchronisation."""
    dev, n = means2d.device, means2d.shape[0]
    tiles_w, tiles_h = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    n_tiles = tiles_w * tiles_h
    rect = tile_rects(means2d, radii.to(dev), width, height)
    nx, ny = rect[:, 1] - rect[:, 0], rect[:, 3] - rect[:, 2]
    counts = (nx * ny).clamp_min(0)
    total = int(counts.sum())
    gid = torch.repeat_interleave(torch.arange(n, device=dev), counts, output_size=total)
    local = torch.arange(total, device=dev) - (torch.cumsum(counts, 0) - counts)[gid]
    nxg = nx[gid]
    tile = (rect[gid, 2] + local // nxg) * tiles_w + rect[gid, 0] + local % nxg
    rank = torch.empty(n, dtype=torch.long, device=dev)
    rank[torch.argsort(depths.to(dev), stable=True)] = torch.arange(n, device=dev)
    keys, perm = torch.sort(tile * max(n, 1) + rank[gid])
    ids = gid[perm].to(torch.int32)
    offsets = torch.searchsorted(keys // max(n, 1), torch.arange(n_tiles + 1, device=dev)).to(torch.int32)
    return ids, offsets


def render_tiles(params: torch.Tensor, feats: torch.Tensor, ids: torch.Tensor, offsets: torch.Tensor, tiles_w: int,
                 n_tiles: int, width: int, height: int, dtype: torch.dtype):
    """The compositing kernel on binned rows: ``out [H, W, 7]`` and ``alpha [H, W, 1]`` in ``dtype``,
    and the float32 final transmittance ``[H * W]`` the backward reads (one launch)."""
    dev = params.device
    out = torch.empty(height, width, N_FEATURES, dtype=dtype, device=dev)
    alpha = torch.empty(height, width, 1, dtype=dtype, device=dev)
    t_final = torch.empty(height * width, dtype=torch.float32, device=dev)
    if n_tiles:
        _forward_kernel[(n_tiles,)](params, feats, ids, offsets, out, alpha, t_final, width, height, tiles_w,
                                    BLOCK_G=BLOCK_G, FP=FP, num_warps=NUM_WARPS)
    return out, alpha, t_final


def tile_grads(saved, geometry, g_rgb, g_depth, g_normal, g_alpha, grad: torch.Tensor | None = None) -> torch.Tensor:
    """Per-Gaussian gradient rows ``[N, 16]`` (mean, conic, opacity, the 7 features) of the
    compositing from the cotangents of ``rgb``, ``depth``, ``normal`` and ``alpha`` (any may be
    None: zero), added into ``grad`` (float32, zero, or a zero fill here) by the backward kernel;
    returned in the dtype of the image. ``saved`` is ``(params, feats, ids, offsets, out, t_final)``,
    ``geometry`` ``(tiles_w, n_tiles, width, height)``."""
    params, feats, ids, offsets, out, t_final = saved
    tiles_w, n_tiles, width, height = geometry
    if grad is None:
        grad = torch.zeros(params.shape[0], GROW, dtype=torch.float32, device=params.device)
    cots = (g_rgb, g_depth, g_normal, g_alpha)
    if n_tiles and any(g is not None for g in cots):
        ptrs = [out if g is None else g for g in cots]
        strides = [(0, 0, 0) if g is None else g.stride() for g in cots]
        _backward_kernel[(n_tiles,)](params, feats, ids, offsets, out, t_final, *ptrs, grad, width, height, tiles_w,
                                     *strides[0], *strides[1][:2], *strides[2], *strides[3][:2],
                                     HAS_RGB=g_rgb is not None, HAS_DEPTH=g_depth is not None,
                                     HAS_NORMAL=g_normal is not None, HAS_ALPHA=g_alpha is not None,
                                     BLOCK_G=BLOCK_G, FP=FP, num_warps=NUM_WARPS)
    if out.dtype != torch.float32:
        grad = grad.to(out.dtype)
    return grad


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, radii, depths, width, height):
        params, feats, ids, offsets, tiles_w, n_tiles = bin_tiles(means2d, conics, opacities, features, radii, depths,
                                                                  width, height)
        out, alpha, t_final = render_tiles(params, feats, ids, offsets, tiles_w, n_tiles, width, height,
                                           means2d.dtype)
        # save_for_backward: ``out`` is an output (kept without a reference cycle through the graph)
        ctx.save_for_backward(params, feats, ids, offsets, out, t_final)
        ctx.grid = (tiles_w, n_tiles, width, height)
        return out, alpha

    @staticmethod
    def backward(ctx, g_feat, g_alpha):
        grad = tile_grads(ctx.saved_tensors, ctx.grid, g_feat[..., 0:3], g_feat[..., 3:4], g_feat[..., 4:7], g_alpha)
        return grad[:, 0:2], grad[:, 2:5], grad[:, 5], grad[:, 6:6 + N_FEATURES], None, None, None, None


def composite(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
              radii: torch.Tensor, depths: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite to ``features [H, W, 7]`` and ``alpha [H, W, 1]`` on the tensors' device (the arguments and
    their shapes are those of :func:`lmgs.render._cpu.composite`; float32 kernels, the outputs and gradients
    come back in the dtype of ``means2d``)."""
    return _Composite.apply(means2d, conics, opacities, features, radii, depths, int(width), int(height))


# ---- The EWA projection in Triton, fused with the compositor's packing ----
#
# Two ``torch.autograd.Function`` classes with hand-written backwards, chained as on the numba
# path (:mod:`lmgs.render._cpu`):
#
# * :class:`_Project`: one kernel launch forward (``_project_kernel``, a lane per Gaussian) that
#   computes what :func:`lmgs.render._numba_projection.project_forward` does, in float64 (the
#   inputs read in their dtype and widened, as numba reads them): ``means2d [N, 2]`` and
#   ``props [N, 11]`` (conic, opacity, rgb, camera z, normal) in the dtype of ``means``, the
#   int32 radii, and what :func:`bin_tiles` would pack from them: the compositor's float32
#   rows and features, each Gaussian's tile rectangle and depth key (the work of
#   ``_prepare_kernel``, here from the float64 mean like the numba rectangles), and a zeroed
#   gradient buffer for the compositor's backward. Its backward is one launch
#   (``_project_grad_kernel``), the port of
#   :func:`lmgs.render._numba_projection.project_backward` (the forward recomputed, the chain
#   rule branch for branch, float64), reading the cotangents of ``means2d`` and ``props``
#   through their strides and writing each parameter's gradient in its dtype.
# * :class:`_CompositePacked`: binning (:func:`bin_info`) and the compositing kernels on
#   those packed rows; differentiable in ``(means2d, props)``, whose
#   values the rows hold. ``rgb``, ``depth`` and ``normal`` come back as views of one
#   ``[H, W, 7]`` image and their cotangents go to the backward kernel as they are (one left
#   unused is not read), so no cotangent is sliced, joined or zero-filled.
#
# ``means2d`` stays a node of the graph between the two (``retain_grad()`` on it gives the 2D
# positional gradient), as on the numba path. Plain ``[N, 3]`` colours are read by the
# projection kernel; SH colours are evaluated first by the caller (``view_colors``, torch).
#
# The float64 arithmetic follows numba's expression for expression; the compiled kernels may
# fuse a multiply and an add (``fma``), which numba does not, so float64 results can differ in
# their last bits (float32 outputs and the integer radii practically never). The depth key is
# the float32 depth's bits for float32 parameters (numba sorts the float64 depths: Gaussians
# whose depths round to the same float32 keep index order here), the rank of the depth in a
# stable sort for other dtypes.

NPROP = 11  # props columns: conic (3), opacity, rgb, camera z, normal (3)
PROJ_BLOCK = 128  # Gaussians per program of the projection kernels
PROJ_NUM_WARPS = 4

_NEAR = tl.constexpr(NEAR_PLANE)
_EPS2D = tl.constexpr(EPS2D)
_LS_MIN = tl.constexpr(LOG_SCALE_MIN)
_LS_MAX = tl.constexpr(LOG_SCALE_MAX)
_NPROP = tl.constexpr(NPROP)
_PARAMS = tl.constexpr(PARAMS)
_FPC = tl.constexpr(FP)
# Float literals below meet float64 operands in arithmetic or comparisons, where Triton makes
# them float64 constants exactly; where they would be a value of their own (``tl.where``,
# ``tl.maximum``) they are exact in float32 too, or added to a float64 zero first.


@triton.jit
def _ld(ptr, i, m, STRIDE: tl.constexpr, C: tl.constexpr):
    """Column ``C`` of rows ``i`` of a contiguous ``[N, STRIDE]`` tensor, widened to float64."""
    return tl.load(ptr + i * STRIDE + C, mask=m, other=0.0).to(tl.float64)


@triton.jit
def _w2c(w2c_ptr):
    """The first three rows of the contiguous ``[4, 4]`` world-to-camera matrix, float64."""
    w00 = tl.load(w2c_ptr + 0).to(tl.float64)
    w01 = tl.load(w2c_ptr + 1).to(tl.float64)
    w02 = tl.load(w2c_ptr + 2).to(tl.float64)
    w03 = tl.load(w2c_ptr + 3).to(tl.float64)
    w10 = tl.load(w2c_ptr + 4).to(tl.float64)
    w11 = tl.load(w2c_ptr + 5).to(tl.float64)
    w12 = tl.load(w2c_ptr + 6).to(tl.float64)
    w13 = tl.load(w2c_ptr + 7).to(tl.float64)
    w20 = tl.load(w2c_ptr + 8).to(tl.float64)
    w21 = tl.load(w2c_ptr + 9).to(tl.float64)
    w22 = tl.load(w2c_ptr + 10).to(tl.float64)
    w23 = tl.load(w2c_ptr + 11).to(tl.float64)
    return w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23


@triton.jit
def _geometry(means_ptr, quats_ptr, ls_ptr, i, m, w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23, fx, fy,
              lxp, lxn, lyp, lyn):
    """The forward quantities of Gaussians ``i`` that both kernels need (numba's ``_axes``,
    ``_centre``, ``_jacobian``, ``_conic_rows`` and ``_normal``), as one flat tuple:

    ``ok_q, qn, qw, qx, qy, qz`` (the unit quaternion; the identity where ``qn <= 1e-12``),
    ``k`` (the argmin of the clamped log-scales), ``s0, s1, s2``, ``c00 .. c22`` (``W R``),
    ``x, y, z_raw, in_front, z``, ``ux, uy, cux, cuy, tx, ty, z2, j00, j02, j11, j12``,
    ``rs00 .. rs22``, ``m00 .. m12``, ``a, b, c, det``, ``sgn`` (the normal's flip) and the
    camera-space normal ``nx, ny, nz`` (flipped by ``sgn``).
    ``lxp .. lyn`` are the field-of-view limits as float64 blocks.
    """
    qw0 = _ld(quats_ptr, i, m, 4, 0)
    qx0 = _ld(quats_ptr, i, m, 4, 1)
    qy0 = _ld(quats_ptr, i, m, 4, 2)
    qz0 = _ld(quats_ptr, i, m, 4, 3)
    qn = tl.sqrt(qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0)
    ok_q = qn > 1e-12
    qs = tl.where(ok_q, qn, 1.0)
    qw = tl.where(ok_q, qw0 / qs, 1.0)
    qx = tl.where(ok_q, qx0 / qs, 0.0)
    qy = tl.where(ok_q, qy0 / qs, 0.0)
    qz = tl.where(ok_q, qz0 / qs, 0.0)
    r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    r01 = 2.0 * (qx * qy - qw * qz)
    r02 = 2.0 * (qx * qz + qw * qy)
    r10 = 2.0 * (qx * qy + qw * qz)
    r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    r12 = 2.0 * (qy * qz - qw * qx)
    r20 = 2.0 * (qx * qz - qw * qy)
    r21 = 2.0 * (qy * qz + qw * qx)
    r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    l0 = tl.minimum(tl.maximum(_ld(ls_ptr, i, m, 3, 0), _LS_MIN), _LS_MAX)
    l1 = tl.minimum(tl.maximum(_ld(ls_ptr, i, m, 3, 1), _LS_MIN), _LS_MAX)
    l2 = tl.minimum(tl.maximum(_ld(ls_ptr, i, m, 3, 2), _LS_MIN), _LS_MAX)
    k = tl.where(l1 < l0, 1, 0)
    k = tl.where(l2 < tl.minimum(l0, l1), 2, k)
    s0 = tl.exp(l0)
    s1 = tl.exp(l1)
    s2 = tl.exp(l2)
    c00 = w00 * r00 + w01 * r10 + w02 * r20
    c01 = w00 * r01 + w01 * r11 + w02 * r21
    c02 = w00 * r02 + w01 * r12 + w02 * r22
    c10 = w10 * r00 + w11 * r10 + w12 * r20
    c11 = w10 * r01 + w11 * r11 + w12 * r21
    c12 = w10 * r02 + w11 * r12 + w12 * r22
    c20 = w20 * r00 + w21 * r10 + w22 * r20
    c21 = w20 * r01 + w21 * r11 + w22 * r21
    c22 = w20 * r02 + w21 * r12 + w22 * r22
    # the camera-space mean; z is 1 behind the near plane
    px = _ld(means_ptr, i, m, 3, 0)
    py = _ld(means_ptr, i, m, 3, 1)
    pz = _ld(means_ptr, i, m, 3, 2)
    x = w00 * px + w01 * py + w02 * pz + w03
    y = w10 * px + w11 * py + w12 * pz + w13
    z_raw = w20 * px + w21 * py + w22 * pz + w23
    in_front = z_raw >= _NEAR
    z = tl.where(in_front, z_raw, 1.0)
    # the EWA Jacobian at the mean, its direction clamped to the widened field of view
    ux = x / z
    uy = y / z
    cux = tl.minimum(tl.maximum(ux, -lxn), lxp)
    cuy = tl.minimum(tl.maximum(uy, -lyn), lyp)
    tx = z * cux
    ty = z * cuy
    z2 = z * z
    j00 = fx / z
    j02 = -fx * tx / z2
    j11 = fy / z
    j12 = -fy * ty / z2
    # m = J (W R S), the 2D covariance m m^T + eps I
    rs00 = c00 * s0
    rs01 = c01 * s1
    rs02 = c02 * s2
    rs10 = c10 * s0
    rs11 = c11 * s1
    rs12 = c12 * s2
    rs20 = c20 * s0
    rs21 = c21 * s1
    rs22 = c22 * s2
    m00 = j00 * rs00 + j02 * rs20
    m01 = j00 * rs01 + j02 * rs21
    m02 = j00 * rs02 + j02 * rs22
    m10 = j11 * rs10 + j12 * rs20
    m11 = j11 * rs11 + j12 * rs21
    m12 = j11 * rs12 + j12 * rs22
    a = m00 * m00 + m01 * m01 + m02 * m02 + _EPS2D
    b = m00 * m10 + m01 * m11 + m02 * m12
    c = m10 * m10 + m11 * m11 + m12 * m12 + _EPS2D
    det = a * c - b * b
    # the normal: the axis of the smallest scale, flipped to face the camera (at the origin)
    nx = tl.where(k == 0, c00, tl.where(k == 1, c01, c02))
    ny = tl.where(k == 0, c10, tl.where(k == 1, c11, c12))
    nz = tl.where(k == 0, c20, tl.where(k == 1, c21, c22))
    sgn = tl.where(nx * x + ny * y + nz * z_raw > 0, -1.0, 1.0)
    return (ok_q, qn, qw, qx, qy, qz, k, s0, s1, s2, c00, c01, c02, c10, c11, c12, c20, c21, c22,
            x, y, z_raw, in_front, z, ux, uy, cux, cuy, tx, ty, z2, j00, j02, j11, j12,
            rs00, rs01, rs02, rs10, rs11, rs12, rs20, rs21, rs22, m00, m01, m02, m10, m11, m12, a, b, c, det, sgn,
            sgn * nx, sgn * ny, sgn * nz)


@triton.jit
def _project_kernel(means_ptr, quats_ptr, ls_ptr, logit_ptr, rgb_ptr, w2c_ptr, m2_ptr, props_ptr, radii_ptr,
                    params_ptr, feats_ptr, info_ptr, grad_ptr, n, fx: tl.float64, fy: tl.float64, cx: tl.float64,
                    cy: tl.float64, lim_xp: tl.float64, lim_xn: tl.float64, lim_yp: tl.float64, lim_yn: tl.float64,
                    width, height, tiles_w, tiles_h, DEPTH_BITS: tl.constexpr, ZERO_GRAD: tl.constexpr,
                    BLOCK: tl.constexpr):
    """Project Gaussians ``i`` (numba's ``project_forward``) and pack them for the compositor.

    Writes ``means2d [N, 2]`` and ``props [N, 11]`` (in their dtype), ``radii [N]`` int32
    (0: culled: behind the near plane, a non-positive determinant, or a square off the
    image), the float32 compositing rows ``params [N, 8]`` and ``feats [N, 16]`` and ``info
    [5, N]`` as ``_prepare_kernel`` writes them (the depth key only with ``DEPTH_BITS``), and
    with ``ZERO_GRAD`` zeros into ``grad [N, 16]``.
    """
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < n
    z64 = tl.zeros([BLOCK], tl.float64)
    w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23 = _w2c(w2c_ptr)
    (ok_q, qn, qw, qx, qy, qz, k, s0, s1, s2, c00, c01, c02, c10, c11, c12, c20, c21, c22,
     x, y, z_raw, in_front, z, ux, uy, cux, cuy, tx, ty, z2, j00, j02, j11, j12,
     rs00, rs01, rs02, rs10, rs11, rs12, rs20, rs21, rs22, m00, m01, m02, m10, m11, m12, a, b, c, det,
     sgn, nx, ny, nz) = _geometry(means_ptr, quats_ptr, ls_ptr, i, m, w00, w01, w02, w03, w10, w11, w12, w13,
                                  w20, w21, w22, w23, fx, fy, z64 + lim_xp, z64 + lim_xn, z64 + lim_yp, z64 + lim_yn)
    ok = in_front & (det > 0)
    det_s = tl.where(ok, det, 1.0)
    mx = fx * x / z + cx
    my = fy * y / z + cy
    mid = 0.5 * (a + c)
    spread = mid * mid - det
    lam = mid + tl.sqrt(tl.where(spread < 0.1, z64 + 0.1, spread))
    radius = tl.ceil(3.0 * tl.sqrt(lam))
    on_img = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
    vis = ok & on_img & (radius > 0)
    r = tl.where(vis, radius, 0.0).to(tl.int32)
    ca = c / det_s
    cb = -b / det_s
    cc = a / det_s
    op = 1.0 / (1.0 + tl.exp(-_ld(logit_ptr, i, m, 1, 0)))
    red = _ld(rgb_ptr, i, m, 3, 0)
    green = _ld(rgb_ptr, i, m, 3, 1)
    blue = _ld(rgb_ptr, i, m, 3, 2)

    tl.store(m2_ptr + 2 * i, mx, mask=m)
    tl.store(m2_ptr + 2 * i + 1, my, mask=m)
    tl.store(radii_ptr + i, r, mask=m)
    prow = props_ptr + i * _NPROP
    tl.store(prow + 0, ca, mask=m)
    tl.store(prow + 1, cb, mask=m)
    tl.store(prow + 2, cc, mask=m)
    tl.store(prow + 3, op, mask=m)
    tl.store(prow + 4, red, mask=m)
    tl.store(prow + 5, green, mask=m)
    tl.store(prow + 6, blue, mask=m)
    tl.store(prow + 7, z, mask=m)
    tl.store(prow + 8, nx, mask=m)
    tl.store(prow + 9, ny, mask=m)
    tl.store(prow + 10, nz, mask=m)
    # the compositor's float32 row (mean, conic, opacity, two zero pads) and features (7, zero-padded)
    row = params_ptr + i * _PARAMS
    tl.store(row + 0, mx.to(tl.float32), mask=m)
    tl.store(row + 1, my.to(tl.float32), mask=m)
    tl.store(row + 2, ca.to(tl.float32), mask=m)
    tl.store(row + 3, cb.to(tl.float32), mask=m)
    tl.store(row + 4, cc.to(tl.float32), mask=m)
    tl.store(row + 5, op.to(tl.float32), mask=m)
    tl.store(row + 6, tl.zeros([BLOCK], tl.float32), mask=m)
    tl.store(row + 7, tl.zeros([BLOCK], tl.float32), mask=m)
    frow = feats_ptr + i * _FPC
    tl.store(frow + 0, red.to(tl.float32), mask=m)
    tl.store(frow + 1, green.to(tl.float32), mask=m)
    tl.store(frow + 2, blue.to(tl.float32), mask=m)
    tl.store(frow + 3, z.to(tl.float32), mask=m)
    tl.store(frow + 4, nx.to(tl.float32), mask=m)
    tl.store(frow + 5, ny.to(tl.float32), mask=m)
    tl.store(frow + 6, nz.to(tl.float32), mask=m)
    cols = tl.arange(0, _FPC)
    tl.store(feats_ptr + i[:, None] * _FPC + cols[None, :], tl.zeros([BLOCK, _FPC], tl.float32),
             mask=m[:, None] & (cols[None, :] >= _NF))
    if DEPTH_BITS:
        dkey = depth_key(z.to(tl.float32))
    else:
        dkey = r
    store_tile_info(info_ptr, i, m, n, mx, my, r, dkey, tiles_w, tiles_h, DEPTH_BITS)
    if ZERO_GRAD:
        gcols = tl.arange(0, _GROW)
        tl.store(grad_ptr + i[:, None] * _GROW + gcols[None, :], tl.zeros([BLOCK, _GROW], tl.float32),
                 mask=m[:, None])


@triton.jit
def _project_grad_kernel(means_ptr, quats_ptr, ls_ptr, logit_ptr, w2c_ptr, gm2_ptr, gm2_s0, gm2_s1, gp_ptr, gp_s0,
                         gp_s1, g_means_ptr, g_quats_ptr, g_ls_ptr, g_logit_ptr, g_rgb_ptr, n, fx: tl.float64,
                         fy: tl.float64, lim_xp: tl.float64, lim_xn: tl.float64, lim_yp: tl.float64,
                         lim_yn: tl.float64, BLOCK: tl.constexpr):
    """The gradients of the projection (numba's ``project_backward``) from those of ``means2d``
    and ``props`` (read through their strides, in their dtype): ``g_means [N, 3]``,
    ``g_quats [N, 4]``, ``g_log_scales [N, 3]``, ``g_logits [N]``, ``g_rgb [N, 3]``, every
    element written (in each one's dtype)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = i < n
    z64 = tl.zeros([BLOCK], tl.float64)
    lxp, lxn, lyp, lyn = z64 + lim_xp, z64 + lim_xn, z64 + lim_yp, z64 + lim_yn
    w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23 = _w2c(w2c_ptr)
    (ok_q, qn, qw, qx, qy, qz, k, s0, s1, s2, c00, c01, c02, c10, c11, c12, c20, c21, c22,
     x, y, z_raw, in_front, z, ux, uy, cux, cuy, tx, ty, z2, j00, j02, j11, j12,
     rs00, rs01, rs02, rs10, rs11, rs12, rs20, rs21, rs22, m00, m01, m02, m10, m11, m12, a, b, c, det,
     sgn, nx, ny, nz) = _geometry(means_ptr, quats_ptr, ls_ptr, i, m, w00, w01, w02, w03, w10, w11, w12, w13,
                                  w20, w21, w22, w23, fx, fy, lxp, lxn, lyp, lyn)
    ok = in_front & (det > 0)
    lr0 = _ld(ls_ptr, i, m, 3, 0)
    lr1 = _ld(ls_ptr, i, m, 3, 1)
    lr2 = _ld(ls_ptr, i, m, 3, 2)
    gmx = tl.load(gm2_ptr + i * gm2_s0, mask=m, other=0.0).to(tl.float64)
    gmy = tl.load(gm2_ptr + i * gm2_s0 + gm2_s1, mask=m, other=0.0).to(tl.float64)
    gp = gp_ptr + i * gp_s0
    gc0 = tl.load(gp, mask=m, other=0.0).to(tl.float64)
    gc1 = tl.load(gp + gp_s1, mask=m, other=0.0).to(tl.float64)
    gc2 = tl.load(gp + 2 * gp_s1, mask=m, other=0.0).to(tl.float64)
    gop = tl.load(gp + 3 * gp_s1, mask=m, other=0.0).to(tl.float64)
    tl.store(g_rgb_ptr + 3 * i, tl.load(gp + 4 * gp_s1, mask=m, other=0.0), mask=m)
    tl.store(g_rgb_ptr + 3 * i + 1, tl.load(gp + 5 * gp_s1, mask=m, other=0.0), mask=m)
    tl.store(g_rgb_ptr + 3 * i + 2, tl.load(gp + 6 * gp_s1, mask=m, other=0.0), mask=m)
    gzf = tl.load(gp + 7 * gp_s1, mask=m, other=0.0).to(tl.float64)
    gn0 = sgn * tl.load(gp + 8 * gp_s1, mask=m, other=0.0).to(tl.float64)
    gn1 = sgn * tl.load(gp + 9 * gp_s1, mask=m, other=0.0).to(tl.float64)
    gn2 = sgn * tl.load(gp + 10 * gp_s1, mask=m, other=0.0).to(tl.float64)
    op = 1.0 / (1.0 + tl.exp(-_ld(logit_ptr, i, m, 1, 0)))
    tl.store(g_logit_ptr + i, gop * op * (1.0 - op), mask=m)
    # means2d = (fx x / z + cx, fy y / z + cy); the feature z
    gx = gmx * fx / z
    gy = gmy * fy / z
    gz = gzf - gmx * fx * x / z2 - gmy * fy * y / z2
    # conic = (c, -b, a) / det_s (det_s = 1 where culled: the conic is then (c, -b, a) itself)
    inv = 1.0 / tl.where(ok, det, 1.0)
    gdet = -(gc0 * c - gc1 * b + gc2 * a) * inv * inv
    ga = tl.where(ok, gc2 * inv + gdet * c, gc2)
    gb = tl.where(ok, -gc1 * inv - 2.0 * gdet * b, -gc1)
    gcc = tl.where(ok, gc0 * inv + gdet * a, gc0)
    # a, b, c = m0.m0 + eps, m0.m1, m1.m1 + eps
    gm00 = 2.0 * ga * m00 + gb * m10
    gm01 = 2.0 * ga * m01 + gb * m11
    gm02 = 2.0 * ga * m02 + gb * m12
    gm10 = 2.0 * gcc * m10 + gb * m00
    gm11 = 2.0 * gcc * m11 + gb * m01
    gm12 = 2.0 * gcc * m12 + gb * m02
    # m = J (rot_c S)
    gj00 = gm00 * rs00 + gm01 * rs01 + gm02 * rs02
    gj02 = gm00 * rs20 + gm01 * rs21 + gm02 * rs22
    gj11 = gm10 * rs10 + gm11 * rs11 + gm12 * rs12
    gj12 = gm10 * rs20 + gm11 * rs21 + gm12 * rs22
    grs00 = gm00 * j00
    grs01 = gm01 * j00
    grs02 = gm02 * j00
    grs10 = gm10 * j11
    grs11 = gm11 * j11
    grs12 = gm12 * j11
    grs20 = gm00 * j02 + gm10 * j12
    grs21 = gm01 * j02 + gm11 * j12
    grs22 = gm02 * j02 + gm12 * j12
    gs0 = grs00 * c00 + grs10 * c10 + grs20 * c20
    gs1 = grs01 * c01 + grs11 * c11 + grs21 * c21
    gs2 = grs02 * c02 + grs12 * c12 + grs22 * c22
    tl.store(g_ls_ptr + 3 * i, tl.where((lr0 >= _LS_MIN) & (lr0 <= _LS_MAX), gs0 * s0, 0.0), mask=m)
    tl.store(g_ls_ptr + 3 * i + 1, tl.where((lr1 >= _LS_MIN) & (lr1 <= _LS_MAX), gs1 * s1, 0.0), mask=m)
    tl.store(g_ls_ptr + 3 * i + 2, tl.where((lr2 >= _LS_MIN) & (lr2 <= _LS_MAX), gs2 * s2, 0.0), mask=m)
    # rot_c = W R: its gradient, plus the normal's (column k of rot_c, flipped by sgn)
    gc00 = grs00 * s0 + tl.where(k == 0, gn0, 0.0)
    gc10 = grs10 * s0 + tl.where(k == 0, gn1, 0.0)
    gc20 = grs20 * s0 + tl.where(k == 0, gn2, 0.0)
    gc01 = grs01 * s1 + tl.where(k == 1, gn0, 0.0)
    gc11 = grs11 * s1 + tl.where(k == 1, gn1, 0.0)
    gc21 = grs21 * s1 + tl.where(k == 1, gn2, 0.0)
    gc02 = grs02 * s2 + tl.where(k == 2, gn0, 0.0)
    gc12 = grs12 * s2 + tl.where(k == 2, gn1, 0.0)
    gc22 = grs22 * s2 + tl.where(k == 2, gn2, 0.0)
    # J: j00 = fx / z, j02 = -fx tx / z^2 (and y)
    gz += -gj00 * fx / z2 - gj11 * fy / z2
    gtx = -gj02 * fx / z2
    gty = -gj12 * fy / z2
    gz += 2.0 * (gj02 * fx * tx + gj12 * fy * ty) / (z2 * z)
    # tx = z clamp(x / z), ty likewise (the clamp passes the gradient on its closed range)
    gz += gtx * cux + gty * cuy
    gux = tl.where((ux >= -lxn) & (ux <= lxp), gtx * z, 0.0)
    guy = tl.where((uy >= -lyn) & (uy <= lyp), gty * z, 0.0)
    gx += gux / z
    gy += guy / z
    gz -= (gux * x + guy * y) / z2
    gzr = tl.where(in_front, gz, 0.0)
    # camera-space mean = W p + t
    tl.store(g_means_ptr + 3 * i, w00 * gx + w10 * gy + w20 * gzr, mask=m)
    tl.store(g_means_ptr + 3 * i + 1, w01 * gx + w11 * gy + w21 * gzr, mask=m)
    tl.store(g_means_ptr + 3 * i + 2, w02 * gx + w12 * gy + w22 * gzr, mask=m)
    # the gradient of R is W^T times that of rot_c
    g00 = w00 * gc00 + w10 * gc10 + w20 * gc20
    g01 = w00 * gc01 + w10 * gc11 + w20 * gc21
    g02 = w00 * gc02 + w10 * gc12 + w20 * gc22
    g10 = w01 * gc00 + w11 * gc10 + w21 * gc20
    g11 = w01 * gc01 + w11 * gc11 + w21 * gc21
    g12 = w01 * gc02 + w11 * gc12 + w21 * gc22
    g20 = w02 * gc00 + w12 * gc10 + w22 * gc20
    g21 = w02 * gc01 + w12 * gc11 + w22 * gc21
    g22 = w02 * gc02 + w12 * gc12 + w22 * gc22
    # R of the unit quaternion
    gw = 2.0 * (-qz * g01 + qy * g02 + qz * g10 - qx * g12 - qy * g20 + qx * g21)
    gxq = 2.0 * (-2.0 * qx * (g11 + g22) + qy * (g01 + g10) + qz * (g02 + g20) + qw * (g21 - g12))
    gyq = 2.0 * (-2.0 * qy * (g00 + g22) + qx * (g01 + g10) + qz * (g12 + g21) + qw * (g02 - g20))
    gzq = 2.0 * (-2.0 * qz * (g00 + g11) + qx * (g02 + g20) + qy * (g12 + g21) + qw * (g10 - g01))
    # normalisation q / |q| (a zero-norm quaternion is the identity: no gradient)
    dot = qw * gw + qx * gxq + qy * gyq + qz * gzq
    qs = tl.where(ok_q, qn, 1.0)
    tl.store(g_quats_ptr + 4 * i, tl.where(ok_q, (gw - qw * dot) / qs, 0.0), mask=m)
    tl.store(g_quats_ptr + 4 * i + 1, tl.where(ok_q, (gxq - qx * dot) / qs, 0.0), mask=m)
    tl.store(g_quats_ptr + 4 * i + 2, tl.where(ok_q, (gyq - qy * dot) / qs, 0.0), mask=m)
    tl.store(g_quats_ptr + 4 * i + 3, tl.where(ok_q, (gzq - qz * dot) / qs, 0.0), mask=m)


def camera_args(camera: Camera) -> tuple[float, ...]:
    """``fx, fy, cx, cy`` and the limits ``lim_xp, lim_xn, lim_yp, lim_yn`` of ``x / z`` and
    ``y / z`` (the field of view plus 30 % of its half-width), as numba's ``_view`` computes them."""
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    width, height = int(camera.width), int(camera.height)
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (fx, fy, cx, cy, (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x, (height - cy) / fy + 0.3 * tan_y,
            cy / fy + 0.3 * tan_y)


@dataclass
class Packed:
    """What the projection kernel leaves for the compositor (not in the autograd graph)."""

    params: torch.Tensor  # [N, 8] float32 compositing rows
    feats: torch.Tensor  # [N, 16] float32 features, zero-padded
    info: torch.Tensor  # [5, N] int32 tile rectangles and depth keys
    radii: torch.Tensor  # [N] int32, 0 = culled
    grad: torch.Tensor | None  # [N, 16] float32 zeros for the compositor's backward (None without a gradient)


def _w2c_on(camera: Camera, dev: torch.device) -> torch.Tensor:
    return camera.world_to_camera.detach().to(dev).contiguous()


class _Project(torch.autograd.Function):
    """The Triton projection; ``box`` (a list) receives the :class:`Packed` rows."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, rgb, camera, box, want_grad):
        n, dev, dtype = means.shape[0], means.device, means.dtype
        width, height = int(camera.width), int(camera.height)
        tiles_w, tiles_h, _ = tile_grid(width, height)
        m2 = torch.empty(n, 2, dtype=dtype, device=dev)
        props = torch.empty(n, NPROP, dtype=dtype, device=dev)
        radii = torch.empty(n, dtype=torch.int32, device=dev)
        params = torch.empty(n, PARAMS, dtype=torch.float32, device=dev)
        feats = torch.empty(n, FP, dtype=torch.float32, device=dev)
        info = torch.empty(5, n, dtype=torch.int32, device=dev)
        grad = torch.empty(n, GROW, dtype=torch.float32, device=dev) if want_grad else None
        bits = dtype == torch.float32
        w2c = _w2c_on(camera, dev)
        if n:
            _project_kernel[(triton.cdiv(n, PROJ_BLOCK),)](
                means.contiguous(), quats.contiguous(), log_scales.contiguous(), opacity_logits.contiguous(),
                rgb.contiguous(), w2c, m2, props, radii, params, feats, info, params if grad is None else grad, n,
                *camera_args(camera), width, height, tiles_w, tiles_h, DEPTH_BITS=bits, ZERO_GRAD=grad is not None,
                BLOCK=PROJ_BLOCK, num_warps=PROJ_NUM_WARPS)
            if not bits:
                rank_depths(props[:, 7], info[4])
        box.append(Packed(params, feats, info, radii, grad))
        ctx.save_for_backward(means, quats, log_scales, opacity_logits)  # (autograd checks in-place changes)
        ctx.camera, ctx.w2c, ctx.rgb_dtype = camera, w2c, rgb.dtype
        return m2, props

    @staticmethod
    def backward(ctx, g_means2d, g_props):
        means, quats, log_scales, opacity_logits = ctx.saved_tensors
        n, dev = means.shape[0], means.device
        grads = (torch.empty(n, 3, dtype=means.dtype, device=dev), torch.empty(n, 4, dtype=quats.dtype, device=dev),
                 torch.empty(n, 3, dtype=log_scales.dtype, device=dev),
                 torch.empty(n, dtype=opacity_logits.dtype, device=dev),
                 torch.empty(n, 3, dtype=ctx.rgb_dtype, device=dev))
        if n:
            fx, fy, _, _, *lims = camera_args(ctx.camera)
            _project_grad_kernel[(triton.cdiv(n, PROJ_BLOCK),)](
                means.contiguous(), quats.contiguous(), log_scales.contiguous(), opacity_logits.contiguous(), ctx.w2c,
                g_means2d, *g_means2d.stride(), g_props, *g_props.stride(), *grads, n, fx, fy, *lims, BLOCK=PROJ_BLOCK,
                num_warps=PROJ_NUM_WARPS)
        return (*grads, None, None, None)


class _CompositePacked(torch.autograd.Function):
    """Binning and compositing of the rows the projection kernel packed; differentiable in
    ``means2d`` and ``props`` (whose values the rows hold). Returns ``rgb``, ``depth``,
    ``normal`` (views of one ``[H, W, 7]`` image) and ``alpha``."""

    @staticmethod
    def forward(ctx, means2d, props, packed, width, height):
        tiles_w, _, n_tiles = tile_grid(width, height)
        ids, offsets = bin_info(packed.info, n_tiles, tiles_w)
        out, alpha, t_final = render_tiles(packed.params, packed.feats, ids, offsets, tiles_w, n_tiles, width, height,
                                             means2d.dtype)
        ctx.save_for_backward(packed.params, packed.feats, ids, offsets, out, t_final)
        ctx.grid = (tiles_w, n_tiles, width, height)
        ctx.grad = packed.grad  # zeroed by the projection kernel, for the first backward
        ctx.set_materialize_grads(False)  # an image left out of the loss: its cotangent is not read
        return out[..., 0:3], out[..., 3:4], out[..., 4:7], alpha

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_normal, g_alpha):
        grad, ctx.grad = ctx.grad, None  # a later backward (retain_graph) zero-fills its own
        grad = tile_grads(ctx.saved_tensors, ctx.grid, g_rgb, g_depth, g_normal, g_alpha, grad)
        return grad[:, 0:2], grad[:, 2:2 + NPROP], None, None, None


def rasterize_triton(means, quats, log_scales, opacity_logits, colors, camera: Camera):
    """Projection and compositing in Triton: ``rgb [H, W, 3]``, ``depth [H, W, 1]``,
    ``normal [H, W, 3]``, ``alpha [H, W, 1]``, ``means2d [N, 2]``, ``radii [N]`` (the
    contract of :func:`lmgs.render._cpu.rasterize_numba`; ``colors`` are rgb ``[N, 3]``, SH
    already evaluated). The world-to-camera matrix gets no gradient."""
    width, height = int(camera.width), int(camera.height)
    params = (means, quats, log_scales, opacity_logits, colors)
    want_grad = torch.is_grad_enabled() and any(t.requires_grad for t in params)
    box: list[Packed] = []
    means2d, props = _Project.apply(*params, camera, box, want_grad)
    rgb, depth, normal, alpha = _CompositePacked.apply(means2d, props, box[0], width, height)
    return rgb, depth, normal, alpha, means2d, box[0].radii
