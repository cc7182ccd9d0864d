"""Densification and pruning, apart from the model (in the manner of gsplat's ``Strategy``).

A :class:`Strategy` holds hyper-parameters; :func:`initialize_state` gives a plain dict of
running statistics; :func:`step_post_backward` reads the 2D positional gradients of the
last render and edits the Gaussians and the optimiser state with the free functions
:func:`duplicate`, :func:`split` and :func:`remove`.

The Gaussian budget caps growth, so a model is never larger than its scene needs
(:func:`budget_from_face_area`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from lmgs.gaussians import PARAM_NAMES, GaussianSet


@dataclass(frozen=True)
class Strategy:
    """Adaptive density control (3DGS defaults, scaled to short CPU schedules).

    Attributes:
        grad_threshold: mean 2D positional gradient (pixels) above which a Gaussian grows.
        grow_scale: Gaussians whose largest scale is below this fraction of the scene
            extent are duplicated; larger ones are split in two.
        prune_opacity: Gaussians below this opacity are removed.
        start, stop, every: densify between these steps, every ``every`` steps.
        reset_every: opacity reset period (0: never).
        budget: the most Gaussians this branch may hold.
    """

    grad_threshold: float = 2e-4
    grow_scale: float = 0.01
    prune_opacity: float = 0.005
    start: int = 100
    stop: int = 1500
    every: int = 100
    reset_every: int = 0
    budget: int = 4000


def budget_from_face_area(face_area_px: float, density: float = 0.12, lo: int = 500, hi: int = 50000) -> int:
    """Gaussians a face needs: ``density`` per pixel of face area, clamped to ``[lo, hi]``.

    ``density`` is the knee found by ``lmgs-eval capacity`` (the quick preset's: astronaut's;
    a subject whose knee lies elsewhere carries its own).
    """
    return int(min(hi, max(lo, round(face_area_px * density))))


def initialize_state(n: int, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    return {"grad2d": torch.zeros(n, device=device), "count": torch.zeros(n, device=device)}


@torch.no_grad()
def accumulate(state: dict[str, torch.Tensor], means2d: torch.Tensor, visible: torch.Tensor, width: int, height: int) -> None:
    """Add the norm of this render's 2D positional gradient (in NDC-like units) to the state."""
    if means2d.grad is None:
        return
    g = means2d.grad.detach().clone()
    g[:, 0] *= width / 2.0
    g[:, 1] *= height / 2.0
    norm = g.norm(dim=-1)
    # adding zero where not visible (the same sums as updating the visible rows alone, which on a
    # GPU would first read back how many there are)
    visible = visible.to(norm.device)
    state["grad2d"] += torch.where(visible, norm, 0.0)
    state["count"] += visible.to(state["count"].dtype)


def _swap_params(opt: torch.optim.Optimizer, gs: GaussianSet, param_fn, moment_fn) -> None:
    """Replace each parameter of ``gs`` by ``Parameter(param_fn(name, tensor))`` in the set and in
    ``opt``, its Adam moments by ``moment_fn(moment)`` (a parameter without state keeps none)."""
    for name in PARAM_NAMES:
        old = getattr(gs, name)
        new = torch.nn.Parameter(param_fn(name, old.detach()))
        for group in opt.param_groups:
            for k, p in enumerate(group["params"]):
                if p is old:
                    st = opt.state.pop(old, None)
                    if st:
                        for key in ("exp_avg", "exp_avg_sq"):
                            if key in st:
                                st[key] = moment_fn(st[key])
                        opt.state[new] = st
                    group["params"][k] = new
        setattr(gs, name, new)


@torch.no_grad()
def remove(gs: GaussianSet, opt: torch.optim.Optimizer, state: dict, mask: torch.Tensor) -> None:
    keep = ~mask
    _swap_params(opt, gs, lambda name, t: t[keep], lambda m: m[keep])
    for k in state:
        state[k] = state[k][keep]


