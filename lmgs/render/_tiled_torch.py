"""Pure-torch per-tile compositor: the speed anchor (docs/field.md) and a fallback.

Same inputs and result as :func:`lmgs.render._cpu.composite`, written the way one would
in eager torch: a Python loop over 16x16 tiles, each tile dense over its own Gaussians
(``[256, n_tile]`` alphas, ``cumprod`` transmittance), autograd for the backward.
"""

from __future__ import annotations

import torch

from lmgs.render._projection import ALPHA_MAX, ALPHA_MIN, N_FEATURES, T_MIN, TILE, tile_rects


def composite(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
              radii: torch.Tensor, depths: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite to ``features [H, W, 7]`` and ``alpha [H, W, 1]``, tile by tile (the arguments
    and their shapes are those of :func:`lmgs.render._cpu.composite`)."""
    dt, dev = means2d.dtype, means2d.device
    tw, th = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    rect = tile_rects(means2d, radii, width, height).to(dev)
    order = torch.argsort(depths, stable=True)
    order = order[radii[order] > 0]
    rect = rect[order]
    ys, xs = torch.meshgrid(torch.arange(TILE, device=dev), torch.arange(TILE, device=dev), indexing="ij")
    rows_out, rows_alpha = [], []
    for ty in range(th):
        tiles_f, tiles_a = [], []
        for tx in range(tw):
            hit = (rect[:, 0] <= tx) & (tx < rect[:, 1]) & (rect[:, 2] <= ty) & (ty < rect[:, 3])
            ids = order[hit]
            if ids.numel() == 0:
                tiles_f.append(torch.zeros(TILE, TILE, N_FEATURES, dtype=dt, device=dev))
                tiles_a.append(torch.zeros(TILE, TILE, 1, dtype=dt, device=dev))
                continue
            px = (xs + tx * TILE).reshape(-1, 1).to(dt) + 0.5
            py = (ys + ty * TILE).reshape(-1, 1).to(dt) + 0.5
            dx = means2d[ids, 0][None] - px  # [256, n]
            dy = means2d[ids, 1][None] - py
            c = conics[ids]
            sigma = 0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) + c[:, 1] * dx * dy
            alpha = (opacities[ids][None] * torch.exp(-sigma)).clamp(max=ALPHA_MAX)
            alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
            t_incl = torch.cumprod(1 - alpha, dim=1)
            alpha = torch.where(t_incl.detach() >= T_MIN, alpha, torch.zeros_like(alpha))
            t_excl = torch.cumprod(torch.cat([alpha.new_ones(alpha.shape[0], 1), 1 - alpha[:, :-1]], 1), 1)
            w = alpha * t_excl
            tiles_f.append((w @ features[ids]).reshape(TILE, TILE, N_FEATURES))
            tiles_a.append(w.sum(1).reshape(TILE, TILE, 1))
        rows_out.append(torch.cat(tiles_f, 1))
        rows_alpha.append(torch.cat(tiles_a, 1))
    feat = torch.cat(rows_out, 0)[:height, :width]
    alpha_out = torch.cat(rows_alpha, 0)[:height, :width]
    return feat, alpha_out
