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

import threading
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
    """``t`` as a C-contiguous numpy array in ``dtype`` (no copy when it already is one)."""
    return t.detach().to(device="cpu", dtype=dtype).contiguous().numpy()


def _params_np(params) -> tuple[np.ndarray, ...]:
    """The Gaussian parameters as numpy arrays for the numba projection: as they are (no copy)
    when they share one dtype, float32 or float64, and are contiguous CPU tensors; else float64
    copies. The projection reads either in float64, so both give the same results."""
    dt = params[0].dtype
    if dt in (torch.float32, torch.float64) and all(t.dtype == dt for t in params):
        return tuple(_np(t, dt) for t in params)
    return tuple(_np(t) for t in params)


def _threads() -> int:
    return max(1, numba.get_num_threads())


# Items (Gaussians, sort keys) per thread below which a numba loop over them runs on fewer
# threads. Every parallel region wakes its whole team (the OpenMP pool, shared with torch,
# waits passively: see lmgs/__init__), which costs more than a small loop's share of the work;
# the results do not depend on the thread count.
ITEMS_PER_THREAD = 1024


def _on_threads(k: int, fn, *args):
    """``fn(*args)`` with numba's thread count lowered to ``k`` (at least 1) for the call."""
    p = numba.get_num_threads()
    if k >= p:
        return fn(*args)
    numba.set_num_threads(max(1, k))
    try:
        return fn(*args)
    finally:
        numba.set_num_threads(p)


