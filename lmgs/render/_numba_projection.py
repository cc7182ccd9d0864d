"""The EWA projection in numba: a forward that writes the compositing rows, and its
hand-written backward.

The formulas are those of :func:`lmgs.render._projection.project` (the definition; see that
module's docstring), one Gaussian at a time in float64, in parallel over Gaussians. The
backward is the derivative of exactly what ``project`` computes, branch for branch, as torch
autograd would take it: ``torch.where`` selects (behind the near plane ``z = 1``, a
non-positive determinant divides by 1), clamps that pass the gradient on their closed range
(the log-scales, the field-of-view clamp of the Jacobian), a zero-norm quaternion (the
identity, no gradient), and the normal's axis and its flip, which carry no gradient of
their own. Tests hold both against torch autograd of ``project``.

The projected quantities per Gaussian (``props``, the inputs of the compositor besides
``means2d``) are laid out as the compositor's gradient rows after the mean::

    0 a, 1 b, 2 c (conic), 3 opacity, 4..6 rgb, 7 camera z, 8..10 camera normal
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from lmgs.render._numba_kernels import NF, TILE, _fill_row

NPROP = 4 + NF  # conic (3), opacity, features (7)


@njit(inline="always")
def _rotation(qw, qx, qy, qz):  # pragma: no cover - compiled
    """Unit quaternion (wxyz, normalised here; zero norm: the identity) and its rotation matrix.

    Returns ``(ok, qn, w, x, y, z, r00 .. r22)``: ``ok`` whether the norm ``qn`` exceeds 1e-12.
    """
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    ok = qn > 1e-12
    if ok:
        w, x, y, z = qw / qn, qx / qn, qy / qn, qz / qn
    else:
        w, x, y, z = 1.0, 0.0, 0.0, 0.0
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    return ok, qn, w, x, y, z, r00, r01, r02, r10, r11, r12, r20, r21, r22


@njit(inline="always")
def _clamp(v, lo, hi):  # pragma: no cover - compiled
    return min(max(v, lo), hi)


@njit(inline="always")
def _mat3(a00, a01, a02, a10, a11, a12, a20, a21, a22, b00, b01, b02, b10, b11, b12, b20, b21, b22):  # pragma: no cover
    """The 3x3 product ``A B``, row by row (each entry summed in the order of ``k``)."""
    return (a00 * b00 + a01 * b10 + a02 * b20, a00 * b01 + a01 * b11 + a02 * b21, a00 * b02 + a01 * b12 + a02 * b22,
            a10 * b00 + a11 * b10 + a12 * b20, a10 * b01 + a11 * b11 + a12 * b21, a10 * b02 + a11 * b12 + a12 * b22,
            a20 * b00 + a21 * b10 + a22 * b20, a20 * b01 + a21 * b11 + a22 * b21, a20 * b02 + a21 * b12 + a22 * b22)


# The per-Gaussian steps below are shared by the forward and the backward (which recomputes
# them). Each returns a flat tuple and takes the earlier steps' tuples whole: numba's parfor
# analysis rejects a nested tuple unpacked inside a prange loop.
@njit(inline="always")
def _view(w2c, fx, fy, cx, cy, width, height):  # pragma: no cover - compiled
    """The camera's first three rows ``(w00, w01, w02, w03, w10, .., w23)`` and the limits
    ``(lim_xp, lim_xn, lim_yp, lim_yn)`` of ``x / z`` and ``y / z`` (the field of view plus 30 %
    of its half-width, where ``project`` clamps them), as one flat tuple."""
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (w2c[0, 0], w2c[0, 1], w2c[0, 2], w2c[0, 3], w2c[1, 0], w2c[1, 1], w2c[1, 2], w2c[1, 3],
            w2c[2, 0], w2c[2, 1], w2c[2, 2], w2c[2, 3], (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x,
            (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y)


@njit(inline="always")
def _axes(g, quats, log_scales, view, ls_min, ls_max):  # pragma: no cover - compiled
    """Gaussian ``g``'s axes in camera space: ``(ok_q, qn, qw, qx, qy, qz)`` of :func:`_rotation`,
    ``k`` the argmin of the clamped log-scales (the normal's axis; first index on ties, torch's),
    the scales ``s0, s1, s2`` and ``rot_cw @ R`` row by row (``c00 .. c22``; its columns are the axes)."""
    w00, w01, w02, _, w10, w11, w12, _, w20, w21, w22 = view[:11]
    ok_q, qn, qw, qx, qy, qz, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(
        np.float64(quats[g, 0]), np.float64(quats[g, 1]), np.float64(quats[g, 2]), np.float64(quats[g, 3]))
    l0 = _clamp(np.float64(log_scales[g, 0]), ls_min, ls_max)
    l1 = _clamp(np.float64(log_scales[g, 1]), ls_min, ls_max)
    l2 = _clamp(np.float64(log_scales[g, 2]), ls_min, ls_max)
    k = 0
    if l1 < l0:
        k = 1
    if l2 < min(l0, l1):
        k = 2
    return (ok_q, qn, qw, qx, qy, qz, k, math.exp(l0), math.exp(l1), math.exp(l2),
            *_mat3(w00, w01, w02, w10, w11, w12, w20, w21, w22, r00, r01, r02, r10, r11, r12, r20, r21, r22))


@njit(inline="always")
def _centre(g, means, view, near):  # pragma: no cover - compiled
    """``(x, y, z_raw, in_front, z)``: the camera-space mean; ``z`` is 1 behind the near plane."""
    w00, w01, w02, w03, w10, w11, w12, w13, w20, w21, w22, w23 = view[:12]
    px, py, pz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
    x = w00 * px + w01 * py + w02 * pz + w03
    y = w10 * px + w11 * py + w12 * pz + w13
    z_raw = w20 * px + w21 * py + w22 * pz + w23
    in_front = z_raw >= near
    return x, y, z_raw, in_front, z_raw if in_front else 1.0


@njit(inline="always")
def _jacobian(centre, view, fx, fy):  # pragma: no cover - compiled
    """``(ux, uy, cux, cuy, tx, ty, z2, j00, j02, j11, j12)``: ``u = x / z`` and its clamp ``cu``,
    ``t = z cu``, ``z2 = z^2`` and the EWA Jacobian's non-zero entries."""
    x, y, _, _, z = centre
    lim_xp, lim_xn, lim_yp, lim_yn = view[12:]
    ux, uy = x / z, y / z
    cux, cuy = _clamp(ux, -lim_xn, lim_xp), _clamp(uy, -lim_yn, lim_yp)
    tx, ty = z * cux, z * cuy
    z2 = z * z
    return ux, uy, cux, cuy, tx, ty, z2, fx / z, -fx * tx / z2, fy / z, -fy * ty / z2


