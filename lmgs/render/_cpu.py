"""The fast CPU compositor: numba kernels behind a ``torch.autograd.Function``.

Only the per-pixel part is hand-written; the projection stays in torch
(:mod:`lmgs.render._projection`), so its gradient comes from autograd and the
hand-written backward only covers ``(means2d, conics, opacities, features)``.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from lmgs.render import _numba_composite as C
from lmgs.render import _numba_kernels as K
from lmgs.render._projection import TILE, tile_rects


def _kernel_dtype(t: torch.Tensor) -> torch.dtype:
    """float32 inputs composite in float32 (twice the SIMD lanes), anything else in float64."""
    return torch.float32 if t.dtype == torch.float32 else torch.float64


def _np(t: torch.Tensor, dtype: torch.dtype = torch.float64) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=dtype).contiguous().numpy()


def _tile_order(n_tiles: int) -> np.ndarray:
    """Tiles per parallel chunk ``[P, ceil(n_tiles / P)]``, padded with -1.

    One chunk per numba thread, tiles interleaved (chunk ``r`` takes tiles ``r, r+P, ...``)
    so every thread gets a share of the busy centre of the image; each chunk allocates
    its per-pixel scratch once.
    """
    p = max(1, numba.get_num_threads())
    m = (n_tiles + p - 1) // p
    order = np.full(p * m, -1, dtype=np.int64)
    order[:n_tiles] = np.arange(n_tiles, dtype=np.int64)
    return order.reshape(m, p).T.copy()


def _composite_rows(rows: np.ndarray, rects: np.ndarray, vis: np.ndarray, depths: np.ndarray, width: int, height: int,
                    nf: int = K.NF):
    """Sort the visible Gaussians front to back, bin them into tiles and composite their rows
    (the first ``nf`` features: 3 is colour alone) in the dtype of ``rows``.

    Returns ``out, t_final, last, (offsets, ids, tile_order, tiles_w, rows)``: ``rows`` as
    composited (float64 when a float32 stop index could not hold every intersection index).
    """
    tiles_w, tiles_h = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    n_tiles = tiles_w * tiles_h
    # stable sort by depth: ties keep index order, like the dense reference
    vis_ids = np.flatnonzero(vis)
    order = vis_ids[np.argsort(depths[vis_ids], kind="stable")].astype(np.int64)
    offsets, ids = K.bin_tiles(rects, order, n_tiles, tiles_w)
    tile_order = _tile_order(n_tiles)
    if rows.dtype == np.float32 and ids.shape[0] >= C.F32_MAX_ISECT:
        rows = rows.astype(np.float64)
    out, t_final, last = C.forward(rows, ids, offsets, tile_order, tiles_w, width, height, nf,
                                   C.consts(rows.dtype), C.pixel_centres(width, height, rows.dtype))
    return out, t_final, last, (offsets, ids, tile_order, tiles_w, rows)


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, radii, depths, width, height):
        n = means2d.shape[0]
        rects = tile_rects(means2d, radii, width, height).numpy()
        kd = _kernel_dtype(means2d)
        rows = K.gaussian_rows(_np(means2d, kd), _np(conics, kd), _np(opacities, kd), _np(features, kd))
        out, t_final, last, (offsets, ids, tile_order, tiles_w, rows) = _composite_rows(
            rows, rects, (radii > 0).numpy(), depths.detach().cpu().numpy(), width, height)
        ctx.saved = (rows, offsets, ids, tile_order, tiles_w, width, height, t_final, last, n)
        dtype, dev = means2d.dtype, means2d.device
        feat = torch.from_numpy(out).to(device=dev, dtype=dtype)
        alpha = torch.from_numpy(1.0 - t_final).to(device=dev, dtype=dtype)[..., None]
        return feat, alpha

    @staticmethod
    def backward(ctx, g_feat, g_alpha):
        rows, offsets, ids, tile_order, tiles_w, width, height, t_final, last, n = ctx.saved
        dtype, dev = g_feat.dtype, g_feat.device
        kd = torch.float32 if rows.dtype == np.float32 else torch.float64
        grad = C.backward(rows, ids, offsets, tile_order, tiles_w, width, height, t_final, last, _np(g_feat, kd),
                          _np(g_alpha, kd)[..., 0], C.consts(rows.dtype), C.pixel_centres(width, height, rows.dtype))
        per_g = torch.from_numpy(C.reduce_grads(grad, ids, n)).to(device=dev, dtype=dtype)
        return per_g[:, 0:2], per_g[:, 2:5], per_g[:, 5], per_g[:, 6:13], None, None, None, None


def composite(
    means2d: torch.Tensor,  # [N, 2]
    conics: torch.Tensor,  # [N, 3]
    opacities: torch.Tensor,  # [N]
    features: torch.Tensor,  # [N, 7]
    radii: torch.Tensor,  # [N] int
    depths: torch.Tensor,  # [N] sort keys
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite to ``features [H, W, 7]`` and ``alpha [H, W, 1]`` (see :func:`C.forward`)."""
    return _Composite.apply(means2d, conics, opacities, features, radii.cpu(), depths.cpu(), width, height)


def rasterize_nograd(means, quats, log_scales, opacity_logits, colors, camera, nf: int = K.NF) -> tuple[torch.Tensor, ...]:
    """Projection and compositing in numba, no autograd: ``features [H, W, nf]``, ``alpha``, ``means2d``, ``radii``.

    The twin of ``project`` + :func:`composite` for rendering a trained model (nothing
    needs a gradient): the ~60 small torch operations of the projection, the float64
    copies and the tile ranges become one parallel pass over the Gaussians
    (:func:`K.project_rows`, float64; the rows are then composited in the inputs' dtype). Plain colours only.
    """
    from lmgs.render import _projection as P

    width, height = int(camera.width), int(camera.height)
    dtype, dev = means.dtype, means.device
    rows, depths, radii, rects, means2d = K.project_rows(
        _np(means), _np(quats), _np(log_scales), _np(opacity_logits), _np(colors), _np(camera.world_to_camera),
        float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), width, height,
        P.NEAR_PLANE, P.EPS2D, P.LOG_SCALE_MIN, P.LOG_SCALE_MAX)
    if _kernel_dtype(means) == torch.float32:
        rows = rows.astype(np.float32)
    out, t_final, _, _ = _composite_rows(rows, rects, radii > 0, depths, width, height, nf)
    feat = torch.from_numpy(out).to(device=dev, dtype=dtype)
    alpha = torch.from_numpy(1.0 - t_final).to(device=dev, dtype=dtype)[..., None]
    return feat, alpha, torch.from_numpy(means2d).to(device=dev, dtype=dtype), torch.from_numpy(radii)
