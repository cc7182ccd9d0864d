"""Tile compositing on CUDA in Triton: the GPU path when gsplat is not installed.

Same inputs and result as :func:`lmgs.render._cpu.composite` (the EWA projection is torch's
:func:`lmgs.render._projection.project`, already on the GPU), and the same definition of the
image: each 16x16 tile composites its Gaussians front to back,

.. math::
    \\alpha_i = \\min(0.99,\\ o_i e^{-\\sigma_i}),\\quad
    \\sigma_i = \\tfrac12 (a d_x^2 + c d_y^2) + b d_x d_y,\\quad d = \\mu'_i - p,

skipping :math:`\\sigma_i < 0` and :math:`\\alpha_i < 1/255`, and stopping before the first
Gaussian that would take the transmittance below :math:`10^{-4}`.

Binning is torch on the device: every (tile, Gaussian) pair of a Gaussian's tile rectangle
gets the key ``tile * N + depth rank``, one sort orders them by tile and then front to back
(ties in depth keep index order, as the CPU path), and ``searchsorted`` gives each tile's
range. One Triton program per tile holds its 256 pixels and walks its range in chunks of
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
BLOCK_G = 16  # Gaussians per chunk
NUM_WARPS = 8

_AMAX = tl.constexpr(ALPHA_MAX)
_AMIN = tl.constexpr(ALPHA_MIN)
_TMIN = tl.constexpr(T_MIN)
_TILE = tl.constexpr(TILE)
_PIX = tl.constexpr(TILE * TILE)
_NF = tl.constexpr(N_FEATURES)


@triton.jit
def _pixels(tile, tiles_w, width, height):
    """Pixel indices of a tile (row-major 16x16), whether each is inside the image, and centres."""
    ty = tile // tiles_w
    tx = tile - ty * tiles_w
    pix = tl.arange(0, _PIX)
    px = tx * _TILE + pix % _TILE
    py = ty * _TILE + pix // _TILE
    inside = (px < width) & (py < height)
    return py * width + px, inside, px.to(tl.float32) + 0.5, py.to(tl.float32) + 0.5


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
def _forward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, out_ptr, tfinal_ptr, width, height, tiles_w,
                    BLOCK_G: tl.constexpr, FP: tl.constexpr):
    tile = tl.program_id(0)
    lin, inside, fx, fy = _pixels(tile, tiles_w, width, height)
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
    tl.store(tfinal_ptr + lin, T, mask=inside)


@triton.jit
def _backward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, out_ptr, tfinal_ptr, gout_ptr, galpha_ptr,
                     gparams_ptr, gfeat_ptr, width, height, tiles_w, BLOCK_G: tl.constexpr, FP: tl.constexpr):
    tile = tl.program_id(0)
    lin, inside, fx, fy = _pixels(tile, tiles_w, width, height)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    cols = tl.arange(0, FP)
    pmask = inside[:, None] & (cols[None, :] < _NF)
    gvec = tl.load(gout_ptr + lin[:, None] * _NF + cols[None, :], mask=pmask, other=0.0)  # [PIX, FP]
    total = tl.sum(gvec * tl.load(out_ptr + lin[:, None] * _NF + cols[None, :], mask=pmask, other=0.0), axis=1)
    ga_t = tl.load(galpha_ptr + lin, mask=inside, other=0.0) * tl.load(tfinal_ptr + lin, mask=inside, other=1.0)
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
        grow = gparams_ptr + g * 8
        tl.atomic_add(grow + 0, tl.sum(d_sigma * (ca[None, :] * dx + cb[None, :] * dy), axis=0), mask=valid)
        tl.atomic_add(grow + 1, tl.sum(d_sigma * (cc[None, :] * dy + cb[None, :] * dx), axis=0), mask=valid)
        tl.atomic_add(grow + 2, tl.sum(d_sigma * 0.5 * dx * dx, axis=0), mask=valid)
        tl.atomic_add(grow + 3, tl.sum(d_sigma * dx * dy, axis=0), mask=valid)
        tl.atomic_add(grow + 4, tl.sum(d_sigma * 0.5 * dy * dy, axis=0), mask=valid)
        tl.atomic_add(grow + 5, tl.sum(d_raw * e, axis=0), mask=valid)
        d_f = tl.dot(tl.trans(w), gvec, input_precision="ieee")  # [BLOCK_G, FP]
        tl.atomic_add(gfeat_ptr + g[:, None] * FP + cols[None, :], d_f, mask=valid[:, None] & (cols[None, :] < _NF))
        T, done = _advance(T, done, al, P)
        k0 += BLOCK_G


def bin_tiles(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width: int, height: int):
    """Tile lists on the device: ``ids`` (int32 Gaussian indices, tile by tile, front to back)
    and ``offsets`` (int32 ``[n_tiles + 1]``: tile ``t`` holds ``ids[offsets[t]:offsets[t+1]]``)."""
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
    return ids, offsets, tiles_w, n_tiles


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, radii, depths, width, height):
        dev, dtype, n = means2d.device, means2d.dtype, means2d.shape[0]
        params = torch.zeros(n, PARAMS, dtype=torch.float32, device=dev)
        params[:, 0:2] = means2d.detach()
        params[:, 2:5] = conics.detach()
        params[:, 5] = opacities.detach()
        feats = torch.zeros(n, FP, dtype=torch.float32, device=dev)
        feats[:, :N_FEATURES] = features.detach()
        ids, offsets, tiles_w, n_tiles = bin_tiles(means2d.detach(), radii, depths, width, height)
        out = torch.empty(height * width, N_FEATURES, dtype=torch.float32, device=dev)
        t_final = torch.empty(height * width, dtype=torch.float32, device=dev)
        if n_tiles:
            _forward_kernel[(n_tiles,)](params, feats, ids, offsets, out, t_final, width, height, tiles_w,
                                        BLOCK_G=BLOCK_G, FP=FP, num_warps=NUM_WARPS)
        ctx.saved = (params, feats, ids, offsets, out, t_final, tiles_w, n_tiles, width, height)
        return (out.view(height, width, N_FEATURES).to(dtype), (1.0 - t_final).view(height, width, 1).to(dtype))

    @staticmethod
    def backward(ctx, g_feat, g_alpha):
        params, feats, ids, offsets, out, t_final, tiles_w, n_tiles, width, height = ctx.saved
        dtype = g_feat.dtype
        g_params = torch.zeros_like(params)
        g_feats = torch.zeros_like(feats)
        if n_tiles:
            _backward_kernel[(n_tiles,)](params, feats, ids, offsets, out, t_final,
                                         g_feat.to(torch.float32).contiguous(),
                                         g_alpha.to(torch.float32).contiguous(), g_params, g_feats, width, height,
                                         tiles_w, BLOCK_G=BLOCK_G, FP=FP, num_warps=NUM_WARPS)
        return (g_params[:, 0:2].to(dtype), g_params[:, 2:5].to(dtype), g_params[:, 5].to(dtype),
                g_feats[:, :N_FEATURES].to(dtype), None, None, None, None)


def composite(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
              radii: torch.Tensor, depths: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite to ``features [H, W, 7]`` and ``alpha [H, W, 1]`` on the tensors' device (the arguments and
    their shapes are those of :func:`lmgs.render._cpu.composite`; float32 kernels, the outputs and gradients
    come back in the dtype of ``means2d``)."""
    return _Composite.apply(means2d, conics, opacities, features, radii, depths, int(width), int(height))