@njit(inline="always")
def _conic_rows(axes, jac, eps2d):  # pragma: no cover - compiled
    """``rs = rot S`` (``rs00 .. rs22``), ``m = J rs`` (its two rows ``m00 .. m12``) and the 2D
    covariance ``a, b, c`` (low-passed by ``eps2d``) with its determinant ``det``."""
    s0, s1, s2, c00, c01, c02, c10, c11, c12, c20, c21, c22 = axes[7:]
    j00, j02, j11, j12 = jac[7:]
    rs00, rs01, rs02 = c00 * s0, c01 * s1, c02 * s2
    rs10, rs11, rs12 = c10 * s0, c11 * s1, c12 * s2
    rs20, rs21, rs22 = c20 * s0, c21 * s1, c22 * s2
    m00 = j00 * rs00 + j02 * rs20
    m01 = j00 * rs01 + j02 * rs21
    m02 = j00 * rs02 + j02 * rs22
    m10 = j11 * rs10 + j12 * rs20
    m11 = j11 * rs11 + j12 * rs21
    m12 = j11 * rs12 + j12 * rs22
    a = m00 * m00 + m01 * m01 + m02 * m02 + eps2d
    b = m00 * m10 + m01 * m11 + m02 * m12
    c = m10 * m10 + m11 * m11 + m12 * m12 + eps2d
    return (rs00, rs01, rs02, rs10, rs11, rs12, rs20, rs21, rs22, m00, m01, m02, m10, m11, m12, a, b, c, a * c - b * b)


