"""The fast CPU path: numba kernels behind ``torch.autograd.Function`` classes.

Two functions with hand-written backwards, chained by autograd:

* :class:`_Project`: the EWA projection (:mod:`lmgs.render._numba_projection`), from the
  Gaussian parameters to ``means2d [N, 2]`` and the other projected quantities
  ``props [N, 11]`` (conic, opacity, rgb, camera z, normal); its forward also writes the
  compositing rows, tile ranges and depths that the compositor reads;
* :class:`_CompositeRows`: sorting, binning and compositing those rows
  (:mod:`lmgs.render._numba_composite`), differentiable in ``(means2d, props)``.

``means2d`` stays a node of the autograd graph between them (its ``.grad`` is the 2D
positional gradient used for densification). :class:`_Composite` composites the outputs of
the torch projection instead (:func:`composite`: used when the camera itself needs a
gradient, which the numba projection does not give).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

from lmgs.render import _numba_composite as C
from lmgs.render import _numba_kernels as K
from lmgs.render import _numba_projection as NP
from lmgs.render import _projection as P
from lmgs.render._projection import TILE, tile_rects
from lmgs.types import Camera


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
    order = K.depth_order(np.ascontiguousarray(depths, np.float64), vis)
    offsets, ids = K.bin_tiles(rects, order, n_tiles, tiles_w, numba.get_num_threads())
    tile_order = _tile_order(n_tiles)
    if rows.dtype == np.float32 and ids.shape[0] >= C.F32_MAX_ISECT:
        rows = rows.astype(np.float64)
    out, t_final, last = C.forward(rows, ids, offsets, tile_order, tiles_w, width, height, nf,
                                   C.consts(rows.dtype), C.pixel_centres(width, height, rows.dtype))
    return out, t_final, last, (offsets, ids, tile_order, tiles_w, rows)


def _composite_forward(ctx, rows, rects, vis, depths, width, height, n, dtype, dev):
    out, t_final, last, (offsets, ids, tile_order, tiles_w, rows) = _composite_rows(
        rows, rects, vis, depths, width, height)
    ctx.saved = (rows, offsets, ids, tile_order, tiles_w, width, height, t_final, last, n)
    feat = torch.from_numpy(out).to(device=dev, dtype=dtype)
    alpha = torch.from_numpy(1.0 - t_final).to(device=dev, dtype=dtype)[..., None]
    return feat, alpha


def _composite_backward(ctx, g_feat, g_alpha) -> torch.Tensor:
    """Per-Gaussian gradients ``[N, 13]`` (mx, my, conic, opacity, features) of the compositing."""
    rows, offsets, ids, tile_order, tiles_w, width, height, t_final, last, n = ctx.saved
    dtype, dev = g_feat.dtype, g_feat.device
    kd = torch.float32 if rows.dtype == np.float32 else torch.float64
    grad = C.backward(rows, ids, offsets, tile_order, tiles_w, width, height, t_final, last, _np(g_feat, kd),
                      _np(g_alpha, kd)[..., 0], C.consts(rows.dtype), C.pixel_centres(width, height, rows.dtype))
    return torch.from_numpy(C.reduce_grads(grad, ids, n, numba.get_num_threads())).to(device=dev, dtype=dtype)


class _Composite(torch.autograd.Function):
    """Compositing of the torch projection's outputs (rows built here from them)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, radii, depths, width, height):
        rects = tile_rects(means2d, radii, width, height).numpy()
        kd = _kernel_dtype(means2d)
        rows = K.gaussian_rows(_np(means2d, kd), _np(conics, kd), _np(opacities, kd), _np(features, kd))
        return _composite_forward(ctx, rows, rects, (radii > 0).numpy(), depths.detach().cpu().numpy(), width,
                                  height, means2d.shape[0], means2d.dtype, means2d.device)

    @staticmethod
    def backward(ctx, g_feat, g_alpha):
        per_g = _composite_backward(ctx, g_feat, g_alpha)
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


@dataclass
class Prepared:
    """What the numba projection leaves for the compositor (numpy, not in the autograd graph)."""

    rows: np.ndarray  # [N, ROW] compositing rows in the kernel dtype
    rects: np.ndarray  # [N, 4] int64 tile ranges
    depths: np.ndarray  # [N] float64 camera z (sort keys)
    radii: np.ndarray  # [N] int32, 0 = culled


def _camera_args(camera: Camera) -> tuple:
    return (_np(camera.world_to_camera), float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
            int(camera.width), int(camera.height), P.NEAR_PLANE, P.EPS2D, P.LOG_SCALE_MIN, P.LOG_SCALE_MAX)


def _project_np(arrays, camera: Camera, dtype: torch.dtype, with_props: bool):
    """Run :func:`NP.project_forward` on float64 ``arrays`` (means, quats, log-scales, opacity
    logits, rgb): ``means2d``, ``props`` (numpy, float32 for float32 ``dtype``) and :class:`Prepared`."""
    n = arrays[0].shape[0]
    kd = np.float32 if dtype == torch.float32 else np.float64  # as _kernel_dtype
    rows = np.empty((n, K.ROW), kd)
    means2d = np.empty((n, 2), kd)
    props = np.empty((n if with_props else 0, NP.NPROP), kd)
    depths, radii, rects = NP.project_forward(*arrays, *_camera_args(camera), rows, means2d, props)
    return means2d, props, Prepared(rows, rects, depths, radii)


