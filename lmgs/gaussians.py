"""Gaussian parameters of one branch (face or mouth): plain tensors, no optimiser inside.

Parameters are stored raw (log-scales, opacity logits, colour logits); activations are
applied where they are used (:meth:`GaussianSet.colors`). Densification edits live apart,
in :mod:`lmgs.strategy`, in the manner of gsplat.
"""

from __future__ import annotations

import math

import torch
from torch import nn

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "color_logits")


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


class GaussianSet(nn.Module):
    """One branch's canonical Gaussians.

    Attributes (``nn.Parameter``):
        means: ``[N, 3]`` world positions.
        quats: ``[N, 4]`` rotations (w, x, y, z), unnormalised.
        log_scales: ``[N, 3]`` log standard deviations.
        opacity_logits: ``[N]`` opacity before the sigmoid.
        color_logits: ``[N, 3]`` RGB before the sigmoid (view-independent colour: talking
            heads are seen from one camera, and SH degree 0 keeps the model small).
    """

    def __init__(self, means: torch.Tensor, colors: torch.Tensor, scale: float | torch.Tensor, opacity: float = 0.5):
        super().__init__()
        n = means.shape[0]
        dev = means.device
        scales = torch.as_tensor(scale, dtype=torch.float32, device=dev).expand(n).clone() if not torch.is_tensor(scale) or scale.ndim == 0 else scale
        quats = torch.zeros(n, 4, device=dev)
        quats[:, 0] = 1.0
        self.means = nn.Parameter(means.float().clone())
        self.quats = nn.Parameter(quats)
        self.log_scales = nn.Parameter(torch.log(scales.float().clamp_min(1e-6))[:, None].repeat(1, 3))
        self.opacity_logits = nn.Parameter(torch.full((n,), _logit(opacity), device=dev))
        self.color_logits = nn.Parameter(torch.logit(colors.float().clamp(0.02, 0.98)))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def colors(self) -> torch.Tensor:
        return torch.sigmoid(self.color_logits)

    def params(self) -> dict[str, nn.Parameter]:
        return {k: getattr(self, k) for k in PARAM_NAMES}

    @staticmethod
    def empty(device: torch.device | str = "cpu") -> "GaussianSet":
        return GaussianSet(torch.zeros(0, 3, device=device), torch.zeros(0, 3, device=device), 0.01)

    def load_tensors(self, state: dict[str, torch.Tensor]) -> None:
        """Replace every parameter by the tensors of ``state`` (sizes may differ)."""
        for k in PARAM_NAMES:
            setattr(self, k, nn.Parameter(state[k].detach().clone()))


def knn_scale(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Initial scale per point: the mean distance to its ``k`` nearest neighbours (3DGS init)."""
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, device=points.device)
    out = torch.empty(n, device=points.device)
    for s in range(0, n, 2048):
        d = torch.cdist(points[s : s + 2048], points)
        d[torch.arange(d.shape[0]), torch.arange(s, s + d.shape[0])] = float("inf")
        out[s : s + 2048] = d.topk(min(k, n - 1), largest=False).values.mean(dim=1)
    return out.clamp(1e-4, 1.0)
