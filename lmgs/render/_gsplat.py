"""CUDA path through gsplat (``pip install 'lmgs[cuda]'``); used only for CUDA tensors.

gsplat composites arbitrary channels, so the same seven per-Gaussian features as the CPU
path (rgb, camera z, camera-space normal, from :func:`lmgs.render._projection.project`)
are passed as ``colors`` and gsplat's own projection and tile kernels do the rest, with
the 3DGS settings (``eps2d=0.3``, ``near_plane=0.01``, 16 px tiles, classic mode).
Differences to the CPU path: gsplat caps alpha at 0.999, not 0.99. ``means2d`` is a view of
gsplat's batched ``[1, N, 2]`` tensor; its ``.grad`` (what densification reads) is filled by a
hook on that tensor.
"""

from __future__ import annotations

import functools

import torch

from lmgs.render._projection import EPS2D, NEAR_PLANE, TILE, project
from lmgs.types import Camera


def rasterize_gsplat(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacity_logits: torch.Tensor,
                     colors: torch.Tensor, sh_degree: int | None,
                     camera: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Return ``features [H, W, 7]``, ``alpha [H, W, 1]``, ``means2d [N, 2]``, ``radii [N]`` (the
    Gaussians' arguments and their shapes are those of :func:`lmgs.render.rasterize`)."""
    from gsplat import rasterization

    p = project(means, quats, log_scales, opacity_logits, colors, sh_degree, camera)
    dev, dt = means.device, means.dtype
    K = torch.tensor(
        [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]], device=dev, dtype=dt
    )
    img, alpha, meta = rasterization(
        means,
        quats,
        torch.exp(log_scales.clamp(-30.0, 10.0)),
        torch.sigmoid(opacity_logits),
        p.features,
        camera.world_to_camera.to(device=dev, dtype=dt)[None],
        K[None],
        int(camera.width),
        int(camera.height),
        near_plane=NEAR_PLANE,
        eps2d=EPS2D,
        tile_size=TILE,
        packed=False,
        rasterize_mode="classic",
        render_mode="RGB",
    )
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.3 returns per-axis radii
        radii = radii.max(dim=-1).values
    batched = meta["means2d"]  # [1, N, 2]: the tensor the tile rasterizer read
    means2d = batched[0]
    if batched.requires_grad:
        # The loss reaches ``batched``, not this view of it, so a retained gradient on the view
        # would stay None and densification would never see one: hand the batch's gradient on.
        batched.register_hook(functools.partial(_hand_on, means2d))
    return img[0], alpha[0], means2d, radii.to(torch.int32)


def _hand_on(view: torch.Tensor, grad: torch.Tensor) -> None:
    """Backward hook: the ``[1, N, 2]`` gradient of gsplat's ``means2d`` as ``view.grad`` ``[N, 2]``."""
    view.grad = grad[0].detach()
