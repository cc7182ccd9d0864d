"""The ``"triton"`` backend (:func:`rasterize_triton`): the EWA projection in Triton, fused with the packing of
the compositor of :mod:`lmgs.render._triton`.

Two ``torch.autograd.Function`` classes with hand-written backwards, chained as on the numba
path (:mod:`lmgs.render._cpu`):

* :class:`_Project`: one kernel launch forward (``_project_kernel``, a lane per Gaussian) that
  computes what :func:`lmgs.render._numba_projection.project_forward` does, in float64 (the
  inputs read in their dtype and widened, as numba reads them): ``means2d [N, 2]`` and
  ``props [N, 11]`` (conic, opacity, rgb, camera z, normal) in the dtype of ``means``, the
  int32 radii, and what :func:`lmgs.render._triton.bin_tiles` would pack from them: the compositor's float32
  rows and features, each Gaussian's tile rectangle and depth key (the work of
  ``_prepare_kernel``, here from the float64 mean like the numba rectangles), and a zeroed
  gradient buffer for the compositor's backward. Its backward is one launch
  (``_project_grad_kernel``), the port of
  :func:`lmgs.render._numba_projection.project_backward` (the forward recomputed, the chain
  rule branch for branch, float64), reading the cotangents of ``means2d`` and ``props``
  through their strides and writing each parameter's gradient in its dtype.
* :class:`_CompositePacked`: binning (:func:`bin_info`) and the compositing kernels on
  those packed rows; differentiable in ``(means2d, props)``, whose
  values the rows hold. ``rgb``, ``depth`` and ``normal`` come back as views of one
  ``[H, W, 7]`` image and their cotangents go to the backward kernel as they are (one left
  unused is not read), so no cotangent is sliced, joined or zero-filled.

``means2d`` stays a node of the graph between the two (``retain_grad()`` on it gives the 2D
positional gradient), as on the numba path. Plain ``[N, 3]`` colours are read by the
projection kernel; SH colours are evaluated first by the caller (``view_colors``, torch).

The float64 arithmetic follows numba's expression for expression; the compiled kernels may
fuse a multiply and an add (``fma``), which numba does not, so float64 results can differ in
their last bits (float32 outputs and the integer radii practically never). The depth key is
the float32 depth's bits for float32 parameters (numba sorts the float64 depths: Gaussians
whose depths round to the same float32 keep index order here), the rank of the depth in a
stable sort for other dtypes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import triton
import triton.language as tl

from lmgs.render._projection import EPS2D, LOG_SCALE_MAX, LOG_SCALE_MIN, NEAR_PLANE
from lmgs.render._triton import (FP, GROW, PARAMS, _GROW, _NF, bin_info, depth_key, rank_depths, render_tiles,
                                 store_tile_info, tile_grads, tile_grid)
from lmgs.types import Camera

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
