"""Input checks and the EWA projection shared by the fast CPU path and the torch anchor.

Everything here is plain differentiable torch over ``N`` Gaussians (cheap: ``O(N)``);
the per-pixel work lives in :mod:`lmgs.render._numba_kernels` (fast path) and
:mod:`lmgs.render._tiled_torch` (anchor).

Conventions (Inria 3DGS, Kerbl et al. 2023, and gsplat):

* camera space is OpenCV (x right, y down, z forward); pixel ``(row i, col j)`` has its
  centre at ``(j + 0.5, i + 0.5)``;
* the 2D mean is :math:`\\mu' = (f_x x/z + c_x,\\ f_y y/z + c_y)`;
* the 2D covariance is the EWA splat (Zwicker et al. 2002)
  :math:`\\Sigma' = J W \\Sigma W^T J^T + 0.3 I` with :math:`\\Sigma = R S S^T R^T`,
  the Jacobian evaluated at the mean clamped to 1.3x the field of view;
* the extent is :math:`r = \\lceil 3 \\sqrt{\\lambda_{max}(\\Sigma')} \\rceil` with
  :math:`\\lambda_{max} = m + \\sqrt{\\max(0.1, m^2 - \\det\\Sigma')}`, :math:`m = \\mathrm{tr}\\,\\Sigma'/2`;
* Gaussians with camera ``z < NEAR_PLANE``, or whose square of radius ``r`` misses the
  image, are culled (``radius = 0``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from lmgs.errors import InputError
from lmgs.types import Camera

NEAR_PLANE = 0.01
EPS2D = 0.3  # low-pass filter added to the 2D covariance diagonal (pixels^2)
TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# log-scales are clamped into this range: exp(-30) ~ 1e-13 keeps covariances finite in
# float32, exp(10) ~ 2.2e4 world units is far beyond any scene.
LOG_SCALE_MIN = -30.0
LOG_SCALE_MAX = 10.0
# Channels composited per Gaussian: rgb, camera z, camera-space normal.
N_FEATURES = 7

_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def check_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None,
    sh_degree: int | None,
    values: bool = True,
) -> int | None:
    """Raise :class:`InputError` on bad shapes or (``values``) non-finite values; return the SH degree.

    Returns ``None`` for plain colours ``[N, 3]``, else the SH degree used.
    """
    if not isinstance(means, torch.Tensor) or means.dim() != 2 or means.shape[1] != 3:
        raise InputError(f"means must be a [N, 3] tensor, got {_shape(means)}")
    n = means.shape[0]
    if not means.is_floating_point():
        raise InputError(f"means must be a floating-point tensor, got {means.dtype}")
    expected = {"quats": (quats, (n, 4)), "log_scales": (log_scales, (n, 3)), "opacity_logits": (opacity_logits, (n,))}
    for name, (t, shape) in expected.items():
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
            raise InputError(f"{name} must have shape {list(shape)} (N={n} from means), got {_shape(t)}")
    if not isinstance(colors, torch.Tensor) or colors.shape[0:1] != (n,) or colors.shape[-1] != 3 or colors.dim() not in (2, 3):
        raise InputError(f"colors must be [N, 3] or SH coefficients [N, K, 3] (N={n}), got {_shape(colors)}")
    degree: int | None = None
    if colors.dim() == 3:
        k = colors.shape[1]
        if sh_degree is None:
            d = math.isqrt(k) - 1
            if (d + 1) ** 2 != k:
                raise InputError(f"colors has K={k} SH coefficients, not a square; pass sh_degree")
            sh_degree = d
        if not 0 <= sh_degree <= 3 or (sh_degree + 1) ** 2 > k:
            raise InputError(f"sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} <= K={k} coefficients and 0..3")
        degree = sh_degree
    elif sh_degree is not None:
        raise InputError(f"sh_degree={sh_degree} was given but colors is [N, 3], not SH [N, K, 3]")
    if background is not None and (not isinstance(background, torch.Tensor) or tuple(background.shape) != (3,)):
        raise InputError(f"background must be a [3] tensor or None, got {_shape(background)}")
    w2c = camera.world_to_camera
    if not isinstance(w2c, torch.Tensor) or tuple(w2c.shape) != (4, 4):
        raise InputError(f"camera.world_to_camera must be a [4, 4] tensor, got {_shape(w2c)}")
    if int(camera.width) <= 0 or int(camera.height) <= 0:
        raise InputError(f"camera size must be positive, got {camera.width}x{camera.height}")
    intr = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
    for k_, v in intr.items():
        if not math.isfinite(float(v)) or (k_ in ("fx", "fy") and float(v) <= 0):
            raise InputError(f"camera.{k_} must be finite (and focal lengths > 0), got {v}")
    tensors = {
        "means": means,
        "quats": quats,
        "log_scales": log_scales,
        "opacity_logits": opacity_logits,
        "colors": colors,
        "camera.world_to_camera": w2c,
    }
    if background is not None:
        tensors["background"] = background
    for name, t in tensors.items():
        if not t.is_floating_point():
            raise InputError(f"{name} must be a floating-point tensor, got {t.dtype}")
    if not values:
        return degree
    found = first_non_finite(tensors)
    if found is not None:
        name, t, bad = found
        rows = bad.reshape(t.shape[0], -1).any(dim=1).nonzero().flatten() if t.dim() > 0 else torch.zeros(1)
        first = rows[:5].tolist()
        raise InputError(
            f"{name} has {int(bad.sum())} non-finite value(s) (NaN/inf) in {len(rows)} of its {t.shape[0]} rows "
            f"(first rows: {first})"
        )
    return degree


def first_non_finite(tensors: dict[str, torch.Tensor]) -> tuple[str, torch.Tensor, torch.Tensor] | None:
    """The first of the named ``tensors`` holding NaN or inf, with the mask of its bad values, or None.

    One reduction per tensor and one read-back for all of them (a single host sync on a GPU): a NaN or
    inf makes a sum non-finite; only a tensor whose sum is not finite is looked at value by value
    (finite values summed past the float range are no error).
    """
    if not tensors:
        return None
    dev = next(iter(tensors.values())).device
    sums = torch.stack([t.detach().sum().to(device=dev, dtype=torch.float64) for t in tensors.values()])
    for (name, t), total in zip(tensors.items(), sums.tolist()):
        if not math.isfinite(total):
            bad = ~torch.isfinite(t.detach())
            if bool(bad.any()):
                return name, t, bad
    return None


def _shape(t: object) -> str:
    return str(list(t.shape)) if isinstance(t, torch.Tensor) else type(t).__name__


def normalize_quats(quats: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``[N, 4]`` (wxyz); a zero-norm quaternion becomes the identity.

    .. math:: \\hat q = q / \\|q\\| \\text{ if } \\|q\\| > 10^{-12} \\text{ else } (1, 0, 0, 0)
    """
    norm = quats.norm(dim=-1, keepdim=True)
    ok = norm > 1e-12
    ident = torch.zeros_like(quats)
    ident[:, 0] = 1.0
    return torch.where(ok, quats / norm.clamp_min(1e-12), ident)