@njit(inline="always")
def _normal(axes, centre):  # pragma: no cover - compiled
    """``(nx, ny, nz, sgn)``: the axis of the smallest scale, times ``sgn = -1`` where that faces
    away from the camera (at the origin), else ``sgn = 1``."""
    k = axes[6]
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = axes[10:]
    x, y, z_raw = centre[:3]
    if k == 0:
        nx, ny, nz = c00, c10, c20
    elif k == 1:
        nx, ny, nz = c01, c11, c21
    else:
        nx, ny, nz = c02, c12, c22
    sgn = -1.0 if nx * x + ny * y + nz * z_raw > 0 else 1.0
    return sgn * nx, sgn * ny, sgn * nz, sgn


@njit(inline="always")
def _put_features(out, g, j, colors, z, nx, ny, nz):  # pragma: no cover - compiled
    """``out[g, j:j + 7]``: the features rgb, camera z and normal (their order in rows and props)."""
    out[g, j] = np.float64(colors[g, 0])
    out[g, j + 1] = np.float64(colors[g, 1])
    out[g, j + 2] = np.float64(colors[g, 2])
    out[g, j + 3] = z
    out[g, j + 4] = nx
    out[g, j + 5] = ny
    out[g, j + 6] = nz


@njit(parallel=True, cache=True)
def project_forward(means, quats, log_scales, opacity_logits, colors, w2c, fx, fy, cx, cy, width, height,
                    near, eps2d, ls_min, ls_max, rows, means2d, props):  # pragma: no cover - compiled
    """Project every Gaussian, writing the compositing rows (``rows [N, ROW]``, in their own
    dtype, see :mod:`lmgs.render._numba_kernels`), ``means2d [N, 2]`` and ``props [N, NPROP]``
    (in theirs; ``props`` may have zero rows: then it is not written).

    The Gaussian parameters (``colors [N, 3]`` rgb) share one dtype, float32 or float64: each
    value is read as a float64 and the arithmetic is float64 whatever it is (float32 inputs give
    the results of their float64 copies, bit for bit). ``w2c [4, 4]`` is float64, world to camera
    (OpenCV).

    Returns ``depths [N]`` float64 (camera z; 1 behind the near plane), ``radii [N]`` int32
    (0 = culled) and ``rects [N, 4]`` int64 half-open tile ranges (zero when culled).
    """
    n = means.shape[0]
    depths = np.empty(n, np.float64)
    radii = np.zeros(n, np.int32)
    rects = np.zeros((n, 4), np.int64)
    with_props = props.shape[0] > 0
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    view = _view(w2c, fx, fy, cx, cy, width, height)
    for g in prange(n):
        axes = _axes(g, quats, log_scales, view, ls_min, ls_max)
        centre = _centre(g, means, view, near)
        x, y, _, in_front, z = centre
        a, b, c, det = _conic_rows(axes, _jacobian(centre, view, fx, fy), eps2d)[15:]
        ok = in_front and det > 0
        det_s = det if ok else 1.0
        mx = fx * x / z + cx
        my = fy * y / z + cy
        mid = 0.5 * (a + c)
        lam = mid + math.sqrt(max(mid * mid - det, 0.1))
        radius = math.ceil(3.0 * math.sqrt(lam))
        on_img = (mx + radius > 0) and (mx - radius < width) and (my + radius > 0) and (my - radius < height)
        if ok and on_img and radius > 0:
            radii[g] = np.int32(radius)
            rects[g, 0] = np.int64(min(max(math.floor((mx - radius) / TILE), 0.0), tw))
            rects[g, 1] = np.int64(min(max(math.ceil((mx + radius) / TILE), 0.0), tw))
            rects[g, 2] = np.int64(min(max(math.floor((my - radius) / TILE), 0.0), th))
            rects[g, 3] = np.int64(min(max(math.ceil((my + radius) / TILE), 0.0), th))
        nx, ny, nz, _ = _normal(axes, centre)
        ca, cb, cc = c / det_s, -b / det_s, a / det_s
        op = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[g])))
        _put_features(rows, g, 7, colors, z, nx, ny, nz)
        _fill_row(rows, g, mx, my, ca, cb, cc, op)
        means2d[g, 0] = mx
        means2d[g, 1] = my
        depths[g] = z
        if with_props:
            props[g, 0] = ca
            props[g, 1] = cb
            props[g, 2] = cc
            props[g, 3] = op
            _put_features(props, g, 4, colors, z, nx, ny, nz)
    return depths, radii, rects


