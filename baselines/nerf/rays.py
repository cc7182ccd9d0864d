"""Rays of the NeRF baselines: camera rays, the head box's slab test, and volume rendering.

Volume rendering (Mildenhall et al., 2020), per ray with :math:`S` stratified samples
between the entry and exit of the box:

.. math::

    \\alpha_k = 1 - e^{-\\sigma_k \\delta_k}, \\quad w_k = \\alpha_k \\prod_{j<k} (1 - \\alpha_j), \\quad
    C = \\sum_k w_k c_k + \\big(1 - \\textstyle\\sum_k w_k\\big) B

:func:`render_rays` takes every sample (training, with autograd); :func:`march_rays` marches
the same samples in groups for rendering a trained field, stopping a ray once its
transmittance is below :data:`STOP_TRANSMITTANCE` and skipping samples in the empty cells of
the field's occupancy grid when it has one.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F


def camera_rays(w2c: np.ndarray, focal: float, cx: float, cy: float, height: int, width: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space origins and unit directions of every pixel centre, ``[H*W, 3]`` each."""
    c2w = torch.from_numpy(np.linalg.inv(np.asarray(w2c, np.float64)).astype(np.float32)).to(device)
    v, u = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    d = torch.stack([(u.float() + 0.5 - cx) / focal, (v.float() + 0.5 - cy) / focal, torch.ones_like(u, dtype=torch.float32)], -1)
    d = F.normalize(d.reshape(-1, 3) @ c2w[:3, :3].T, dim=-1)
    return c2w[:3, 3].expand_as(d), d


def box_hits(origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab test: entry and exit distances ``[R]`` and a hit mask ``[R]``."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0, t1 = (lo - origins) * inv, (hi - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, far, far > near + 1e-6


def render_rays(field, cond, origins, dirs, near, far, background, samples: int, diag: float, jitter: bool) -> torch.Tensor:
    """Composite ``S`` samples per ray between ``near`` and ``far`` over ``background`` ``[R, 3]``.

    :math:`\\delta_k` is measured in units of ``diag / S`` (the sample spacing of a ray
    crossing the whole box), so a raw density of about 2 is opaque whatever the scene scale.
    """
    R = origins.shape[0]
    k = torch.arange(samples, device=origins.device, dtype=origins.dtype)
    off = torch.rand(R, samples, device=origins.device) if jitter else torch.full((R, samples), 0.5, device=origins.device)
    span = (far - near)[:, None]
    t = near[:, None] + span * (k + off) / samples  # [R, S]
    pts = origins[:, None] + dirs[:, None] * t[..., None]
    sigma, rgb = field(pts.reshape(-1, 3), cond)
    sigma, rgb = sigma.view(R, samples), rgb.view(R, samples, 3)
    delta = span / samples / (diag / samples)
    alpha = 1 - torch.exp(-sigma * delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1] + 1e-10], 1), 1)
    w = alpha * trans
    return (w[..., None] * rgb).sum(1) + (1 - w.sum(1, keepdim=True)) * background


STOP_TRANSMITTANCE = 1e-4
"""A marched ray stops when its transmittance falls below this (:func:`march_rays`)."""


@torch.no_grad()
def march_rays(field, cond, origins, dirs, near, far, background, samples: int, diag: float, group: int = 8,
               stop: float = STOP_TRANSMITTANCE) -> torch.Tensor:
    """:func:`render_rays` without jitter, for rendering: the same samples and compositing.

    Samples are taken ``group`` at a time along every ray; a ray whose transmittance fell below
    ``stop`` takes no more (``stop=0``: every sample, equal to :func:`render_rays`). Samples in
    cells the field's occupancy grid marks empty (``field.occupied``, when it has one) are not
    evaluated and count as empty.
    """
    R = origins.shape[0]
    dev, dt = origins.device, origins.dtype
    span = far - near
    delta = (span / samples / (diag / samples))[:, None]
    color = torch.zeros(R, 3, device=dev, dtype=dt)
    trans = torch.ones(R, device=dev, dtype=dt)
    alive = torch.arange(R, device=dev)
    occupied = getattr(field, "occupied", None)
    for k0 in range(0, samples, group):
        if stop > 0:
            alive = alive[trans[alive] >= stop]
        if len(alive) == 0:
            break
        k = torch.arange(k0, min(k0 + group, samples), device=dev, dtype=dt)
        t = near[alive, None] + span[alive, None] * (k + 0.5) / samples  # [A, G]
        pts = origins[alive, None] + dirs[alive, None] * t[..., None]
        A, G = t.shape
        sigma = torch.zeros(A * G, device=dev, dtype=dt)
        rgb = torch.zeros(A * G, 3, device=dev, dtype=dt)
        flat = pts.reshape(-1, 3)
        keep = occupied(flat) if occupied is not None else None
        if keep is None:
            sigma, rgb = field(flat, cond)
        elif bool(keep.any()):
            sigma[keep], rgb[keep] = field(flat[keep], cond)
        alpha = 1 - torch.exp(-sigma.view(A, G) * delta[alive])
        # transmittance before each sample of the group, continuing from the earlier groups
        tr = trans[alive, None] * torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1] + 1e-10], 1), 1)
        color[alive] += ((alpha * tr)[..., None] * rgb.view(A, G, 3)).sum(1)
        trans[alive] = tr[:, -1] * (1 - alpha[:, -1] + 1e-10)
    return color + trans[:, None] * background
