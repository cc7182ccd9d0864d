"""Losses of the reference model: L1, D-SSIM, and the Geometry Regularizer.

.. math::
    \\mathcal{L}_D = L1(I, I_G) + \\lambda\\,\\mathcal{L}_{D\\text{-}SSIM}(I, I_G) + \\mathcal{L}_{Geo}

    \\mathcal{L}_{Geo} = \\lambda_D L_D(D, \\tilde D) + \\lambda_N \\sum_{i,j} (1 - N_{ij} \\cdot \\tilde N_{ij})

(paper, "Geometry Regularizer" and "Training Detail"; :math:`\\lambda_D = \\lambda_N = 10^{-4}`;
:math:`\\lambda = 0.2` as in 3DGS / TalkingGaussian).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _gauss_window(size: int = 11, sigma: float = 1.5, device=None) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of ``[H, W, 3]`` images in [0, 1] (Gaussian window 11, sigma 1.5, as 3DGS's loss)."""
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None]
    g = _gauss_window(device=img.device)
    c = x.shape[1]
    wx = g.view(1, 1, 1, -1).repeat(c, 1, 1, 1)
    wy = g.view(1, 1, -1, 1).repeat(c, 1, 1, 1)

    def blur(t):
        return F.conv2d(F.conv2d(t, wx, padding=(0, 5), groups=c), wy, padding=(5, 0), groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def photometric(img: torch.Tensor, ref: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """``(1 - λ) L1 + λ (1 - SSIM)``, the 3DGS / TalkingGaussian image loss."""
    return (1 - lambda_dssim) * (img - ref).abs().mean() + lambda_dssim * (1 - ssim(img, ref))


def scale_invariant_depth(depth: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor, gather: bool = True) -> torch.Tensor:
    """Scale-invariant log-depth loss (Eigen et al. 2014) over ``mask``.

    .. math:: L_D = \\frac1n \\sum \\delta^2 - \\frac1{n^2} (\\sum \\delta)^2, \\quad \\delta = \\log D - \\log \\tilde D

    ``gather=False`` sums over the whole image with the mask as weights instead of selecting the
    masked pixels: the same value up to the order of float sums, and nothing read back from the
    device (selecting by a mask, or testing how many pixels it holds, waits for a GPU).
    """
    m = mask & (ref > 0) & (depth > 1e-6)
    if not gather:
        n = m.to(depth.dtype).sum()
        d = torch.where(m, torch.log(torch.where(m, depth, 1.0)) - torch.log(torch.where(m, ref, 1.0)), 0.0)
        mean = d.sum() / n.clamp_min(1.0)
        return torch.where(n >= 2, (d * d).sum() / n.clamp_min(1.0) - mean**2, depth.sum() * 0.0)
    n = m.sum()
    if n < 2:
        return depth.sum() * 0.0
    d = torch.log(depth[m]) - torch.log(ref[m])
    return (d**2).mean() - d.mean() ** 2


def normal_loss(normal: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor, reduce: str = "sum",
                gather: bool = True) -> torch.Tensor:
    """:math:`\\sum_{ij} (1 - N_{ij} \\cdot \\tilde N_{ij})` over ``mask``.

    ``reduce="sum"`` is the paper's formula; ``"mean"`` divides by the masked pixel count (the
    per-pixel normal terms of 2DGS / PGSR), so its weight does not grow with the face's area.
    ``gather=False``: masked sums, as in :func:`scale_invariant_depth`.
    """
    if reduce not in ("sum", "mean"):
        raise ValueError(f"normal_loss: reduce must be 'sum' or 'mean', not {reduce!r}")
    n = F.normalize(normal, dim=-1, eps=1e-6)
    per_pixel = 1.0 - (n * ref).sum(-1)
    if not gather:
        total = torch.where(mask, per_pixel, 0.0).sum()
        return total if reduce == "sum" else total / mask.sum().clamp_min(1).to(total.dtype)
    err = per_pixel[mask]
    if reduce == "sum":
        return err.sum()
    return err.mean() if err.numel() else err.sum()


def geometry(
    depth: torch.Tensor, normal: torch.Tensor, alpha: torch.Tensor, ref_depth: torch.Tensor, ref_normal: torch.Tensor,
    lambda_d: float = 1e-4, lambda_n: float = 1e-4, normal_reduce: str = "sum", gather: bool = True,
) -> torch.Tensor:
    """The Geometry Regularizer on pixels where both the render and the reference have a surface.

    ``depth`` is the alpha-normalised expected depth ``[H, W, 1]``; ``normal`` ``[H, W, 3]``.
    ``gather=False`` computes both terms as masked sums (:func:`scale_invariant_depth`): equal up to
    float rounding, and no read-back on a GPU.
    """
    mask = (alpha[..., 0] > 0.5) & (ref_depth > 0)
    return (lambda_d * scale_invariant_depth(depth[..., 0], ref_depth, mask, gather)
            + lambda_n * normal_loss(normal, ref_normal, mask, normal_reduce, gather))
