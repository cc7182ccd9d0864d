"""One optimisation step of a Gaussian model, shared by :func:`lmgs.train.fit` and the 3DGS baselines.

The Gaussians train with Adam, one parameter group per parameter kind at the schedule's rate
(:func:`gaussian_adam`); the networks (audio, deformation) with AdamW (:func:`network_adamw`),
stepped only in the dynamic stage. After each backward pass the quaternions are renormalised
(:func:`optimise`) and densification reads the render's 2D positional gradients
(:func:`densify`, over :mod:`lmgs.strategy`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch

from lmgs.gaussians import PARAM_NAMES, GaussianSet
from lmgs.strategy import Strategy, accumulate, step_post_backward


def gaussian_adam(branches: Iterable[GaussianSet], t) -> torch.optim.Adam:
    """Adam over the parameters of ``branches`` (a group per parameter, branch by branch, named as
    the parameter) at the learning rates of ``t`` (a :class:`~lmgs.presets.TrainConfig`)."""
    rates = {"means": t.lr_means, "quats": t.lr_quats, "log_scales": t.lr_scales, "opacity_logits": t.lr_opacity,
             "color_logits": t.lr_colors}
    groups = [{"params": [getattr(gs, name)], "lr": rates[name], "name": name} for gs in branches for name in PARAM_NAMES]
    return torch.optim.Adam(groups, eps=1e-15, fused=fused_on_gpu(g["params"][0] for g in groups))


def network_adamw(modules: Iterable[torch.nn.Module], lr: float) -> torch.optim.AdamW:
    """AdamW (weight decay 1e-4) over the parameters of ``modules``, in order."""
    params = [p for m in modules for p in m.parameters()]
    return torch.optim.AdamW(params, lr=lr, weight_decay=1e-4, fused=fused_on_gpu(params))


def fused_on_gpu(params: Iterable[torch.Tensor]) -> bool | None:
    """True (torch's fused kernel: one launch per parameter group instead of one per operation per
    tensor) when every parameter is on a GPU; else None, torch's default (the CPU keeps its results
    of the per-tensor loop)."""
    params = list(params)
    return True if params and all(p.is_cuda for p in params) else None


def optimise(loss: torch.Tensor, g_opt: torch.optim.Optimizer, n_opt: torch.optim.Optimizer, nets: bool,
             branches: Iterable[GaussianSet]) -> None:
    """Backward through ``loss``, a step of the Gaussians' optimiser (and of the networks' when
    ``nets``: the dynamic stage), then the quaternions of ``branches`` renormalised."""
    g_opt.zero_grad(set_to_none=True)
    n_opt.zero_grad(set_to_none=True)
    loss.backward()
    g_opt.step()
    if nets:
        n_opt.step()
    with torch.no_grad():
        for gs in branches:
            gs.quats.data = torch.nn.functional.normalize(gs.quats.data, dim=-1)


def densify(branches: Sequence[tuple[Strategy, GaussianSet, dict, torch.Tensor, torch.Tensor]], g_opt: torch.optim.Optimizer,
            step: int, extent: float, width: int, height: int) -> None:
    """Densification after step ``step`` (1-based): for each ``(strategy, gaussians, state, means2d,
    visible)`` the render's 2D gradients are accumulated, then each branch grows, splits and prunes
    on its strategy's schedule."""
    for _, _, state, means2d, visible in branches:
        accumulate(state, means2d, visible, width, height)
    for strategy, gs, state, _, _ in branches:
        step_post_backward(strategy, gs, g_opt, state, step, extent)