@njit(parallel=True, cache=True)
def project_backward(means, quats, log_scales, opacity_logits, w2c, fx, fy, cx, cy, width, height,
                     near, eps2d, ls_min, ls_max, g_rows):  # pragma: no cover - compiled
    """Gradients of the projection from ``g_rows [N, 2 + NPROP]``: those of ``means2d`` (columns
    0, 1) and of ``props`` (the rest).

    Recomputes each Gaussian's forward quantities (cheaper than storing them) with the steps
    :func:`project_forward` takes, and applies the chain rule backwards through them, in
    float64 (the inputs and ``g_rows`` read as float64, as in the forward).

    Returns ``g_means [N, 3]``, ``g_quats [N, 4]``, ``g_log_scales [N, 3]``,
    ``g_opacity_logits [N]`` and ``g_colors [N, 3]`` in the dtype of ``means`` (float64 sums
    rounded once).
    """
    n = means.shape[0]
    dt = means.dtype
    g_means = np.zeros((n, 3), dt)
    g_quats = np.zeros((n, 4), dt)
    g_ls = np.zeros((n, 3), dt)
    g_logit = np.zeros(n, dt)
    g_col = np.zeros((n, 3), dt)
    view = _view(w2c, fx, fy, cx, cy, width, height)
    w00, w01, w02, _, w10, w11, w12, _, w20, w21, w22, _, lim_xp, lim_xn, lim_yp, lim_yn = view
    for g in prange(n):
        # ---- forward, as in project_forward ----
        axes = _axes(g, quats, log_scales, view, ls_min, ls_max)
        ok_q, qn, qw, qx, qy, qz, k, s0, s1, s2, c00, c01, c02, c10, c11, c12, c20, c21, c22 = axes
        centre = _centre(g, means, view, near)
        x, y, z_raw, in_front, z = centre
        jac = _jacobian(centre, view, fx, fy)
        ux, uy, cux, cuy, tx, ty, z2, j00, j02, j11, j12 = jac
        rs00, rs01, rs02, rs10, rs11, rs12, rs20, rs21, rs22, m00, m01, m02, m10, m11, m12, a, b, c, det = _conic_rows(
            axes, jac, eps2d)
        ok = in_front and det > 0
        sgn = _normal(axes, centre)[3]
        lr0, lr1, lr2 = np.float64(log_scales[g, 0]), np.float64(log_scales[g, 1]), np.float64(log_scales[g, 2])
        # ---- backward ----
        gmx, gmy = np.float64(g_rows[g, 0]), np.float64(g_rows[g, 1])
        gc0, gc1, gc2 = np.float64(g_rows[g, 2]), np.float64(g_rows[g, 3]), np.float64(g_rows[g, 4])
        op = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[g])))
        g_logit[g] = np.float64(g_rows[g, 5]) * op * (1.0 - op)
        g_col[g, 0] = g_rows[g, 6]
        g_col[g, 1] = g_rows[g, 7]
        g_col[g, 2] = g_rows[g, 8]
        # means2d = (fx x / z + cx, fy y / z + cy); the feature z
        gx = gmx * fx / z
        gy = gmy * fy / z
        gz = np.float64(g_rows[g, 9]) - gmx * fx * x / z2 - gmy * fy * y / z2
        # conic = (c, -b, a) / det_s
        if ok:
            inv = 1.0 / det
            gdet = -(gc0 * c - gc1 * b + gc2 * a) * inv * inv
            ga = gc2 * inv + gdet * c
            gb = -gc1 * inv - 2.0 * gdet * b
            gcc = gc0 * inv + gdet * a
        else:
            ga, gb, gcc = gc2, -gc1, gc0
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
        grs00, grs01, grs02 = gm00 * j00, gm01 * j00, gm02 * j00
        grs10, grs11, grs12 = gm10 * j11, gm11 * j11, gm12 * j11
        grs20 = gm00 * j02 + gm10 * j12
        grs21 = gm01 * j02 + gm11 * j12
        grs22 = gm02 * j02 + gm12 * j12
        gc00, gc01, gc02 = grs00 * s0, grs01 * s1, grs02 * s2
        gc10, gc11, gc12 = grs10 * s0, grs11 * s1, grs12 * s2
        gc20, gc21, gc22 = grs20 * s0, grs21 * s1, grs22 * s2
        gs0 = grs00 * c00 + grs10 * c10 + grs20 * c20
        gs1 = grs01 * c01 + grs11 * c11 + grs21 * c21
        gs2 = grs02 * c02 + grs12 * c12 + grs22 * c22
        g_ls[g, 0] = gs0 * s0 if ls_min <= lr0 <= ls_max else 0.0
        g_ls[g, 1] = gs1 * s1 if ls_min <= lr1 <= ls_max else 0.0
        g_ls[g, 2] = gs2 * s2 if ls_min <= lr2 <= ls_max else 0.0
        # the normal: column k of rot_c, flipped to face the camera
        gn0 = sgn * np.float64(g_rows[g, 10])
        gn1 = sgn * np.float64(g_rows[g, 11])
        gn2 = sgn * np.float64(g_rows[g, 12])
        if k == 0:
            gc00 += gn0
            gc10 += gn1
            gc20 += gn2
        elif k == 1:
            gc01 += gn0
            gc11 += gn1
            gc21 += gn2
        else:
            gc02 += gn0
            gc12 += gn1
            gc22 += gn2
        # J: j00 = fx / z, j02 = -fx tx / z^2 (and y)
        gz += -gj00 * fx / z2 - gj11 * fy / z2
        gtx = -gj02 * fx / z2
        gty = -gj12 * fy / z2
        gz += 2.0 * (gj02 * fx * tx + gj12 * fy * ty) / (z2 * z)
        # tx = z clamp(x / z), ty likewise
        gz += gtx * cux + gty * cuy
        gux = gtx * z if -lim_xn <= ux <= lim_xp else 0.0
        guy = gty * z if -lim_yn <= uy <= lim_yp else 0.0
        gx += gux / z
        gy += guy / z
        gz -= (gux * x + guy * y) / z2
        gzr = gz if in_front else 0.0
        # camera-space mean = W p + t
        g_means[g, 0] = w00 * gx + w10 * gy + w20 * gzr
        g_means[g, 1] = w01 * gx + w11 * gy + w21 * gzr
        g_means[g, 2] = w02 * gx + w12 * gy + w22 * gzr
        if not ok_q:
            continue  # the identity: no gradient to the quaternion
        # rot_c = W R: the gradient of R is W^T times that of rot_c
        g00, g01, g02, g10, g11, g12, g20, g21, g22 = _mat3(w00, w10, w20, w01, w11, w21, w02, w12, w22,
                                                            gc00, gc01, gc02, gc10, gc11, gc12, gc20, gc21, gc22)
        # R of the unit quaternion
        gw = 2.0 * (-qz * g01 + qy * g02 + qz * g10 - qx * g12 - qy * g20 + qx * g21)
        gxq = 2.0 * (-2.0 * qx * (g11 + g22) + qy * (g01 + g10) + qz * (g02 + g20) + qw * (g21 - g12))
        gyq = 2.0 * (-2.0 * qy * (g00 + g22) + qx * (g01 + g10) + qz * (g12 + g21) + qw * (g02 - g20))
        gzq = 2.0 * (-2.0 * qz * (g00 + g11) + qx * (g02 + g20) + qy * (g12 + g21) + qw * (g10 - g01))
        # normalisation q / |q|
        dot = qw * gw + qx * gxq + qy * gyq + qz * gzq
        g_quats[g, 0] = (gw - qw * dot) / qn
        g_quats[g, 1] = (gxq - qx * dot) / qn
        g_quats[g, 2] = (gyq - qy * dot) / qn
        g_quats[g, 3] = (gzq - qz * dot) / qn
    return g_means, g_quats, g_ls, g_logit, g_col
