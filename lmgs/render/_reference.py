"""Dense pure-torch reference twin of :func:`lmgs.render.rasterize`, for tests only.

Every Gaussian against every pixel: ``O(H W N)`` memory, so keep scenes tiny. Written
independently of the fast path (its own projection and compositing, by matrices and
``cumprod``); only the SH evaluation and the input conventions are shared. Autograd gives
its gradients.
"""

from __future__ import annotations

import torch

from lmgs.render._projection import eval_sh
from lmgs.render.rasterize import RasterResult
from lmgs.types import Camera


def _rotmat(q: torch.Tensor) -> torch.Tensor:
    # R = (w^2 - v.v) I + 2 v v^T + 2 w [v]_x, for a unit quaternion (w, v)
    w, v = q[:, 0], q[:, 1:]
    eye = torch.eye(3, dtype=q.dtype, device=q.device).expand(q.shape[0], 3, 3)
    cross = torch.zeros(q.shape[0], 3, 3, dtype=q.dtype, device=q.device)
    cross[:, 0, 1], cross[:, 0, 2] = -v[:, 2], v[:, 1]
    cross[:, 1, 0], cross[:, 1, 2] = v[:, 2], -v[:, 0]
    cross[:, 2, 0], cross[:, 2, 1] = -v[:, 1], v[:, 0]
    return (w * w - (v * v).sum(1))[:, None, None] * eye + 2 * v[:, :, None] * v[:, None, :] + 2 * w[:, None, None] * cross


def _rasterize(
    means: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4]
    log_scales: torch.Tensor,  # [N, 3]
    opacity_logits: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, 3] or [N, K, 3]
    camera: Camera,
    background: torch.Tensor | None = None,  # [3]
    *,
    sh_degree: int | None = None,
) -> RasterResult:
    """Dense twin of :func:`lmgs.render.rasterize` (same conventions, same result)."""
    n = means.shape[0]
    dt, dev = means.dtype, means.device
    width, height = int(camera.width), int(camera.height)
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    w2c = camera.world_to_camera.to(device=dev, dtype=dt)
    rot_cw, t_cw = w2c[:3, :3], w2c[:3, 3]

    qn = quats.norm(dim=1, keepdim=True)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dt, device=dev).expand(n, 4)
    q = torch.where(qn > 1e-12, quats / qn.clamp_min(1e-12), ident)
    ls = log_scales.clamp(-30.0, 10.0)
    rot = rot_cw @ _rotmat(q)  # camera-space axes
    sigma3 = rot @ torch.diag_embed(ls.exp() ** 2) @ rot.transpose(1, 2)

    pc = (rot_cw @ means.T).T + t_cw
    zr = pc[:, 2]
    front = zr >= 0.01
    z = torch.where(front, zr, torch.ones_like(zr))
    u = fx * pc[:, 0] / z + cx
    v = fy * pc[:, 1] / z + cy
    limx = (-(cx / fx + 0.15 * width / fx), (width - cx) / fx + 0.15 * width / fx)
    limy = (-(cy / fy + 0.15 * height / fy), (height - cy) / fy + 0.15 * height / fy)
    xc = (pc[:, 0] / z).clamp(*limx)
    yc = (pc[:, 1] / z).clamp(*limy)
    jac = torch.zeros(n, 2, 3, dtype=dt, device=dev)
    jac[:, 0, 0] = fx / z
    jac[:, 0, 2] = -fx * xc / z
    jac[:, 1, 1] = fy / z
    jac[:, 1, 2] = -fy * yc / z
    cov2 = jac @ sigma3 @ jac.transpose(1, 2) + 0.3 * torch.eye(2, dtype=dt, device=dev)
    det = torch.linalg.det(cov2) if n else torch.zeros(0, dtype=dt, device=dev)
    ok = front & (det > 0)
    cov2 = torch.where(ok[:, None, None], cov2, torch.eye(2, dtype=dt, device=dev).expand(n, 2, 2))
    prec = torch.linalg.inv(cov2) if n else cov2

    with torch.no_grad():
        # the conventional closed form of 3DGS (not the exact largest eigenvalue)
        mid = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
        lam = mid + (mid * mid - det).clamp_min(0.1).sqrt()
        r = torch.ceil(3 * lam.sqrt())
        on = (u + r > 0) & (u - r < width) & (v + r > 0) & (v - r < height)
        radii = torch.where(ok & on & (r > 0), r, torch.zeros_like(r)).to(torch.int32)
        vis = radii > 0

    # pixels and their tiles
    ys, xs = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev), indexing="ij")
    pix = torch.stack([xs.flatten() + 0.5, ys.flatten() + 0.5], -1).to(dt)  # [P, 2]
    tx, ty = (xs.flatten() // 16)[:, None], (ys.flatten() // 16)[:, None]
    tw, th = (width + 15) // 16, (height + 15) // 16
    with torch.no_grad():
        rr = radii.double()
        ud, vd = u.detach().double(), v.detach().double()
        x0 = torch.floor((ud - rr) / 16).clamp(0, tw)
        x1 = torch.ceil((ud + rr) / 16).clamp(0, tw)
        y0 = torch.floor((vd - rr) / 16).clamp(0, th)
        y1 = torch.ceil((vd + rr) / 16).clamp(0, th)
        in_tile = (tx >= x0) & (tx < x1) & (ty >= y0) & (ty < y1) & vis  # [P, N]

    means2d = torch.stack([u, v], -1)  # [N, 2]
    d = means2d[None, :, :] - pix[:, None, :]  # [P, N, 2]
    power = 0.5 * torch.einsum("pni,nij,pnj->pn", d, prec, d)
    raw = torch.sigmoid(opacity_logits)[None, :] * torch.exp(-power)
    alpha = raw.clamp(max=0.99)
    keep = in_tile & (power >= 0) & (alpha >= 1.0 / 255.0)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))

    order = torch.argsort(z.detach(), stable=True)
    alpha = alpha[:, order]
    t_incl = torch.cumprod(1 - alpha, dim=1)
    # stop before the first Gaussian that would take T below 1e-4 (T is non-increasing)
    alpha = torch.where(t_incl.detach() >= 1e-4, alpha, torch.zeros_like(alpha))
    one = torch.ones(alpha.shape[0], 1, dtype=dt, device=dev)
    t_excl = torch.cumprod(torch.cat([one, 1 - alpha[:, :-1]], 1), 1)
    w = alpha * t_excl  # [P, N] sorted

    if colors.dim() == 3:
        campos = -rot_cw.T @ t_cw
        dirs = means - campos
        dirs = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)
        k = colors.shape[1]
        deg = sh_degree if sh_degree is not None else int(round(k**0.5)) - 1
        rgb = eval_sh(colors, deg, dirs)
    else:
        rgb = colors
    axis = ls.detach().argmin(1)
    nrm = rot[torch.arange(n, device=dev), :, axis]  # [N, 3]
    nrm = torch.where(((nrm * pc).sum(1, keepdim=True) > 0).detach(), -nrm, nrm)
    feats = torch.cat([rgb, z[:, None], nrm], 1)[order]  # [N, 7]
    img = (w @ feats).reshape(height, width, 7)
    a = w.sum(1).reshape(height, width, 1)
    out_rgb = img[..., :3]
    if background is not None:
        t_fin = t_excl[:, -1:] * (1 - alpha[:, -1:]) if n else torch.ones_like(a.reshape(-1, 1))
        out_rgb = out_rgb + t_fin.reshape(height, width, 1) * background
    return RasterResult(out_rgb, a, img[..., 3:4], img[..., 4:7], radii, vis, means2d)
