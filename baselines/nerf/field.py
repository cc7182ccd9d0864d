"""The NeRF baselines' radiance field: :class:`NeRFHead` in four flavours and its encoders.

Positional encoding (AD-NeRF, GeneFace), dense multi-resolution grids (RAD-NeRF), the tri-plane
hash encoder of :mod:`lmgs` with region attention (ER-NeRF); an MLP head gives density and colour
(:class:`FieldMLP`). The flavours are described in :mod:`baselines.nerf`.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from lmgs.audio import AudioNet
from lmgs.config import AudioConfig, TriplaneConfig
from lmgs.encoders import TriplaneEncoder
from lmgs.landmarks import LandmarkPredictor


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
