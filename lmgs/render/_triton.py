"""The GPU path when gsplat is not installed, in Triton: binning and tile compositing.

The ``"triton"`` backend of :func:`lmgs.render.rasterize` is
:func:`lmgs.render._triton_projection.rasterize_triton`: its projection kernels write the packed rows
this module's kernels bin and composite. :func:`composite` composites
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

import torch
import triton
import triton.language as tl

from lmgs.render._projection import ALPHA_MAX, ALPHA_MIN, N_FEATURES, T_MIN, TILE, tile_rects

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
