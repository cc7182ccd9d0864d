"""Region-attention deformation network (TalkingGaussian / ER-NeRF) with landmark guidance.

For each canonical Gaussian :math:`i` with spatial feature :math:`F_i` (tri-plane
:math:`\\phi(x_i)`, enhanced by Spatial Enhancement when on), the frame's audio feature
:math:`F_a` and expression signal :math:`e` (blink AU45, optionally a vector such as 3DMM
expression parameters), region attention gates each modality by a function of the spatial
feature (ER-NeRF, Li et al., ICCV 2023; TalkingGaussian, Li et al., ECCV 2024):

.. math::

    a^{aud}_i = \\sigma\\big(\\mathrm{MLP}_{aud}(F_i)\\big), \\quad
    a^{exp}_i = \\sigma\\big(\\mathrm{MLP}_{exp}(F_i)\\big), \\quad
    h_i = \\big[F_i \\,\\|\\, a^{aud}_i \\odot F_a \\,\\|\\, a^{exp}_i \\odot e\\big]

(``attention="softmax"`` uses a softmax over each modality's channels instead of
:math:`\\sigma`; ``bound_audio=True`` feeds :math:`\\tanh(F_a)`, off by default: it saturates), then an MLP
(whose last layer starts at zero with ``zero_init=True``) gives the offsets

.. math::

    [\\Delta x_i, \\Delta r_i, \\Delta s_i] = \\mathrm{MLP}(h_i), \\quad \\Delta x_i \\leftarrow 10^{-2} \\Delta x_i

and Landmark Compensation (:class:`lmgs.guidance.LandmarkCompensation`) adds its gated
correction when ``lc`` is on. The rotation offset is added to the quaternion (the caller
normalises), the scale offset to the log-scale. The mouth branch of TalkingGaussian predicts
only position offsets from audio (``DeformConfig.mouth()``).

The spatial part that does not change from frame to frame (:math:`\\phi(x_i)` of the
canonical points) can be computed once with :meth:`DeformNet.encode_points` and passed in.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from lmgs.config import DeformConfig, GuidanceConfig, TriplaneConfig
from lmgs.encoders.triplane import TriplaneEncoder
from lmgs.errors import InputError
from lmgs.guidance import LandmarkCompensation, spatial_enhance


@dataclass(frozen=True)
class DeformOutput:
    """Per-Gaussian offsets of one frame.

    Attributes:
        d_xyz: ``[N, 3]`` position offsets.
        d_rot: ``[N, 4]`` quaternion offsets (added before normalisation); zeros in position-only mode.
        d_scale: ``[N, 3]`` log-scale offsets; zeros in position-only mode.
        se_fraction: share of points Spatial Enhancement selected (``None`` when SE is off).
        audio_attention: ``[N, A]`` the audio gates (for region-attention visualisation).
    """

    d_xyz: torch.Tensor
    d_rot: torch.Tensor
    d_scale: torch.Tensor
    se_fraction: float | None
    audio_attention: torch.Tensor


def _gate(x: torch.Tensor, kind: str) -> torch.Tensor:
    return torch.sigmoid(x) if kind == "sigmoid" else torch.softmax(x, dim=-1)


class DeformNet(nn.Module):
    """One branch (face or mouth) of the deformation: points + audio + expression -> offsets.

    Args:
        audio_dim: size of :math:`F_a` (after the smoother).
        cfg: the network's sizes and modes (``DeformConfig.quick()`` face, ``DeformConfig.mouth()``).
        triplane: tri-plane config (this branch owns its encoder, as TalkingGaussian's branches do).
        guidance: SE / LC switches and sizes; ``GuidanceConfig(se=False, lc=False)`` gives plain
            TalkingGaussian.
        box_min, box_max: bounding box of the canonical points for the tri-plane.

    Shapes:
        ``forward(xyz [N,3], audio [A] , landmarks [68,3] | None, blink [] | None,
        exp [E] | None, point_features [N,D] | None) -> DeformOutput``
    """

    def __init__(
        self,
        audio_dim: int,
        cfg: DeformConfig = DeformConfig(),
        triplane: TriplaneConfig = TriplaneConfig(),
        guidance: GuidanceConfig = GuidanceConfig(),
        box_min=None,
        box_max=None,
    ):
        super().__init__()
        if cfg.attention not in ("sigmoid", "softmax"):
            raise InputError(f"attention must be 'sigmoid' or 'softmax', got {cfg.attention!r}")
        self.cfg, self.guidance_cfg = cfg, guidance
        self.audio_dim = int(audio_dim)
        self.encoder = TriplaneEncoder(triplane, box_min, box_max)
        D = self.encoder.out_dim
        self.exp_total = (1 if cfg.blink else 0) + cfg.exp_dim
        self.aud_att = nn.Sequential(nn.Linear(D, cfg.att_hidden), nn.ReLU(), nn.Linear(cfg.att_hidden, audio_dim))
        self.exp_att = (
            nn.Sequential(nn.Linear(D, cfg.att_hidden), nn.ReLU(), nn.Linear(cfg.att_hidden, self.exp_total))
            if self.exp_total
            else None
        )
        n_out = 3 if cfg.position_only else 10
        layers, d_in = [], D + audio_dim + self.exp_total
        for _ in range(cfg.n_layers):
            layers += [nn.Linear(d_in, cfg.hidden), nn.ReLU()]
            d_in = cfg.hidden
        layers.append(nn.Linear(d_in, n_out))
        if cfg.zero_init:
            nn.init.zeros_(layers[-1].weight)
            nn.init.zeros_(layers[-1].bias)
        self.mlp = nn.Sequential(*layers)
        self.lc = LandmarkCompensation(D, guidance) if guidance.lc else None

    @property
    def feature_dim(self) -> int:
        return self.encoder.out_dim

    def encode_points(self, xyz: torch.Tensor) -> torch.Tensor:
        """:math:`\\phi(x_i)` ``[N, D]``; constant over frames for fixed canonical points (cache it)."""
        return self.encoder(xyz)

    def forward(
        self,
        xyz: torch.Tensor,
        audio: torch.Tensor,
        landmarks: torch.Tensor | None = None,
        blink: torch.Tensor | float | None = None,
        exp: torch.Tensor | None = None,
        point_features: torch.Tensor | None = None,
    ) -> DeformOutput:
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f"xyz must be [N, 3], got {tuple(xyz.shape)}")
        if audio.shape != (self.audio_dim,):
            raise InputError(f"audio feature must be [{self.audio_dim}] for one frame, got {tuple(audio.shape)}")
        f = self.encode_points(xyz) if point_features is None else point_features
        g = None
        if self.guidance_cfg.se or self.guidance_cfg.lc:
            if landmarks is None or landmarks.shape != (self.guidance_cfg.n_landmarks, 3):
                got = None if landmarks is None else tuple(landmarks.shape)
                raise InputError(f"SE/LC are on: landmarks [{self.guidance_cfg.n_landmarks}, 3] are needed, got {got}")
            g = self.encoder(landmarks.to(xyz))
        se_fraction = None
        if self.guidance_cfg.se:
            res = spatial_enhance(f, g, self.guidance_cfg.theta, self.guidance_cfg.select_fraction)
            F, se_fraction = res.features, res.fraction
        else:
            F = f
        kind = self.cfg.attention
        a_aud = _gate(self.aud_att(F), kind)  # [N, A]
        audio = torch.tanh(audio.to(F)) if self.cfg.bound_audio else audio.to(F)
        parts = [F, a_aud * audio]
        if self.exp_total:
            e = self._expression(blink, exp, F)
            parts.append(_gate(self.exp_att(F), kind) * e)
        out = self.mlp(torch.cat(parts, dim=-1))
        d_xyz = out[:, :3] * self.cfg.position_scale
        n = xyz.shape[0]
        if self.cfg.position_only:
            d_rot, d_scale = F.new_zeros(n, 4), F.new_zeros(n, 3)
        else:
            d_rot, d_scale = out[:, 3:7], out[:, 7:10]
        if self.lc is not None:
            cx, cr, cs, _ = self.lc(F, g)
            d_xyz = d_xyz + cx * self.cfg.position_scale
            if not self.cfg.position_only:
                d_rot, d_scale = d_rot + cr, d_scale + cs
        return DeformOutput(d_xyz, d_rot, d_scale, se_fraction, a_aud)

    def _expression(self, blink, exp, ref: torch.Tensor) -> torch.Tensor:
        vals = []
        if self.cfg.blink:
            if blink is None:
                raise InputError("this branch uses the blink signal (AU45): pass blink=")
            vals.append(torch.as_tensor(blink, dtype=ref.dtype, device=ref.device).reshape(1))
        if self.cfg.exp_dim:
            if exp is None or exp.shape != (self.cfg.exp_dim,):
                raise InputError(f"expression vector must be [{self.cfg.exp_dim}], got {None if exp is None else tuple(exp.shape)}")
            vals.append(exp.to(ref))
        return torch.cat(vals)