def clamp_log_scales(log_scales: torch.Tensor) -> torch.Tensor:
    """Clamp ``[N, 3]`` log-scales into ``[LOG_SCALE_MIN, LOG_SCALE_MAX]`` (no gradient outside)."""
    return log_scales.clamp(LOG_SCALE_MIN, LOG_SCALE_MAX)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[N, 3, 3]`` from unit quaternions ``[N, 4]`` (wxyz)."""
    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )  # fmt: skip
    return r.reshape(-1, 3, 3)


def eval_sh(coeffs: torch.Tensor, degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Colour ``[N, 3]`` from real SH coefficients ``[N, K, 3]`` for unit view directions ``[N, 3]``.

    The 3DGS convention: :math:`c = \\max(0, \\sum_{l \\le d} \\sum_m c_{lm} Y_{lm}(\\mathbf v) + 0.5)`,
    with :math:`\\mathbf v` the unit vector from the camera centre to the Gaussian.
    """
    res = _SH_C0 * coeffs[:, 0]
    if degree >= 1:
        x, y, z = (dirs[:, i : i + 1] for i in range(3))
        res = res - _SH_C1 * y * coeffs[:, 1] + _SH_C1 * z * coeffs[:, 2] - _SH_C1 * x * coeffs[:, 3]
        if degree >= 2:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            res = (
                res
                + _SH_C2[0] * xy * coeffs[:, 4]
                + _SH_C2[1] * yz * coeffs[:, 5]
                + _SH_C2[2] * (2 * zz - xx - yy) * coeffs[:, 6]
                + _SH_C2[3] * xz * coeffs[:, 7]
                + _SH_C2[4] * (xx - yy) * coeffs[:, 8]
            )
            if degree >= 3:
                res = (
                    res
                    + _SH_C3[0] * y * (3 * xx - yy) * coeffs[:, 9]
                    + _SH_C3[1] * xy * z * coeffs[:, 10]
                    + _SH_C3[2] * y * (4 * zz - xx - yy) * coeffs[:, 11]
                    + _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[:, 12]
                    + _SH_C3[4] * x * (4 * zz - xx - yy) * coeffs[:, 13]
                    + _SH_C3[5] * z * (xx - yy) * coeffs[:, 14]
                    + _SH_C3[6] * x * (xx - 3 * yy) * coeffs[:, 15]
                )
    return (res + 0.5).clamp_min(0.0)


