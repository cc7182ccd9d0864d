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
For inference, :meth:`DeformNet.prepare` goes further: every layer that reads only
:math:`F_i` is linear in it up to its first activation, and :math:`F_i = f_i` except for the
points Spatial Enhancement selects, so the first layers' products with :math:`f_i` (and the
attention gates of unselected points, and of every point without SE) are computed once per
clip; a frame then computes the selected points' share (:math:`g_{j^*_i} W^\\top`, one
product per keypoint) and the layers after the first activations
(:meth:`DeformNet.forward_prepared`; equal to :meth:`DeformNet.forward` up to float rounding).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from lmgs.config import DeformConfig, GuidanceConfig, TriplaneConfig
from lmgs.encoders.triplane import TriplaneEncoder
from lmgs.errors import InputError
from lmgs.guidance import LandmarkCompensation, select_points, selected_share, spatial_enhance, unit_rows


def select_by_mask(device: torch.device) -> bool:
    """Whether :meth:`DeformNet.forward_prepared` applies Spatial Enhancement's selection to every row
    by masks (on a GPU: picking the selected rows would first read back how many there are) rather
    than computing the selected rows alone (on the CPU: less work). Both give the same offsets."""
    return device.type != "cpu"


@dataclass(frozen=True)
class DeformOutput:
    """Per-Gaussian offsets of one frame.

    Attributes:
        d_xyz: ``[N, 3]`` position offsets.
        d_rot: ``[N, 4]`` quaternion offsets (added before normalisation); zeros in position-only mode.
        d_scale: ``[N, 3]`` log-scale offsets; zeros in position-only mode.
        se_fraction: share of points Spatial Enhancement selected, a 0-d tensor on the points'
            device (``float()`` reads it back; ``None`` when SE is off).
        audio_attention: ``[N, A]`` the audio gates (for region-attention visualisation).
    """

    d_xyz: torch.Tensor
    d_rot: torch.Tensor
    d_scale: torch.Tensor
    se_fraction: torch.Tensor | None
    audio_attention: torch.Tensor