def _team(n_items: int) -> int:
    """Threads for a numba loop over ``n_items`` items: the thread count, capped by the work."""
    return max(1, min(_threads(), n_items // ITEMS_PER_THREAD))


def _tile_order(offsets: np.ndarray) -> np.ndarray:
    """The non-empty tiles per parallel chunk ``[P, m]``, padded with -1 (:func:`K.balance_tiles`).

    One chunk per numba thread (fewer when fewer tiles hold Gaussians), the tiles dealt by their
    intersection counts so that the chunks cost about the same (a fixed interleaving deals whole
    tile columns to a chunk when the thread count divides the tiles per row, and the head's
    columns cost more than the border's); each chunk allocates its per-pixel scratch once.
    Every pixel's result is the same whatever the chunking.
    """
    n_busy = int(np.count_nonzero(offsets[1:] != offsets[:-1]))
    return K.balance_tiles(offsets, max(1, min(_threads(), n_busy)))


def _composite_rows(rows: np.ndarray, rects: np.ndarray, vis: np.ndarray, depths: np.ndarray, width: int, height: int,
                    nf: int = K.NF):
    """Sort the visible Gaussians front to back, bin them into tiles and composite their rows
    (the first ``nf`` features: 3 is colour alone) in the dtype of ``rows``.

    Returns ``out, t_final, alpha, last, saved``: ``alpha = 1 - t_final``; ``saved`` what
    :func:`_composite_grads` needs: ``(rows, offsets, ids, tile_order, tiles_w)``
    with ``rows`` as composited (float64 when a float32 stop index could not hold every
    intersection index).
    """
    tiles_w, tiles_h = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    n_tiles = tiles_w * tiles_h
    # stable sort by depth: ties keep index order, like the dense reference
    k = min(_threads(), depths.shape[0] // K.SORT_CHUNK)
    order = _on_threads(k, K.depth_order, np.ascontiguousarray(depths, np.float64), vis, k)
    k = _team(order.shape[0])
    offsets, ids = _on_threads(k, K.bin_tiles, rects, order, n_tiles, tiles_w, k)
    tile_order = _tile_order(offsets)
    if rows.dtype == np.float32 and ids.shape[0] >= C.F32_MAX_ISECT:
        rows = rows.astype(np.float64)
    out, t_final, alpha, last = _on_threads(tile_order.shape[0], C.forward, rows, ids, offsets, tile_order, tiles_w,
                                            width, height, nf, C.consts(rows.dtype),
                                            C.pixel_centres(width, height, rows.dtype))
    return out, t_final, alpha, last, (rows, offsets, ids, tile_order, tiles_w)


_SCRATCH = threading.local()
SCRATCH_MAX_BYTES = 1 << 28  # larger gradient buffers are not kept


def _grad_buffer(n_isect: int, dtype: np.dtype) -> np.ndarray:
    """``[n_isect, 13]`` scratch for the backward kernel's per-intersection gradients (which it
    overwrites whole), kept per Python thread and dtype and grown as needed: a fresh buffer of
    this size (tens of MB) costs a page fault per 4 kB, every step."""
    bufs = getattr(_SCRATCH, "grad", None)
    if bufs is None:
        bufs = _SCRATCH.grad = {}
    size, key = n_isect * C.GROW, np.dtype(dtype)
    buf = bufs.get(key)
    if buf is None or buf.size < size:
        buf = np.empty(size + size // 4, key)
        if buf.nbytes <= SCRATCH_MAX_BYTES:
            bufs[key] = buf
    return buf[:size].reshape(n_isect, C.GROW)


def _composite_forward(ctx, rows, rects, vis, depths, width, height, n, dtype, dev):
    out, t_final, alpha, last, saved = _composite_rows(rows, rects, vis, depths, width, height)
    ctx.saved = (saved, width, height, t_final, last, n)
    feat = torch.from_numpy(out).to(device=dev, dtype=dtype)
    return feat, torch.from_numpy(alpha).to(device=dev, dtype=dtype)[..., None]


def _composite_grads(ctx, g_rgb, g_depth, g_normal, g_alpha) -> torch.Tensor:
    """Per-Gaussian gradients ``[N, 13]`` (mx, my, conic, opacity, features) of the compositing,
    from those of the images ``rgb [H, W, 3]``, ``depth [H, W, 1]``, ``normal [H, W, 3]`` and
    ``alpha [H, W, 1]`` (each made a C-contiguous array in the kernel dtype: no copy when it is one)."""
    (rows, offsets, ids, tile_order, tiles_w), width, height, t_final, last, n = ctx.saved
    dtype, dev = g_rgb.dtype, g_rgb.device
    kd = torch.float32 if rows.dtype == np.float32 else torch.float64
    grad = _on_threads(tile_order.shape[0], C.backward, rows, ids, offsets, tile_order, tiles_w, width, height, t_final,
                       last, _np(g_rgb, kd), _np(g_depth, kd), _np(g_normal, kd), _np(g_alpha, kd)[..., 0],
                       C.consts(rows.dtype), C.pixel_centres(width, height, rows.dtype),
                       _grad_buffer(ids.shape[0], rows.dtype))
    k = _team(n)
    per_g = _on_threads(k, C.reduce_grads, grad, ids, n, k)
    return torch.from_numpy(per_g).to(device=dev, dtype=dtype)


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
        per_g = _composite_grads(ctx, g_feat[..., 0:3], g_feat[..., 3:4], g_feat[..., 4:7], g_alpha)
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
    """Run :func:`NP.project_forward` on ``arrays`` (means, quats, log-scales, opacity logits, rgb;
    :func:`_params_np`): ``means2d``, ``props`` (numpy, float32 for float32 ``dtype``) and :class:`Prepared`."""
    n = arrays[0].shape[0]
    kd = np.float32 if dtype == torch.float32 else np.float64  # as _kernel_dtype
    rows = np.empty((n, K.ROW), kd)
    means2d = np.empty((n, 2), kd)
    props = np.empty((n if with_props else 0, NP.NPROP), kd)
    depths, radii, rects = _on_threads(_team(n), NP.project_forward, *arrays, *_camera_args(camera), rows, means2d,
                                       props)
    return means2d, props, Prepared(rows, rects, depths, radii)


def project_numba(means, quats, log_scales, opacity_logits, colors, camera: Camera):
    """The numba projection without autograd: ``means2d [N, 2]``, ``props [N, 11]`` (conic,
    opacity, rgb, camera z, normal) in the dtype of ``means``, and :class:`Prepared`."""
    arrays = _params_np((means, quats, log_scales, opacity_logits, colors))
    m2, props, prep = _project_np(arrays, camera, means.dtype, True)
    return torch.from_numpy(m2).to(means.dtype), torch.from_numpy(props).to(means.dtype), prep


class _Project(torch.autograd.Function):
    """The numba projection; ``box`` (a list) receives the :class:`Prepared` rows."""

    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, colors, camera, box):
        arrays = _params_np((means, quats, log_scales, opacity_logits, colors))
        m2, props, prep = _project_np(arrays, camera, means.dtype, True)
        box.append(prep)
        ctx.save_for_backward(means, quats, log_scales, opacity_logits)  # (autograd checks in-place changes)
        ctx.camera = camera
        ctx.dtypes = tuple(t.dtype for t in (means, quats, log_scales, opacity_logits, colors))
        dev = means.device
        return torch.from_numpy(m2).to(device=dev, dtype=means.dtype), torch.from_numpy(props).to(device=dev,
                                                                                                     dtype=means.dtype)

    @staticmethod
    def backward(ctx, g_means2d, g_props):
        dev = g_means2d.device
        arrays = _params_np(ctx.saved_tensors)
        grads = _on_threads(_team(g_means2d.shape[0]), NP.project_backward, *arrays, *_camera_args(ctx.camera),
                            _grad_rows(g_means2d, g_props))
        return (*(torch.from_numpy(g).to(device=dev, dtype=dt) for g, dt in zip(grads, ctx.dtypes)), None, None)


def _grad_rows(g_means2d: torch.Tensor, g_props: torch.Tensor) -> np.ndarray:
    """The gradients of ``means2d [N, 2]`` and ``props [N, NPROP]`` side by side, ``[N, 2 + NPROP]``:
    the compositor's ``[N, 13]`` gradient rows themselves when the two are its column slices
    (no copy), else the two joined (in float64 unless both are float32)."""
    n, w = g_means2d.shape[0], 2 + NP.NPROP
    dt, size = g_means2d.dtype, g_means2d.element_size()
    if (dt in (torch.float32, torch.float64) and g_props.dtype == dt and g_means2d.device.type == "cpu"
            and g_props.device.type == "cpu" and n > 0 and g_means2d.stride() == (w, 1) and g_props.stride() == (w, 1)
            and g_means2d.untyped_storage().data_ptr() == g_props.untyped_storage().data_ptr()
            and g_props.data_ptr() == g_means2d.data_ptr() + 2 * size):
        return g_means2d.detach().as_strided((n, w), (w, 1)).numpy()
    kd = torch.float32 if dt == g_props.dtype == torch.float32 else torch.float64
    return _np(torch.cat([g_means2d.to(kd), g_props.to(kd)], 1), kd)


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
        per_g = _composite_grads(ctx, g_rgb, g_depth, g_normal, g_alpha)
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
    m2, _, prep = _project_np(_params_np(params), camera, dtype, False)
    out, _, alpha, _, _ = _composite_rows(prep.rows, prep.rects, prep.radii > 0, prep.depths, width, height, nf)
    feat = torch.from_numpy(out).to(device=dev, dtype=dtype)
    alpha = torch.from_numpy(alpha).to(device=dev, dtype=dtype)[..., None]
    depth, normal = (feat[..., 3:4], feat[..., 4:7]) if nf == K.NF else (None, None)
    return feat[..., 0:3], depth, normal, alpha, torch.from_numpy(m2).to(device=dev, dtype=dtype), torch.from_numpy(
        prep.radii)
