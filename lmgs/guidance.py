"""Landmark guidance of the deformation: Spatial Enhancement and Landmark Compensation.

Both from the paper implemented here (landmark-guided 3DGS talking heads, sections
"Spatial Enhancement" and "Landmark Compensation"). The 68 keypoints :math:`k_j` of a frame
come from the audio-to-landmark predictor (:mod:`lmgs.landmarks`); points and keypoints are
encoded by the same tri-plane hash encoder :math:`\\phi`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from lmgs.config import GuidanceConfig
from lmgs.errors import InputError


@dataclass(frozen=True)
class EnhanceResult:
    """Output of :func:`spatial_enhance`.

    Attributes:
        features: ``[N, D]`` :math:`F_i` (enhanced where selected, else :math:`f_i`).
        selected: ``[N]`` bool, :math:`i \\in \\mathcal{M}`.
        match: ``[N]`` int64, :math:`j^*_i` (defined for every point; used only where selected).
        max_similarity: ``[N]`` :math:`\\max_j S_{ij}`.
    """

    features: torch.Tensor
    selected: torch.Tensor
    match: torch.Tensor
    max_similarity: torch.Tensor

    @property
    def fraction(self) -> float:
        """Share of points selected (log it: the paper reports about 0.2 at 0.6); reading it waits
        for the device (:func:`selected_share` keeps it there)."""
        return float(selected_share(self.selected))


def selected_share(selected: torch.Tensor) -> torch.Tensor:
    """The share of True in ``selected`` as a 0-d float32 tensor on its device (0 when empty)."""
    if selected.numel() == 0:
        return torch.zeros((), device=selected.device)
    return selected.float().mean()


def cosine_similarity_matrix(f: torch.Tensor, g: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """:math:`S_{ij} = f_i^\\top g_j / (\\|f_i\\| \\|g_j\\|)`, ``[N, D] x [K, D] -> [N, K]`` (norms floored at eps)."""
    return unit_rows(f, eps) @ unit_rows(g, eps).T


def unit_rows(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Each row over its norm (floored at eps): one side of :func:`cosine_similarity_matrix`."""
    return x / x.norm(dim=-1, keepdim=True).clamp_min(eps)


def select_points(s: torch.Tensor, theta: float, max_fraction: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The selection of :func:`spatial_enhance` from the similarities ``S`` ``[N, K]``:
    ``(selected [N] bool, match [N] int64, max_similarity [N])``."""
    best, match = s.max(dim=1)
    if max_fraction > 0.0 and s.shape[0]:
        k = int(round(max_fraction * s.shape[0]))
        if k == 0:
            return torch.zeros_like(best, dtype=torch.bool), match, best
        # the threshold stays on the device (a float() here would wait for it)
        return best >= torch.topk(best, k).values[-1].clamp_min(theta), match, best
    return best >= theta, match, best


def spatial_enhance(f: torch.Tensor, g: torch.Tensor, theta: float = 0.6, max_fraction: float = 0.0) -> EnhanceResult:
    """Spatial Enhancement: add the most similar keypoint's feature to points similar enough.

    .. math::

        \\mathcal{M} = \\{ i \\mid \\max_j S_{ij} \\ge \\theta \\}, \\quad
        j^*_i = \\arg\\max_j S_{ij}, \\quad
        F_i = \\begin{cases} f_i + g_{j^*_i} & i \\in \\mathcal{M} \\\\ f_i & \\text{otherwise} \\end{cases}

    The selection (mask and argmax) is a hard, non-differentiable choice; the added
    features are differentiable in both :math:`f` and :math:`g`.

    Args:
        f: ``[N, D]`` point features :math:`\\phi(x_i)`.
        g: ``[K, D]`` keypoint features :math:`\\phi(k_j)` of one frame (K = 68).
        theta: threshold :math:`\\theta` (paper: 0.6).
        max_fraction: 0: every point at or above ``theta`` (the paper). In (0, 1): at most
            ``round(max_fraction * N)`` points, the most similar ones (the threshold is raised
            to the similarity of the last one kept; ties at it are kept too).
    """
    if f.ndim != 2 or g.ndim != 2 or f.shape[1] != g.shape[1]:
        raise InputError(f"spatial_enhance expects f [N, D] and g [K, D], got {tuple(f.shape)} and {tuple(g.shape)}")
    if g.shape[0] == 0:
        raise InputError("spatial_enhance needs at least one keypoint")
    with torch.no_grad():
        selected, match, best = select_points(cosine_similarity_matrix(f, g), theta, max_fraction)
    # One-hot matrix product rather than ``g[match]``: the backward of an index with
    # repeated indices accumulates with atomic adds on the CPU (run-to-run different
    # float sums); a matrix product is reproducible for a given machine and thread count.
    pick = torch.nn.functional.one_hot(match, g.shape[0]).to(f.dtype) * selected.unsqueeze(-1).to(f.dtype)
    features = f + pick @ g
    return EnhanceResult(features, selected, match, best)


MOUTH_STATE_DIM = 2  # inner-lip opening, mouth width


def mouth_state(landmarks: torch.Tensor) -> torch.Tensor:
    """The mouth's state ``[..., 2]`` from 68 landmarks ``[..., 68, 2 or 3]``: the inner lips' opening
    (points 62 and 66) and the mouth's width (48 and 54), each over the distance between the outer
    eye corners (36 and 45), so that neither the head's distance nor its pose changes them."""
    if landmarks.shape[-2] != 68:
        raise InputError(f"the mouth state reads 68 landmarks, got {landmarks.shape[-2]}")
    eyes = (landmarks[..., 36, :] - landmarks[..., 45, :]).norm(dim=-1).clamp_min(1e-8)
    gap = (landmarks[..., 62, :] - landmarks[..., 66, :]).norm(dim=-1)
    width = (landmarks[..., 48, :] - landmarks[..., 54, :]).norm(dim=-1)
    return torch.stack([gap / eyes, width / eyes], dim=-1)


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, d_out))