@dataclass(frozen=True)
class PreparedPoints:
    """What :meth:`DeformNet.prepare` computes once per clip for fixed canonical points.

    Attributes:
        f: ``[N, D]`` point features :math:`\\phi(x_i)`.
        f_unit: ``[N, D]`` the same over their norms (Spatial Enhancement's similarities), or None.
        base: for each first layer that reads :math:`F_i` (:meth:`DeformNet._first_layers`),
            ``[N, out]`` its F-columns times :math:`f_i` plus its bias.
        a_aud, a_exp: ``[N, A]`` / ``[N, E]`` the attention gates of :math:`f_i` (the gates of
            every point without SE, of the unselected ones with it); ``a_exp`` None without expression.
    """

    f: torch.Tensor
    f_unit: torch.Tensor | None
    base: dict[str, torch.Tensor]
    a_aud: torch.Tensor
    a_exp: torch.Tensor | None
    w_first: torch.Tensor
    slices: dict[str, slice]


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
            F, se_fraction = res.features, selected_share(res.selected)
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

    # ------------------------------------------------------------------ inference
    def _first_layers(self) -> list[tuple[str, nn.Linear]]:
        """The first layers that read :math:`F_i` (their first D input columns do)."""
        out = [("aud", self.aud_att[0])]
        if self.exp_att is not None:
            out.append(("exp", self.exp_att[0]))
        out.append(("mlp", self.mlp[0]))
        if self.lc is not None:
            out += [("off", self.lc.offset[0]), ("tau", self.lc.tau[0])]
        return out

    @torch.no_grad()
    def prepare(self, xyz: torch.Tensor, point_features: torch.Tensor | None = None) -> PreparedPoints:
        """The per-point work of :meth:`forward` that does not change from frame to frame."""
        f = self.encode_points(xyz) if point_features is None else point_features
        d, layers = self.feature_dim, self._first_layers()
        base = {name: torch.addmm(lin.bias, f, lin.weight[:, :d].T) for name, lin in layers}
        kind = self.cfg.attention
        a_aud = _gate(self.aud_att[1:](base["aud"]), kind)
        a_exp = _gate(self.exp_att[1:](base["exp"]), kind) if self.exp_att is not None else None
        bounds = np.cumsum([0] + [lin.out_features for _, lin in layers])
        slices = {name: slice(int(a), int(b)) for (name, _), a, b in zip(layers, bounds[:-1], bounds[1:])}
        w_first = torch.cat([lin.weight[:, :d] for _, lin in layers])
        return PreparedPoints(f, unit_rows(f) if self.guidance_cfg.se else None, base, a_aud, a_exp, w_first, slices)

    @torch.no_grad()
    def forward_prepared(
        self,
        prep: PreparedPoints,
        audio: torch.Tensor,
        landmarks: torch.Tensor | None = None,
        blink: torch.Tensor | float | None = None,
        exp: torch.Tensor | None = None,
    ) -> DeformOutput:
        """:meth:`forward` for one frame from :meth:`prepare`'s parts (inference: no gradients)."""
        if audio.shape != (self.audio_dim,):
            raise InputError(f"audio feature must be [{self.audio_dim}] for one frame, got {tuple(audio.shape)}")
        gcfg, kind, d = self.guidance_cfg, self.cfg.attention, self.feature_dim
        a_aud, a_exp, base = prep.a_aud, prep.a_exp, prep.base
        g = idx = None
        extra: dict[str, torch.Tensor] = {}
        se_fraction = None
        if gcfg.se or gcfg.lc:
            if landmarks is None or landmarks.shape != (gcfg.n_landmarks, 3):
                got = None if landmarks is None else tuple(landmarks.shape)
                raise InputError(f"SE/LC are on: landmarks [{gcfg.n_landmarks}, 3] are needed, got {got}")
            g = self.encoder(landmarks.to(prep.f))
        if gcfg.se:
            selected, match, _ = select_points(prep.f_unit @ unit_rows(g).T, gcfg.theta, gcfg.select_fraction)
            se_fraction = selected_share(selected)
            gw = g @ prep.w_first.T  # F_i = f_i + g_j* on the selected rows: each first layer gains g_j* W^T there
            if not select_by_mask(prep.f.device):  # the selected rows alone
                idx = selected.nonzero()[:, 0]
                if len(idx):
                    gw = gw[match[idx]]
                    extra = {name: gw[:, sl] for name, sl in prep.slices.items()}
                    a_aud = a_aud.clone()
                    a_aud[idx] = _gate(self.aud_att[1:](base["aud"][idx] + extra["aud"]), kind)
                    if a_exp is not None:
                        a_exp = a_exp.clone()
                        a_exp[idx] = _gate(self.exp_att[1:](base["exp"][idx] + extra["exp"]), kind)
            else:  # every row, the selection applied by masks: no read-back of how many rows were selected
                sel = selected[:, None]
                gw = gw[match] * sel.to(gw.dtype)
                extra = {name: gw[:, sl] for name, sl in prep.slices.items()}
                a_aud = torch.where(sel, _gate(self.aud_att[1:](base["aud"] + extra["aud"]), kind), a_aud)
                if a_exp is not None:
                    a_exp = torch.where(sel, _gate(self.exp_att[1:](base["exp"] + extra["exp"]), kind), a_exp)

        def first(name: str, h: torch.Tensor) -> torch.Tensor:
            if not extra:
                return h
            if idx is None:
                return h + extra[name]
            h[idx] += extra[name]
            return h

        audio = torch.tanh(audio.to(prep.f)) if self.cfg.bound_audio else audio.to(prep.f)
        # mlp(cat[F, a_aud * audio, a_exp * e]) with its first layer split by input columns
        w0 = self.mlp[0].weight
        h = first("mlp", torch.addmm(base["mlp"], a_aud, (w0[:, d : d + self.audio_dim] * audio).T))
        if self.exp_total:
            h = torch.addmm(h, a_exp * self._expression(blink, exp, prep.f), w0[:, d + self.audio_dim :].T)
        out = self.mlp[1:](h)
        d_xyz = out[:, :3] * self.cfg.position_scale
        n = prep.f.shape[0]
        if self.cfg.position_only:
            d_rot, d_scale = prep.f.new_zeros(n, 4), prep.f.new_zeros(n, 3)
        else:
            d_rot, d_scale = out[:, 3:7], out[:, 7:10]
        if self.lc is not None:
            c = self.lc.condition(g)
            h_off = first("off", base["off"] + self.lc.offset[0].weight[:, d:] @ c)
            h_tau = first("tau", base["tau"] + self.lc.tau[0].weight[:, d:] @ c)
            act = torch.sigmoid if self.lc.cfg.tau_activation == "sigmoid" else torch.tanh
            comp = self.lc.offset[1:](h_off) * act(self.lc.tau[1:](h_tau))
            d_xyz = d_xyz + comp[:, :3] * self.cfg.position_scale
            if not self.cfg.position_only:
                d_rot, d_scale = d_rot + comp[:, 3:7], d_scale + comp[:, 7:10]
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