def project_numba(means, quats, log_scales, opacity_logits, colors, camera: Camera):
    """The numba projection without autograd: ``means2d [N, 2]``, ``props [N, 11]`` (conic,
    opacity, rgb, camera z, normal) in the dtype of ``means``, and :class:`Prepared`."""
    arrays = tuple(_np(t) for t in (means, quats, log_scales, opacity_logits, colors))
    m2, props, prep = _project_np(arrays, camera, means.dtype, True)
    return torch.from_numpy(m2).to(means.dtype), torch.from_numpy(props).to(means.dtype), prep


class _Project(torch.autograd.Function):
    """The numba projection; ``box`` (a list) receives the :class:`Prepared` rows."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, colors, camera, box):
        arrays = tuple(_np(t) for t in (means, quats, log_scales, opacity_logits, colors))
        m2, props, prep = _project_np(arrays, camera, means.dtype, True)
        box.append(prep)
        ctx.arrays, ctx.camera = arrays[:4], camera
        ctx.dtypes = tuple(t.dtype for t in (means, quats, log_scales, opacity_logits, colors))
        dev = means.device
        return torch.from_numpy(m2).to(device=dev, dtype=means.dtype), torch.from_numpy(props).to(device=dev,
                                                                                                     dtype=means.dtype)

    @staticmethod
    def backward(ctx, g_means2d, g_props):
        dev = g_means2d.device
        grads = NP.project_backward(*ctx.arrays, *_camera_args(ctx.camera), _np(g_means2d), _np(g_props))
        return (*(torch.from_numpy(g).to(device=dev, dtype=dt) for g, dt in zip(grads, ctx.dtypes)), None, None)


def project_autograd(means, quats, log_scales, opacity_logits, colors, camera: Camera):
    """``means2d [N, 2]`` and ``props [N, 11]`` of the numba projection, differentiable (the
    hand-written backward of :func:`NP.project_backward`)."""
    return _Project.apply(means, quats, log_scales, opacity_logits, colors, camera, [])


class _CompositeRows(torch.autograd.Function):
    """Compositing of the rows the numba projection wrote; differentiable in ``means2d`` and
    ``props`` (whose values the rows hold). Returns ``rgb``, ``depth``, ``normal`` (views of one
    ``[H, W, 7]`` image: their gradients are joined once in the backward, where slicing
    a single output would add a zero-filled image per slice) and ``alpha``."""

    @staticmethod
    def forward(ctx, means2d, props, prep, width, height):
        feat, alpha = _composite_forward(ctx, prep.rows, prep.rects, prep.radii > 0, prep.depths, width, height,
                                         means2d.shape[0], means2d.dtype, means2d.device)
        return feat[..., 0:3], feat[..., 3:4], feat[..., 4:7], alpha

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_normal, g_alpha):
        per_g = _composite_backward(ctx, torch.cat([g_rgb, g_depth, g_normal], -1), g_alpha)
        return per_g[:, 0:2], per_g[:, 2:], None, None, None


def rasterize_numba(means, quats, log_scales, opacity_logits, colors, camera: Camera,
                    nf: int = K.NF) -> tuple[torch.Tensor | None, ...]:
    """Projection and compositing in numba: ``rgb [H, W, 3]``, ``depth [H, W, 1]``,
    ``normal [H, W, 3]``, ``alpha [H, W, 1]``, ``means2d [N, 2]``, ``radii [N]``.

    ``colors`` are rgb ``[N, 3]`` (SH already evaluated). With a gradient to take the two
    autograd functions above run (all 7 features); without, the projection and compositing
    run alone, and ``nf = 3`` composites colour only (``depth`` and ``normal`` None).
    """
    width, height = int(camera.width), int(camera.height)
    params = (means, quats, log_scales, opacity_logits, colors)
    if torch.is_grad_enabled() and any(t.requires_grad for t in params):
        box: list[Prepared] = []
        means2d, props = _Project.apply(*params, camera, box)
        rgb, depth, normal, alpha = _CompositeRows.apply(means2d, props, box[0], width, height)
        return rgb, depth, normal, alpha, means2d, torch.from_numpy(box[0].radii)
    dtype, dev = means.dtype, means.device
    arrays = tuple(_np(t) for t in params)
    m2, _, prep = _project_np(arrays, camera, dtype, False)
    out, t_final, _, _ = _composite_rows(prep.rows, prep.rects, prep.radii > 0, prep.depths, width, height, nf)
    feat = torch.from_numpy(out).to(device=dev, dtype=dtype)
    alpha = torch.from_numpy(1.0 - t_final).to(device=dev, dtype=dtype)[..., None]
    depth, normal = (feat[..., 3:4], feat[..., 4:7]) if nf == K.NF else (None, None)
    return feat[..., 0:3], depth, normal, alpha, torch.from_numpy(m2).to(device=dev, dtype=dtype), torch.from_numpy(
        prep.radii)
