"""Tri-plane hash encoder: three 2D multiresolution hash grids (ER-NeRF, instant-ngp).

A 3D point is normalised by a bounding box into :math:`[0,1]^3` and projected onto the three
axis planes xy, yz and xz. Each plane is an instant-ngp multiresolution grid (Müller et al.,
"Instant Neural Graphics Primitives", SIGGRAPH 2022) in 2D; the features of the three planes
are concatenated, as ER-NeRF does (Li et al., "Efficient Region-Aware Neural Radiance Fields
for High-Fidelity Talking Portrait Synthesis", ICCV 2023):

.. math::

    \\phi(\\mathbf{x}) = \\big[\\, H_{xy}(x, y) \\,\\|\\, H_{yz}(y, z) \\,\\|\\, H_{xz}(x, z) \\,\\big],
    \\qquad H(\\mathbf{u}) = \\big[\\, \\mathrm{bilerp}_\\ell(\\mathbf{u}\\, R_\\ell) \\,\\big]_{\\ell=0}^{L-1}

with level resolutions :math:`R_\\ell = \\lfloor N_{min} b^\\ell \\rfloor`,
:math:`b = \\exp\\big((\\ln N_{max} - \\ln N_{min}) / (L - 1)\\big)`. A level whose dense grid
of :math:`(R_\\ell + 1)^2` vertices fits in the table :math:`T` is indexed densely
(:math:`i = v_x + v_y (R_\\ell + 1)`); larger levels use the instant-ngp spatial hash

.. math::

    h(v_x, v_y) = \\big(v_x \\pi_1 \\oplus v_y \\pi_2\\big) \\bmod T, \\qquad \\pi_1 = 1,\\ \\pi_2 = 2654435761.

Two paths compute the same thing: a numba CPU kernel (``backend="numba"``, the default on
CPU; forward and backward written out, about 10x faster than autograd here) and vectorised
torch (``backend="torch"``: one gather + bilinear weights with ordinary autograd, used on
CUDA). :func:`_triplane_encode_reference` is their naive per-point twin for tests.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from lmgs.config import TriplaneConfig
from lmgs.errors import InputError

_PRIME_Y = 2654435761
# plane -> the two point axes it sees: xy, yz, xz (ER-NeRF's order)
PLANES: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (0, 2))


def level_resolutions(cfg: TriplaneConfig) -> list[int]:
    """Grid resolution :math:`R_\\ell` of each level (geometric from base to finest)."""
    if cfg.n_levels < 1:
        raise InputError(f"triplane n_levels must be >= 1, got {cfg.n_levels}")
    if cfg.n_levels == 1:
        return [int(cfg.base_resolution)]
    b = math.exp((math.log(cfg.finest_resolution) - math.log(cfg.base_resolution)) / (cfg.n_levels - 1))
    return [int(math.floor(cfg.base_resolution * b**lvl + 1e-6)) for lvl in range(cfg.n_levels)]


def hash_grid_2d(ix: torch.Tensor, iy: torch.Tensor, res: torch.Tensor, dense: torch.Tensor, table_size: int) -> torch.Tensor:
    """Table index of integer grid vertices (dense where the level fits, else spatial hash).

    Args:
        ix, iy: integer vertex coordinates, ``[..., L, K]`` int64.
        res: ``[L]`` level resolutions (int64).
        dense: ``[L]`` bool, whether the level is indexed densely.
        table_size: :math:`T`, a power of two.

    Returns:
        ``[..., L, K]`` int64 index into the level's table (before the level offset).
    """
    r = res.view(-1, 1)
    dense_idx = ix + iy * (r + 1)
    hashed = (ix ^ (iy * _PRIME_Y)) & (table_size - 1)
    return torch.where(dense.view(-1, 1), dense_idx, hashed)


class TriplaneEncoder(nn.Module):
    """Tri-plane multiresolution hash encoder :math:`\\phi`.

    Args:
        cfg: sizes (levels, features per level, table size, resolutions).
        box_min, box_max: the bounding box mapped to :math:`[0,1]^3`; default
            ``[-cfg.bound, cfg.bound]^3``. Points outside are clamped to the box.

    Shapes:
        ``forward(x)``: ``x [..., 3]`` world points -> ``[..., 3 * n_levels * n_features]``.
    """

    def __init__(self, cfg: TriplaneConfig = TriplaneConfig(), box_min=None, box_max=None):
        super().__init__()
        if cfg.log2_table_size < 4 or cfg.log2_table_size > 24:
            raise InputError(f"triplane log2_table_size must be in [4, 24], got {cfg.log2_table_size}")
        self.cfg = cfg
        T = 1 << cfg.log2_table_size
        res = level_resolutions(cfg)
        sizes = [min(T, (r + 1) ** 2) for r in res]
        dense = [(r + 1) ** 2 <= T for r in res]
        offsets, total = [], 0
        for _ in PLANES:
            row = []
            for s in sizes:
                row.append(total)
                total += s
            offsets.append(row)
        self.table_size = T
        self.register_buffer("res", torch.tensor(res, dtype=torch.int64), persistent=False)
        self.register_buffer("dense", torch.tensor(dense, dtype=torch.bool), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.int64), persistent=False)  # [3, L]
        lo = torch.full((3,), -cfg.bound) if box_min is None else torch.as_tensor(box_min, dtype=torch.float32)
        hi = torch.full((3,), cfg.bound) if box_max is None else torch.as_tensor(box_max, dtype=torch.float32)
        if lo.shape != (3,) or hi.shape != (3,) or not bool((hi > lo).all()):
            raise InputError(f"triplane box must be two [3] vectors with max > min, got {lo.tolist()} / {hi.tolist()}")
        self.register_buffer("box_min", lo.clone())
        self.register_buffer("box_max", hi.clone())
        # instant-ngp / torch-ngp initialisation: tiny uniform features
        self.embeddings = nn.Parameter(torch.empty(total, cfg.n_features).uniform_(-1e-4, 1e-4))

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    def set_box(self, box_min: torch.Tensor, box_max: torch.Tensor) -> None:
        """Change the bounding box (e.g. to the canonical Gaussians' extent plus a margin)."""
        lo = torch.as_tensor(box_min).to(self.box_min)
        hi = torch.as_tensor(box_max).to(self.box_max)
        if lo.shape != (3,) or hi.shape != (3,) or not bool((hi > lo).all()):
            raise InputError(f"triplane box must be two [3] vectors with max > min, got {lo.tolist()} / {hi.tolist()}")
        self.box_min.copy_(lo)
        self.box_max.copy_(hi)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Map world points into :math:`[0,1]^3` by the box (clamped)."""
        return ((x - self.box_min) / (self.box_max - self.box_min)).clamp(0.0, 1.0)

    def forward(self, x: torch.Tensor, backend: str = "auto") -> torch.Tensor:
        """Encode points.

        Args:
            x: ``[..., 3]`` world points.
            backend: ``"auto"`` (numba on CPU, torch elsewhere), ``"numba"`` or ``"torch"``.

        Returns:
            ``[..., 3 * n_levels * n_features]``: planes xy, yz, xz, each level by level.
        """
        if x.shape[-1] != 3:
            raise InputError(f"triplane input must be [..., 3] points, got shape {tuple(x.shape)}")
        if backend == "auto":
            backend = "numba" if self.embeddings.device.type == "cpu" else "torch"
        if backend not in ("numba", "torch"):
            raise InputError(f"triplane backend must be 'auto', 'numba' or 'torch', got {backend!r}")
        lead = x.shape[:-1]
        u = self.normalize(x.reshape(-1, 3).to(self.embeddings.dtype))  # [N, 3]
        if backend == "numba":
            out = _NumbaTriplane.apply(u, self.embeddings, self.res, self.dense, self.offsets, self.table_size)
            return out.reshape(*lead, self.out_dim)
        # integer indexing only (a list index would be copied to the device and wait for it)
        uv = torch.stack([torch.stack((u[:, a], u[:, b]), dim=-1) for a, b in PLANES], dim=1)  # [N, 3, 2]
        res = self.res.to(u.dtype)
        pos = uv[:, :, None, :] * res.view(1, 1, -1, 1)  # [N, 3, L, 2]
        # u == 1 lands on the last cell with fraction 1, not outside the grid
        cell = torch.minimum(pos.floor(), (res - 1).view(1, 1, -1, 1)).to(torch.int64)
        frac = pos - cell.to(pos.dtype)
        cx, cy = cell[..., 0:1], cell[..., 1:2]  # [N, 3, L, 1]
        ix = torch.cat([cx, cx + 1, cx, cx + 1], dim=-1)  # corners (0,0) (1,0) (0,1) (1,1)
        iy = torch.cat([cy, cy, cy + 1, cy + 1], dim=-1)
        idx = hash_grid_2d(ix, iy, self.res, self.dense, self.table_size) + self.offsets[None, :, :, None]
        fx, fy = frac[..., 0:1], frac[..., 1:2]
        w = torch.cat([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=-1)  # [N, 3, L, 4]
        # index_select: its backward adds rows (index_add_); embedding's sorts the indices and reads a count back
        feats = self.embeddings.index_select(0, idx.reshape(-1)).view(*idx.shape, -1)  # [N,3,L,4,F]
        out = (feats * w.unsqueeze(-1)).sum(dim=-2)  # [N, 3, L, F]
        return out.reshape(*lead, self.out_dim)


class _NumbaTriplane(torch.autograd.Function):
    """Autograd wrapper of the numba kernels: ``u [N,3]`` in [0,1], table ``[total,F]`` -> ``[N,3,L,F]``."""

    @staticmethod
    def forward(ctx, u, table, res, dense, offsets, table_size):
        from lmgs.encoders import _triplane_numba as k

        un = u.detach().contiguous().numpy()
        tn = table.detach().contiguous().numpy()
        out = np.zeros((un.shape[0], 3, res.numel(), tn.shape[1]), dtype=tn.dtype)
        args = (res.numpy(), dense.numpy(), offsets.numpy(), np.int64(table_size))
        k.triplane_forward(un, tn, *args[:3], args[3], out)
        ctx.save_for_backward(u, table)
        ctx.args = args
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        from lmgs.encoders import _triplane_numba as k

        u, table = ctx.saved_tensors
        un = u.detach().contiguous().numpy()
        tn = table.detach().contiguous().numpy()
        g = grad_out.detach().to(table.dtype).contiguous().numpy()
        res, dense, offsets, T = ctx.args
        grad_u = grad_table = None
        if ctx.needs_input_grad[1]:
            gt = np.zeros_like(tn)
            k.triplane_backward_table(un, g, res, dense, offsets, T, gt)
            grad_table = torch.from_numpy(gt)
        if ctx.needs_input_grad[0]:
            gu = np.zeros_like(un)
            k.triplane_backward_points(un, tn, g, res, dense, offsets, T, gu)
            grad_u = torch.from_numpy(gu)
        return grad_u, grad_table, None, None, None, None


def _triplane_encode_reference(enc: TriplaneEncoder, x: torch.Tensor) -> torch.Tensor:
    """Naive per-point twin of :meth:`TriplaneEncoder.forward` (Python loops and ints; tests only)."""
    cfg = enc.cfg
    T = enc.table_size
    res = level_resolutions(cfg)
    lo, hi = enc.box_min, enc.box_max
    rows = []
    for p in x.reshape(-1, 3):
        u = [((p[a] - lo[a]) / (hi[a] - lo[a])).clamp(0.0, 1.0) for a in range(3)]
        feats = []
        for plane, (a, b) in enumerate(PLANES):
            base = plane * sum(min(T, (r + 1) ** 2) for r in res)
            for r in res:
                px, py = u[a] * r, u[b] * r
                x0, y0 = min(int(math.floor(px.item())), r - 1), min(int(math.floor(py.item())), r - 1)
                tx, ty = px - x0, py - y0
                acc = torch.zeros(cfg.n_features, dtype=enc.embeddings.dtype)
                for dx, dy, wgt in ((0, 0, (1 - tx) * (1 - ty)), (1, 0, tx * (1 - ty)), (0, 1, (1 - tx) * ty), (1, 1, tx * ty)):
                    vx, vy = x0 + dx, y0 + dy
                    if (r + 1) ** 2 <= T:
                        i = vx + vy * (r + 1)
                    else:
                        i = ((vx * 1) ^ (vy * _PRIME_Y)) % T
                    acc = acc + wgt * enc.embeddings[base + i]
                base += min(T, (r + 1) ** 2)
                feats.append(acc)
        rows.append(torch.cat(feats))
    return torch.stack(rows).reshape(*x.shape[:-1], -1)