@torch.no_grad()
def duplicate(gs: GaussianSet, opt: torch.optim.Optimizer, state: dict, mask: torch.Tensor) -> None:
    """Append an exact copy of each selected Gaussian (Adam moments of the copies start at 0)."""
    idx = mask.nonzero().squeeze(1)
    _copy_rows(gs, opt, idx, jitter=None)
    for k in state:
        state[k] = torch.cat([state[k], torch.zeros(len(idx), device=state[k].device)])


@torch.no_grad()
def split(gs: GaussianSet, opt: torch.optim.Optimizer, state: dict, mask: torch.Tensor) -> None:
    """Replace each selected Gaussian by two, sampled from it, with scales divided by 1.6."""
    idx = mask.nonzero().squeeze(1)
    if len(idx) == 0:
        return
    scales = gs.log_scales.detach()[idx].exp()
    g = torch.Generator(device="cpu").manual_seed(int(len(gs)) * 7919 + int(idx.sum()))
    offset = torch.randn(len(idx), 3, generator=g).to(scales) * scales
    q = torch.nn.functional.normalize(gs.quats.detach()[idx], dim=-1)
    offset = _rotate(q, offset)
    with torch.no_grad():
        gs.log_scales.data[idx] -= torch.log(torch.tensor(1.6))
        gs.means.data[idx] += offset
    _copy_rows(gs, opt, idx, jitter=-2 * offset)
    for k in state:
        state[k] = torch.cat([state[k], torch.zeros(len(idx), device=state[k].device)])


def _copy_rows(gs: GaussianSet, opt: torch.optim.Optimizer, idx: torch.Tensor, jitter: torch.Tensor | None) -> None:
    """Append copies of rows ``idx`` (the means moved by ``jitter``), their Adam moments zero."""

    def grown(name: str, t: torch.Tensor) -> torch.Tensor:
        rows = t[idx].clone()
        if name == "means" and jitter is not None:
            rows = rows + jitter
        return torch.cat([t, rows])

    _swap_params(opt, gs, grown, lambda m: torch.cat([m, torch.zeros_like(m[idx])]))


def _rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    w, xyz = q[:, :1], q[:, 1:]
    t = 2.0 * torch.cross(xyz, v, dim=-1)
    return v + w * t + torch.cross(xyz, t, dim=-1)


@torch.no_grad()
def step_post_backward(
    strategy: Strategy, gs: GaussianSet, opt: torch.optim.Optimizer, state: dict, step: int, extent: float
) -> dict[str, int]:
    """Grow, split and prune at the strategy's schedule; returns counts of what changed."""
    out = {"duplicated": 0, "split": 0, "pruned": 0}
    if not (strategy.start <= step < strategy.stop) or step % strategy.every:
        return out
    avg = state["grad2d"] / state["count"].clamp_min(1)
    big = gs.log_scales.detach().exp().max(dim=1).values > strategy.grow_scale * extent
    grow = avg > strategy.grad_threshold
    room = max(0, strategy.budget - len(gs))
    if room and grow.any():
        # Largest gradients first, within the budget.
        cand = grow.nonzero().squeeze(1)
        cand = cand[avg[cand].argsort(descending=True)][:room]
        sel = torch.zeros_like(grow)
        sel[cand] = True
        dup, spl = sel & ~big, sel & big
        out["duplicated"] = int(dup.sum())
        out["split"] = int(spl.sum())
        n0 = len(gs)
        duplicate(gs, opt, state, dup)
        spl = torch.cat([spl, torch.zeros(len(gs) - n0, dtype=torch.bool, device=spl.device)])
        split(gs, opt, state, spl)
    low = torch.sigmoid(gs.opacity_logits.detach()) < strategy.prune_opacity
    if low.any() and low.sum() < len(gs):
        out["pruned"] = int(low.sum())
        remove(gs, opt, state, low)
    state["grad2d"].zero_()
    state["count"].zero_()
    return out