def view_colors(means: torch.Tensor, colors: torch.Tensor, sh_degree: int | None, camera: Camera) -> torch.Tensor:
    """rgb ``[N, 3]`` in the dtype of ``means``: ``colors`` itself, or SH ``[N, K, 3]`` evaluated
    (:func:`eval_sh`) for the direction from the camera centre to each mean."""
    dtype = means.dtype
    if colors.dim() != 3:
        return colors.to(dtype)
    w2c = camera.world_to_camera.to(device=means.device, dtype=dtype)
    rot_cw, t_cw = w2c[:3, :3], w2c[:3, 3]
    campos = -rot_cw.T @ t_cw
    dirs = means - campos
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return eval_sh(colors.to(dtype), int(sh_degree or 0), dirs)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities, all in the autograd graph except ``radii``."""

    means2d: torch.Tensor  # [N, 2] pixels
    conics: torch.Tensor  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    opacities: torch.Tensor  # [N] sigmoid(opacity_logits)
    features: torch.Tensor  # [N, 7] rgb, camera z, camera-space normal (towards the camera)
    depths: torch.Tensor  # [N] camera z (detached copy used for sorting)
    radii: torch.Tensor  # [N] int32 pixels, 0 = culled


def project(
    means: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4] wxyz, any norm
    log_scales: torch.Tensor,  # [N, 3]
    opacity_logits: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, 3] or [N, K, 3]
    sh_degree: int | None,
    camera: Camera,
) -> Projected:
    """EWA-project Gaussians (see the module docstring for the formulas)."""
    dtype = means.dtype
    w2c = camera.world_to_camera.to(device=means.device, dtype=dtype)
    rot_cw, t_cw = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    width, height = int(camera.width), int(camera.height)

    q = normalize_quats(quats.to(dtype))
    ls = clamp_log_scales(log_scales.to(dtype))
    rot = quat_to_rotmat(q)  # [N, 3, 3] world
    rot_c = rot_cw @ rot  # [N, 3, 3] columns = Gaussian axes in camera space
    mc = means @ rot_cw.T + t_cw  # [N, 3]
    z_raw = mc[:, 2]
    in_front = z_raw >= NEAR_PLANE
    z = torch.where(in_front, z_raw, torch.ones_like(z_raw))  # safe value keeps the graph finite
    x, y = mc[:, 0], mc[:, 1]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    tx = z * (x / z).clamp(-lim_xn, lim_xp)
    ty = z * (y / z).clamp(-lim_yn, lim_yp)
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], -1).reshape(-1, 2, 3)
    m = jac @ (rot_c * ls.exp()[:, None, :])  # [N, 2, 3] = J W R S
    cov = m @ m.transpose(1, 2)  # [N, 2, 2]
    a = cov[:, 0, 0] + EPS2D
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + EPS2D
    det = a * c - b * b
    ok = in_front & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + (mid * mid - det).clamp_min(0.1).sqrt()
        radius = torch.ceil(3.0 * lam.sqrt())
        mx, my = means2d[:, 0], means2d[:, 1]
        on_img = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        vis = ok & on_img & (radius > 0)
        radii = torch.where(vis, radius, torch.zeros_like(radius)).to(torch.int32)

    # Normal: the camera-space axis of the smallest scale, flipped to face the camera
    # (the camera centre is the origin, so facing it means n . mean_c <= 0).
    k = ls.detach().argmin(dim=1)
    normal = rot_c.gather(2, k[:, None, None].expand(-1, 3, 1)).squeeze(2)
    flip = ((normal * mc).sum(-1, keepdim=True) > 0).detach()
    normal = torch.where(flip, -normal, normal)

    rgb = view_colors(means, colors, sh_degree, camera)
    features = torch.cat([rgb, z[:, None], normal], dim=-1)
    return Projected(means2d, conics, torch.sigmoid(opacity_logits.to(dtype)), features, z.detach(), radii)


def tile_rects(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Tile ranges ``[N, 4]`` int64 ``(x0, x1, y0, y1)``, half-open, of each Gaussian's square.

    Tile ``tx`` is touched iff :math:`\\lfloor (\\mu_x - r)/16 \\rfloor \\le t_x < \\lceil (\\mu_x + r)/16 \\rceil`
    (clamped to the grid), as in gsplat's ``isect_tiles``. A Gaussian contributes only to
    pixels of its tiles: that is part of the definition of the image, not an approximation.
    """
    tw, th = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    m = means2d.detach().double()
    r = radii.double()
    x0 = torch.floor((m[:, 0] - r) / TILE).clamp(0, tw)
    x1 = torch.ceil((m[:, 0] + r) / TILE).clamp(0, tw)
    y0 = torch.floor((m[:, 1] - r) / TILE).clamp(0, th)
    y1 = torch.ceil((m[:, 1] + r) / TILE).clamp(0, th)
    rect = torch.stack([x0, x1, y0, y1], -1).long()
    rect[radii <= 0] = 0
    return rect
