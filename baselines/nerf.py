"""NeRF family: AD-NeRF, RAD-NeRF, ER-NeRF and GeneFace, simplified onto one small volume renderer.

All four share :class:`NeRFHead` (a conditioned radiance field) and :func:`render_rays`
(volume rendering inside the head's bounding box, composited over the frame's background,
as the field's protocol does with the torso over ``bc.jpg``). They differ only where the
originals differ:

* ``adnerf`` (Guo et al., ICCV 2021): an MLP on the positional encoding of the point,
  with the smoothed per-frame audio feature concatenated to its input.
* ``radnerf`` (Tang et al., 2022): a decomposed audio-spatial encoding: multi-resolution
  dense 3D grids for the point and a 2D grid indexed by a learned 2D projection of the
  audio feature; no region attention.
* ``ernerf`` (Li et al., ICCV 2023): the tri-plane hash encoder of :mod:`lmgs` for the
  point and region attention (channel gates from the spatial feature) over the audio.
* ``geneface`` (Ye et al., ICLR 2023): audio -> 68 3D landmarks (the project's per-subject
  predictor) -> an MLP NeRF conditioned on the landmarks (their whitened PCA coefficients).

Volume rendering (Mildenhall et al., 2020), per ray with :math:`S` stratified samples
between the entry and exit of the box:

.. math::

    \\alpha_k = 1 - e^{-\\sigma_k \\delta_k}, \\quad w_k = \\alpha_k \\prod_{j<k} (1 - \\alpha_j), \\quad
    C = \\sum_k w_k c_k + \\big(1 - \\textstyle\\sum_k w_k\\big) B

Rendering a trained field (no autograd) marches the same samples in groups along each ray
(:func:`march_rays`): a ray stops once its transmittance is below ``1e-4`` (what it would
still add is below a 40th of a uint8 level), and ER-NeRF and RAD-NeRF skip samples in cells
of their occupancy grid (:meth:`NeRFHead.update_occupancy`) where no training condition put
density, as the originals' occupancy-grid ray marching does. AD-NeRF and GeneFace have no
occupancy grid (neither original does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from baselines.common import (
    Adapter,
    audio_windows,
    driving_background,
    driving_w2c,
    head_box,
    landmark_targets,
    mean_background,
    n_frames_of,
    progress_bar,
    seed_all,
    to_u8,
)
from baselines.protocol import register
from lmgs.audio import AudioNet
from lmgs.config import AudioConfig, TriplaneConfig
from lmgs.encoders import TriplaneEncoder
from lmgs.landmarks import LandmarkPredictor, fit_landmark_predictor

STANDINS = ("audio front end: the project's log-mel windows (DeepSpeech / HuBERT features cannot be had offline)",)


@dataclass(frozen=True)
class NeRFBudget:
    """Training and rendering budget of a NeRF baseline.

    Attributes:
        steps: optimiser steps (one training frame per step).
        rays: random rays per step (drawn among the rays that cross the head box).
        head_share: share of those rays drawn from the pixels where the frame differs from its
            background (the head; AD-NeRF likewise samples the head region more): without it, a
            head that covers a small part of the box lets the density collapse to zero everywhere.
        samples: stratified samples per ray.
        hidden: width of the field MLP.
        lr: Adam learning rate.
        landmark_steps: steps of the audio-to-landmark predictor (GeneFace only).
        chunk: rays per chunk when rendering full frames.
        occupancy: cells per side of the occupancy grid that rendering skips empty space with
            (ER-NeRF and RAD-NeRF only; 0: none).
    """

    steps: int = 1500
    rays: int = 1024
    head_share: float = 0.75
    samples: int = 32
    hidden: int = 64
    lr: float = 5e-3
    landmark_steps: int = 300
    chunk: int = 2048
    occupancy: int = 32

    @classmethod
    def tiny(cls) -> "NeRFBudget":
        return cls(steps=200, rays=384, samples=24, hidden=32, lr=1e-2, landmark_steps=40)

    @classmethod
    def quick(cls) -> "NeRFBudget":
        return cls()


# ----------------------------------------------------------------------------- rays
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


OCCUPANCY_METHODS = ("ernerf", "radnerf")
"""The flavours whose originals march rays through an occupancy grid."""
OCCUPANCY_FRAMES = 32
"""Training conditions the occupancy grid is made from (evenly spread over the clip)."""

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


# ----------------------------------------------------------------------------- encoders
class PositionalEncoding(nn.Module):
    """:math:`\\gamma(x) = [x, \\sin(2^l \\pi x), \\cos(2^l \\pi x)]_{l<L}` (NeRF / AD-NeRF)."""

    def __init__(self, n_freqs: int = 6):
        super().__init__()
        self.register_buffer("freqs", (2.0 ** torch.arange(n_freqs)) * math.pi, persistent=False)
        self.out_dim = 3 + 6 * n_freqs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xf = x[..., None] * self.freqs  # [N, 3, L]
        return torch.cat([x, xf.sin().flatten(1), xf.cos().flatten(1)], -1)


class DenseGrids3D(nn.Module):
    """Multi-resolution dense 3D feature grids, trilinear (RAD-NeRF's spatial grid, unhashed)."""

    def __init__(self, resolutions=(8, 16, 32), n_features: int = 4):
        super().__init__()
        self.grids = nn.ParameterList([nn.Parameter(torch.empty(1, n_features, r, r, r).uniform_(-1e-2, 1e-2)) for r in resolutions])
        self.out_dim = n_features * len(resolutions)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x in [-1, 1]
        g = x.view(1, -1, 1, 1, 3)
        return torch.cat([F.grid_sample(p, g, align_corners=True).view(p.shape[1], -1).T for p in self.grids], -1)


class FieldMLP(nn.Module):
    """``[feature] -> (sigma >= 0, rgb in [0, 1])``; starts nearly transparent."""

    def __init__(self, d_in: int, hidden: int, n_layers: int = 3):
        super().__init__()
        layers, d = [], d_in
        for _ in range(n_layers):
            layers += [nn.Linear(d, hidden), nn.ReLU()]
            d = hidden
        self.body = nn.Sequential(*layers)
        self.out = nn.Linear(d, 4)
        with torch.no_grad():
            self.out.bias[0] = -2.0

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        o = self.out(self.body(h))
        return F.softplus(o[:, 0]), torch.sigmoid(o[:, 1:])

    @torch.no_grad()
    def forward_parts(self, parts: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward(cat(parts, -1))`` for rendering, without building the concatenation: a 1-D part
        (the same for every point, e.g. the frame's audio condition) folds into the first bias;
        ReLUs act in place. Equal to :meth:`forward` up to float rounding."""
        layers = [m for m in self.body if isinstance(m, nn.Linear)]
        w, bias, h, k = layers[0].weight, layers[0].bias, None, 0
        for part in parts:
            wp = w[:, k : k + part.shape[-1]]
            k += part.shape[-1]
            if part.dim() == 1:
                bias = bias + wp @ part
            else:
                h = part @ wp.T if h is None else h.addmm_(part, wp.T)
        h = h.add_(bias).relu_()
        for lin in layers[1:]:
            h = F.linear(h, lin.weight, lin.bias).relu_()
        o = self.out(h)
        return F.softplus(o[:, 0]), torch.sigmoid(o[:, 1:])


class NeRFHead(nn.Module):
    """A radiance field conditioned per frame, in one of four flavours (see the module doc).

    Args:
        kind: ``adnerf``, ``radnerf``, ``ernerf`` or ``geneface``.
        in_channels, window: shape of the audio windows ``[W, C]``.
        box_min, box_max: the head box; points are normalised to ``[-1, 1]^3`` by it.
        hidden: MLP width.
        n_landmark_coef: PCA coefficients of the landmark condition (GeneFace), else 0.
        intrinsics: ``(focal, cx, cy, width, height)``.
        occupancy: cells per side of the occupancy grid (0: none; see :meth:`update_occupancy`).
    """

    OCCUPANCY_DENSITY = 0.01
    """A cell is empty when no probed condition gave a density above this at its probes (per-sample
    alpha below 1 %; RAD-NeRF's own threshold, 10 at its step of sqrt(3)/512, is about 3 %)."""

    def __init__(self, kind: str, in_channels: int, window: int, box_min, box_max, hidden: int, n_landmark_coef: int = 0,
                 intrinsics=(1.0, 0.0, 0.0, 1, 1), n_train_frames: int = 1, occupancy: int = 0):
        super().__init__()
        self.kind = kind
        # occupancy grid over the box ([-1, 1]^3 after normalize), all occupied until update_occupancy
        self.register_buffer("occ_grid", torch.ones((occupancy,) * 3, dtype=torch.bool))
        self.register_buffer("box_min", torch.as_tensor(box_min, dtype=torch.float32))
        self.register_buffer("box_max", torch.as_tensor(box_max, dtype=torch.float32))
        self.intrinsics = tuple(float(v) for v in intrinsics)
        h, w = int(self.intrinsics[4]), int(self.intrinsics[3])
        self.register_buffer("train_w2c", torch.zeros(n_train_frames, 4, 4))
        self.register_buffer("default_background", torch.zeros(h, w, 3, dtype=torch.uint8))
        cond = 32
        if kind == "geneface":
            self.predictor = LandmarkPredictor(in_channels, window, n_landmark_coef)
            # components whose spread is numerical noise are switched off (whitening would blow them up)
            self.register_buffer("coef_mask", torch.ones(n_landmark_coef))
            self.cond_net = nn.Sequential(nn.Linear(n_landmark_coef, cond), nn.LeakyReLU(0.02), nn.Linear(cond, cond))
        else:
            self.audio_net = AudioNet(in_channels, window, AudioConfig(dim=cond))
        if kind in ("adnerf", "geneface"):
            self.pe = PositionalEncoding(6)
            self.mlp = FieldMLP(self.pe.out_dim + cond, hidden)
        elif kind == "radnerf":
            self.grid = DenseGrids3D()
            self.aud_coord = nn.Linear(cond, 2)
            self.aud_grid = nn.Parameter(torch.empty(1, 8, 32, 32).uniform_(-1e-2, 1e-2))
            self.mlp = FieldMLP(self.grid.out_dim + 8, hidden, n_layers=2)
        elif kind == "ernerf":
            tcfg = TriplaneConfig(n_levels=6, n_features=2, log2_table_size=14, base_resolution=8, finest_resolution=128)
            self.triplane = TriplaneEncoder(tcfg, torch.full((3,), -1.0), torch.full((3,), 1.0))
            D = self.triplane.out_dim
            self.att = nn.Sequential(nn.Linear(D, 32), nn.ReLU(), nn.Linear(32, cond))
            self.mlp = FieldMLP(D + cond, hidden, n_layers=2)
        else:
            raise ValueError(f"unknown NeRF kind {kind!r}")

    @property
    def diag(self) -> float:
        return float((self.box_max - self.box_min).norm())

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (2 * (x - self.box_min) / (self.box_max - self.box_min) - 1).clamp(-1, 1)

    def occupied(self, x: torch.Tensor) -> torch.Tensor | None:
        """Whether world points ``[N, 3]`` lie in occupied cells (None: no occupancy grid)."""
        g = self.occ_grid
        if g.numel() == 0:
            return None
        n = g.shape[0]
        i = ((self.normalize(x) + 1) * (n / 2)).long().clamp_(0, n - 1)
        return g[i[:, 0], i[:, 1], i[:, 2]]

    @torch.no_grad()
    def update_occupancy(self, conds: torch.Tensor, probes: int = 2, seed: int = 0, chunk: int = 1 << 16) -> float:
        """Mark the cells where any of ``conds`` ``[K, 32]`` puts density; returns the occupied fraction.

        Each cell is probed at ``probes`` random points per condition; a cell is occupied if a
        probe's density exceeds :attr:`OCCUPANCY_DENSITY`, and the grid is dilated by one cell
        (a probe can miss the densest point of its cell), as ER-NeRF / RAD-NeRF's occupancy
        grids are made from the densities of training conditions.
        """
        n = self.occ_grid.shape[0]
        if n == 0:
            return 1.0
        gen = torch.Generator().manual_seed(seed)
        dev = self.box_min.device
        ax = torch.arange(n, dtype=torch.float32)
        cells = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        top = torch.zeros(n**3, device=dev)
        for c in conds:
            for _ in range(probes):
                u = (cells + torch.rand(cells.shape, generator=gen)) * (2.0 / n) - 1.0
                x = ((u + 1) / 2 * (self.box_max.cpu() - self.box_min.cpu()) + self.box_min.cpu()).to(dev)
                for s in range(0, len(x), chunk):
                    sig, _ = self(x[s : s + chunk], c)
                    top[s : s + chunk] = torch.maximum(top[s : s + chunk], sig)
        occ = (top > self.OCCUPANCY_DENSITY).float().view(1, 1, n, n, n)
        self.occ_grid.copy_(F.max_pool3d(occ, 3, stride=1, padding=1)[0, 0] > 0)
        return float(self.occ_grid.float().mean())

    def conditions(self, feats: torch.Tensor, landmark_coef: torch.Tensor | None = None) -> torch.Tensor:
        """Per-frame condition vectors ``[T, 32]`` from audio windows (or landmark coefficients)."""
        if self.kind == "geneface":
            coef = self.predictor.coefficients(feats) if landmark_coef is None else landmark_coef
            return self.cond_net((coef * self.coef_mask).clamp(-4.0, 4.0))
        return self.audio_net(feats)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        u = self.normalize(x)
        if not torch.is_grad_enabled() and cond.dim() == 1:
            return self._render_forward(u, cond)
        c = cond.expand(u.shape[0], -1)
        if self.kind in ("adnerf", "geneface"):
            return self.mlp(torch.cat([self.pe(u), c], -1))
        if self.kind == "radnerf":
            a = torch.tanh(self.aud_coord(cond)).view(1, 1, 1, 2)
            fa = F.grid_sample(self.aud_grid, a, align_corners=True).view(1, -1).expand(u.shape[0], -1)
            return self.mlp(torch.cat([self.grid(u), fa], -1))
        f = self.triplane(u)  # ER-NeRF: region attention gates the audio by the point's feature
        return self.mlp(torch.cat([f, torch.sigmoid(self.att(f)) * c], -1))

    def _render_forward(self, u: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` without autograd, one condition for all points (:meth:`FieldMLP.forward_parts`)."""
        if self.kind in ("adnerf", "geneface"):
            return self.mlp.forward_parts([self.pe(u), cond])
        if self.kind == "radnerf":
            a = torch.tanh(self.aud_coord(cond)).view(1, 1, 1, 2)
            fa = F.grid_sample(self.aud_grid, a, align_corners=True).view(-1)
            return self.mlp.forward_parts([self.grid(u), fa])
        f = self.triplane(u)
        return self.mlp.forward_parts([f, torch.sigmoid(self.att(f)).mul_(cond)])


HEAD_DIFFERENCE = 12
"""uint8 levels (any channel) by which a pixel must differ from its background to count as the head."""


def head_pixels(clip, i: int) -> np.ndarray:
    """``[H, W]`` bool: the pixels of frame ``i`` that differ from its background (the rendered head)."""
    diff = np.abs(clip.frames[i].astype(np.int16) - clip.background(i).astype(np.int16)).max(-1)
    return diff > HEAD_DIFFERENCE


def _landmark_coefficients(predictor, targets: torch.Tensor) -> torch.Tensor:
    """Whitened PCA coefficients of target landmarks in the predictor's basis (inverse of ``decode``)."""
    off = ((targets - predictor.mean_lms) / predictor.scale).reshape(len(targets), -1)
    return (off @ predictor.basis.T) / predictor.coef_std


class NeRFMethod(Adapter):
    """Adapter of one NeRF flavour to the talking-head protocol."""

    budget_cls = NeRFBudget
    family = "NeRF"
    standins = STANDINS

    def _build(self, build: dict) -> NeRFHead:
        return NeRFHead(self.name, **build)

    def _train(self, clip, seed: int, progress: bool):
        dev = self.dev
        rng = seed_all(seed)
        b = self.cfg
        n = len(clip)
        feats = audio_windows(clip.audio, n).to(dev)
        lo, hi = head_box(clip)
        build = {"in_channels": int(feats.shape[2]), "window": int(feats.shape[1]), "box_min": lo.tolist(), "box_max": hi.tolist(),
                 "hidden": b.hidden, "intrinsics": [clip.focal, clip.cx, clip.cy, clip.width, clip.height], "n_train_frames": n,
                 "occupancy": b.occupancy if self.name in OCCUPANCY_METHODS else 0}
        lm_coef = None
        predictor = None
        if self.name == "geneface":
            targets = torch.from_numpy(landmark_targets(clip)).to(dev)
            predictor = fit_landmark_predictor(feats, targets, steps=b.landmark_steps, seed=seed)
            build["n_landmark_coef"] = predictor.n_components
            lm_coef = _landmark_coefficients(predictor, targets)
        model = NeRFHead(self.name, **build).to(dev)
        if predictor is not None:
            model.predictor.load_state_dict(predictor.state_dict())
            model.predictor.requires_grad_(False)
            std = predictor.coef_std
            model.coef_mask.copy_((std > 1e-3 * std.max()).float())
        else:
            model.audio_net.encoder.fit_normalization(feats)
        model.train_w2c.copy_(torch.from_numpy(np.asarray(clip.w2c, np.float32)))
        model.default_background.copy_(torch.from_numpy(mean_background(clip)))
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=b.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(b.steps, 1), eta_min=b.lr * 0.1)
        lo_t, hi_t = model.box_min, model.box_max
        rays_cache: dict[int, tuple] = {}
        bar = progress_bar(b.steps, f"{self.name} fit", progress)
        order = rng.integers(0, n, size=b.steps)
        for step in range(b.steps):
            i = int(order[step])
            if i not in rays_cache:
                o, d = camera_rays(clip.w2c[i], clip.focal, clip.cx, clip.cy, clip.height, clip.width, dev)
                near, far, hit = box_hits(o, d, lo_t, hi_t)
                fg = torch.from_numpy(head_pixels(clip, i).reshape(-1)).to(dev) & hit
                rays_cache[i] = (o, d, near, far, torch.nonzero(hit)[:, 0], torch.nonzero(fg)[:, 0])
            o, d, near, far, idx, fg_idx = rays_cache[i]
            if len(idx) == 0:
                continue
            n_fg = int(round(b.head_share * b.rays)) if len(fg_idx) else 0
            pick = torch.cat([fg_idx[torch.from_numpy(rng.integers(0, max(len(fg_idx), 1), size=n_fg)).to(dev)],
                              idx[torch.from_numpy(rng.integers(0, len(idx), size=b.rays - n_fg)).to(dev)]])
            gt = torch.from_numpy(clip.frames[i].reshape(-1, 3)[pick.cpu().numpy()]).to(dev).float() / 255
            bg = torch.from_numpy(clip.background(i).reshape(-1, 3)[pick.cpu().numpy()]).to(dev).float() / 255
            cond = model.conditions(feats, lm_coef)[i] if self.name == "geneface" else model.audio_net(feats, index=torch.tensor([i], device=dev))[0]
            rgb = render_rays(model, cond, o[pick], d[pick], near[pick], far[pick], bg, b.samples, model.diag, jitter=True)
            loss = F.mse_loss(rgb, gt)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            if bar is not None:
                bar.update(1)
                if step % 25 == 0:
                    bar.set_postfix(loss=f"{float(loss):.4f}")
        if bar is not None:
            bar.close()
        if build["occupancy"]:
            # the conditions of OCCUPANCY_FRAMES training frames spread over the clip
            pick = torch.from_numpy(np.unique(np.linspace(0, n - 1, OCCUPANCY_FRAMES).round().astype(np.int64))).to(dev)
            with torch.no_grad():
                model.update_occupancy(model.audio_net(feats, index=pick), seed=seed)
        return model, build

    @torch.no_grad()
    def render(self, driving) -> np.ndarray:
        self._check_fitted()
        m = self.model
        dev = m.box_min.device
        n = n_frames_of(driving)
        f, cx, cy, w, h = m.intrinsics
        w, h = int(w), int(h)
        out = np.empty((n, h, w, 3), np.uint8)
        if n == 0:
            return out
        feats = audio_windows(driving.audio, n).to(dev)
        conds = m.conditions(feats)
        train_w2c = m.train_w2c.cpu().numpy()
        default_bg = m.default_background.cpu().numpy()
        for t in range(n):
            bg = torch.from_numpy(np.ascontiguousarray(driving_background(driving, default_bg, t))).to(dev).float().reshape(-1, 3) / 255
            img = bg.clone()
            o, d = camera_rays(driving_w2c(driving, train_w2c, t), f, cx, cy, h, w, dev)
            near, far, hit = box_hits(o, d, m.box_min, m.box_max)
            idx = torch.nonzero(hit)[:, 0]
            for s in range(0, len(idx), self.cfg.chunk):
                j = idx[s : s + self.cfg.chunk]
                img[j] = march_rays(m, conds[t], o[j], d[j], near[j], far[j], bg[j], self.cfg.samples, m.diag)
            out[t] = to_u8(img.view(h, w, 3))
        return out

    def budget_text(self) -> str:
        b = self.cfg
        extra = f", {b.landmark_steps} landmark steps" if self.name == "geneface" else ""
        grid = f", occupancy grid {b.occupancy}^3" if self.name in OCCUPANCY_METHODS and b.occupancy else ""
        return (f"{b.steps} steps x {b.rays} rays x {b.samples} samples, MLP width {b.hidden}{extra}; full-frame render, "
                f"{b.samples} samples per ray, rays stop at transmittance {STOP_TRANSMITTANCE:g}{grid}")


@register("adnerf")
class ADNeRF(NeRFMethod):
    name = "adnerf"
    display_name = "AD-NeRF"
    description = (
        "Kept: a NeRF whose MLP takes the positional encoding of the point with the per-frame audio feature "
        "(audio net + attention smoother over 8 frames) concatenated, volume-rendered over the frame's background. "
        "Simplified: one head field (no separate torso NeRF: the torso is the given background), a small MLP, "
        "stratified samples in the head box only, no hierarchical sampling, log-mel instead of DeepSpeech, CPU budget."
    )


@register("radnerf")
class RADNeRF(NeRFMethod):
    name = "radnerf"
    display_name = "RAD-NeRF"
    description = (
        "Kept: the decomposed audio-spatial encoding (a multi-resolution 3D grid for the point, a 2D grid indexed by "
        "a learned 2D projection of the audio feature) feeding a small MLP, no region attention, volume rendering. "
        "Kept also: occupancy-grid ray marching when rendering (a 32^3 grid over the head box marking where 32 "
        "training conditions put density; empty cells are skipped). Simplified: dense grids (8^3, 16^3, 32^3) "
        "instead of hash grids, no eye/torso branches, stratified samples in the head box (no grid-guided sampling "
        "in training), log-mel instead of DeepSpeech, CPU budget."
    )


@register("ernerf")
class ERNeRF(NeRFMethod):
    name = "ernerf"
    display_name = "ER-NeRF"
    description = (
        "Kept: the tri-plane hash encoder (lmgs.encoders.TriplaneEncoder) for the point and region attention: "
        "channel gates computed from the point's tri-plane feature multiply the audio feature before the MLP; "
        "volume rendering over the frame's background, occupancy-grid ray marching when rendering (a 32^3 grid over "
        "the head box from 32 training conditions). Simplified: 6 levels up to 128 per plane, no eye/AU branch, "
        "no torso field, no adaptive pose encoding, stratified samples in the head box in training, log-mel "
        "features, CPU budget."
    )


@register("geneface")
class GeneFace(NeRFMethod):
    name = "geneface"
    display_name = "GeneFace"
    description = (
        "Kept: the two-stage audio -> 68 3D landmarks -> landmark-conditioned NeRF pipeline; the NeRF is trained on "
        "the tracked landmarks (their whitened PCA coefficients) and driven at test time by the predicted ones. "
        "Simplified: the audio-to-landmark stage is the project's per-subject temporal CNN (lmgs.landmarks), not "
        "GeneFace's generic VAE trained on LRS3, and there is no domain-adaptive post-net; the NeRF is a small "
        "positional-encoding MLP with stratified samples in the head box; CPU budget."
    )
    standins = STANDINS + (
        "audio-to-landmark: the project's per-subject temporal CNN trained on the training split (GeneFace's pretrained VAE cannot be had offline)",
    )