class LandmarkCompensation(nn.Module):
    """Landmark Compensation: a global landmark condition and gated per-point offsets.

    .. math::

        c_{lms} = \\psi\\big(\\textstyle\\bigoplus_{j=1}^{68} g_j\\big), \\quad
        h_i = [F_i \\,\\|\\, c_{lms}], \\quad
        [\\hat d_x^i, \\hat d_r^i, \\hat d_s^i] = \\mathrm{MLP}_{offset}(h_i)\\, \\tau_i, \\quad
        \\tau_i = \\sigma\\big(\\mathrm{MLP}_\\tau(h_i)\\big)

    :math:`\\tau_i` goes through a sigmoid (``tau_activation="sigmoid"``, default), so the
    compensation strength is a per-point gate in (0, 1) that can shut the branch off but never
    flips its sign; ``"tanh"`` allows (-1, 1). The last layer of :math:`\\mathrm{MLP}_{offset}`
    is initialised to exactly zero, so training starts from the backbone's offsets alone
    (the gradient of that layer is not zero, so it learns from the first step).

    Args:
        feat_dim: D of :math:`F_i` and :math:`g_j`.
        cfg: ``n_landmarks``, ``cond_dim``, ``hidden``, ``tau_activation``.

    Shapes:
        ``forward(F [N, D], g [K, D]) -> (d_xyz [N, 3], d_rot [N, 4], d_scale [N, 3], tau [N, 1])``.
    """

    def __init__(self, feat_dim: int, cfg: GuidanceConfig = GuidanceConfig()):
        super().__init__()
        if cfg.tau_activation not in ("sigmoid", "tanh"):
            raise InputError(f"tau_activation must be 'sigmoid' or 'tanh', got {cfg.tau_activation!r}")
        self.cfg = cfg
        self.feat_dim = int(feat_dim)
        self.psi = _mlp(cfg.n_landmarks * feat_dim, cfg.hidden, cfg.cond_dim)
        self.offset = _mlp(feat_dim + cfg.cond_dim, cfg.hidden, 10)
        self.tau = _mlp(feat_dim + cfg.cond_dim, cfg.hidden, 1)
        nn.init.zeros_(self.offset[-1].weight)
        nn.init.zeros_(self.offset[-1].bias)

    def condition(self, g: torch.Tensor) -> torch.Tensor:
        """:math:`c_{lms}` ``[cond_dim]`` from the keypoint features ``[K, D]``."""
        if g.shape != (self.cfg.n_landmarks, self.feat_dim):
            raise InputError(f"landmark features must be [{self.cfg.n_landmarks}, {self.feat_dim}], got {tuple(g.shape)}")
        return self.psi(g.reshape(-1))

    def forward(self, F: torch.Tensor, g: torch.Tensor):
        c = self.condition(g)
        # Linear on a concat = sum of two Linears: avoids materialising [N, D + cond] and lets
        # the condition's share be computed once per frame instead of once per point.
        h_off = _split_first_layer(self.offset, F, c)
        h_tau = _split_first_layer(self.tau, F, c)
        act = torch.sigmoid if self.cfg.tau_activation == "sigmoid" else torch.tanh
        tau = act(h_tau)
        out = h_off * tau
        return out[:, :3], out[:, 3:7], out[:, 7:10], tau


def _split_first_layer(mlp: nn.Sequential, F: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """``mlp(cat([F, c broadcast]))`` without building the concatenation."""
    first = mlp[0]
    d = F.shape[1]
    h = F @ first.weight[:, :d].T + (first.weight[:, d:] @ c + first.bias)
    for layer in list(mlp)[1:]:
        h = layer(h)
    return h
