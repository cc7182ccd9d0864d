"""Rendering a NeRF baseline: marching with early stop and an occupancy grid changes no pixel it should not.

The reference is :func:`baselines.nerf.render_rays` (every sample, the training renderer)
and hand-made fields whose density is known: a ball of uniform density in the box.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.nerf import NeRFHead, box_hits, march_rays, render_rays

BOX = ([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])


class Ball(NeRFHead):
    """Density ``sigma`` inside the ball of radius 0.5 (normalised box coordinates), 0 outside."""

    def __init__(self, sigma: float = 5.0, occupancy: int = 8):
        super().__init__("adnerf", in_channels=8, window=4, box_min=BOX[0], box_max=BOX[1], hidden=8, occupancy=occupancy)
        self.sigma = sigma

    def forward(self, x, cond):
        u = self.normalize(x)
        inside = u.norm(dim=-1) < 0.5
        rgb = torch.stack([0.5 + 0.4 * u[:, 0], 0.5 + 0.4 * u[:, 1], torch.full_like(u[:, 0], 0.3)], -1)
        return torch.where(inside, self.sigma, 0.0), rgb


def _rays(n: int = 3000, seed: int = 0, spread: float = 1.2):
    g = torch.Generator().manual_seed(seed)
    o = torch.cat([(torch.rand(n, 2, generator=g) * 2 - 1) * spread, torch.full((n, 1), -3.0)], -1)
    d = torch.nn.functional.normalize(torch.cat([torch.randn(n, 2, generator=g) * 0.05, torch.ones(n, 1)], -1), dim=-1)
    near, far, hit = box_hits(o, d, torch.tensor(BOX[0]), torch.tensor(BOX[1]))
    o, d, near, far = o[hit], d[hit], near[hit], far[hit]
    bg = torch.rand(len(o), 3, generator=g)
    return o, d, near, far, bg


def _random_field():
    torch.manual_seed(0)
    f = NeRFHead("adnerf", in_channels=8, window=4, box_min=BOX[0], box_max=BOX[1], hidden=16)
    with torch.no_grad():
        f.mlp.out.bias[0] = 1.0  # dense enough that rays stop part-way
    return f.eval()


@pytest.mark.parametrize("field", [Ball(occupancy=0), _random_field()], ids=["ball", "random-mlp"])
def test_marching_every_sample_equals_the_training_renderer(field):
    o, d, near, far, bg = _rays()
    cond = torch.zeros(32)
    with torch.no_grad():
        ref = render_rays(field, cond, o, d, near, far, bg, 32, field.diag, jitter=False)
    out = march_rays(field, cond, o, d, near, far, bg, 32, field.diag, stop=0.0)
    assert torch.allclose(out, ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("field", [Ball(occupancy=0), _random_field()], ids=["ball", "random-mlp"])
def test_early_stop_changes_a_ray_by_at_most_the_stop_transmittance(field):
    o, d, near, far, bg = _rays()
    cond = torch.zeros(32)
    full = march_rays(field, cond, o, d, near, far, bg, 32, field.diag, stop=0.0)
    fast = march_rays(field, cond, o, d, near, far, bg, 32, field.diag, stop=1e-4)
    err = (fast - full).abs().max()
    assert err <= 1e-4


def test_early_stop_evaluates_fewer_samples_behind_opaque_surfaces():
    ball, seen = Ball(sigma=50.0, occupancy=0), []
    forward = ball.forward
    ball.forward = lambda x, c: (seen.append(len(x)), forward(x, c))[1]
    o, d, near, far, bg = _rays(spread=0.25)  # every ray crosses the ball
    march_rays(ball, torch.zeros(32), o, d, near, far, bg, 32, ball.diag, stop=0.0)
    every = sum(seen)
    seen.clear()
    march_rays(ball, torch.zeros(32), o, d, near, far, bg, 32, ball.diag, stop=1e-4)
    assert every == 32 * len(o)
    assert sum(seen) < 0.75 * every


def test_occupancy_grid_marks_the_ball_and_skips_only_empty_space():
    ball = Ball(occupancy=8)
    frac = ball.update_occupancy(torch.zeros(2, 32), probes=2)
    g = ball.occ_grid
    # cells whose centre is inside the ball are occupied, the box's corners are not
    ax = (torch.arange(8) + 0.5) / 4 - 1
    cx, cy, cz = torch.meshgrid(ax, ax, ax, indexing="ij")
    assert g[(cx**2 + cy**2 + cz**2).sqrt() < 0.5].all()
    assert not g[0, 0, 0] and not g[7, 7, 7] and not g[0, 7, 0]
    assert 0.1 < frac < 0.9
    o, d, near, far, bg = _rays()
    cond = torch.zeros(32)
    skipped = march_rays(ball, cond, o, d, near, far, bg, 32, ball.diag, stop=0.0)
    ball.occ_grid.fill_(True)
    every = march_rays(ball, cond, o, d, near, far, bg, 32, ball.diag, stop=0.0)
    assert torch.equal(skipped, every)


def test_occupancy_grid_without_dilation_would_cut_the_ball():
    # the one-cell dilation is what keeps the boundary: probes alone miss cells the ball only clips
    ball = Ball(occupancy=8)
    ball.update_occupancy(torch.zeros(1, 32), probes=1)
    dilated = ball.occ_grid.clone()
    n = 8
    ax = torch.arange(n, dtype=torch.float32)
    cells = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    gen = torch.Generator().manual_seed(0)
    u = (cells + torch.rand(cells.shape, generator=gen)) * (2.0 / n) - 1.0
    probed = (u.norm(dim=-1) < 0.5).view(n, n, n)
    assert (dilated | probed).equal(dilated) and probed.sum() < dilated.sum()
    o, d, near, far, bg = _rays()
    cond = torch.zeros(32)
    with_dilation = march_rays(ball, cond, o, d, near, far, bg, 32, ball.diag, stop=0.0)
    ball.occ_grid.copy_(probed)
    cut = march_rays(ball, cond, o, d, near, far, bg, 32, ball.diag, stop=0.0)
    ball.occ_grid.fill_(True)
    every = march_rays(ball, cond, o, d, near, far, bg, 32, ball.diag, stop=0.0)
    assert torch.equal(with_dilation, every)
    assert (cut - every).abs().max() > 0.05


def test_trained_ernerf_renders_the_same_with_its_grid(tmp_path):
    # a fitted ER-NeRF (tiny budget): the grid it made from its training conditions changes the
    # render by well under one uint8 level on average
    from lmgs.types import DrivingAudio
    from baselines.protocol import create_method
    from model_fixtures import synthetic_clip

    clip = synthetic_clip()
    m = create_method("ernerf", preset="tiny")
    m.fit(clip, seed=0, workdir=tmp_path, progress=False)
    assert m.model.occ_grid.shape == (m.cfg.occupancy,) * 3
    print("occupied", float(m.model.occ_grid.float().mean()))
    drv = DrivingAudio(audio=clip.audio, w2c=clip.w2c, backgrounds=clip.backgrounds, blink=clip.blink)
    fast = m.render(drv).astype(np.float64)
    m.model.occ_grid.fill_(True)
    full = m.render(drv).astype(np.float64)
    assert np.abs(fast - full).mean() < 0.5


@pytest.mark.parametrize("kind", ["adnerf", "radnerf", "ernerf", "geneface"])
def test_render_forward_equals_the_training_forward(kind):
    # the no-grad path (no concatenation, condition folded into the first bias, in-place ReLU)
    torch.manual_seed(1)
    f = NeRFHead(kind, in_channels=8, window=4, box_min=BOX[0], box_max=BOX[1], hidden=16,
                 n_landmark_coef=6 if kind == "geneface" else 0)
    with torch.no_grad():
        for prm in f.parameters():  # away from the near-transparent start, so every term matters
            prm.add_(torch.randn_like(prm) * 0.3)
    x = torch.rand(500, 3) * 2 - 1
    cond = torch.randn(32)
    with torch.enable_grad():
        s_ref, c_ref = f(x, cond)
    with torch.no_grad():
        s, c = f(x, cond)
    assert torch.allclose(s, s_ref.detach(), atol=1e-5, rtol=1e-5) and torch.allclose(c, c_ref.detach(), atol=1e-6)
    assert s_ref.std() > 1e-3 and c_ref.std() > 1e-3
