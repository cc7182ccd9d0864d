"""The paper's lightweight Audio Encoder and the field's attention smoother.

Audio Encoder (paper, "Audio Net"): a sliding window of size 2 over the per-frame feature
steps, reshaped so each position carries two neighbouring steps; four stacked 1D
convolutions compress it along time; the channel dimension is flattened and a linear layer
projects it to the compact :math:`F_a`. The four stride-2 convolutions and the final
projection follow ER-NeRF's ``AudioNet`` (Li et al., ICCV 2023), which the paper's
description mirrors.

Attention smoother (AD-NeRF's ``AudioAttNet``, Guo et al., ICCV 2021; used by ER-NeRF and
TalkingGaussian): for frame :math:`i` it looks at :math:`F_a` of frames
:math:`i-4 \\ldots i+3` (zero-padded at the ends), predicts one weight per frame with 1D
convolutions and a linear layer, and returns the softmax-weighted sum

.. math::

    \\bar F_a^i = \\sum_{t=0}^{7} \\alpha_t F_a^{i-4+t}, \\qquad
    \\alpha = \\mathrm{softmax}\\big(\\mathrm{Linear}(\\mathrm{Conv}(F_a^{i-4:i+4}))\\big).
"""

from __future__ import annotations

import torch
from torch import nn

from lmgs.config import AudioConfig
from lmgs.errors import InputError


def sliding_pairs(x: torch.Tensor) -> torch.Tensor:
    """Sliding window of size 2 (stride 1) over the step axis: ``[N, W, C] -> [N, max(W-1,1), 2C]``.

    Position :math:`t` holds :math:`[x_t \\| x_{t+1}]`; a one-step window pairs the step with itself.
    """
    if x.shape[1] == 1:
        return torch.cat([x, x], dim=-1)
    return torch.cat([x[:, :-1], x[:, 1:]], dim=-1)


class AudioEncoder(nn.Module):
    """Per-frame windows ``[N, W, C]`` -> compact audio features :math:`F_a` ``[N, dim]``.

    The input is standardised per channel with statistics set by :meth:`fit_normalization`
    (identity until then), so log-mel, DeepSpeech logits and WavLM features enter at one scale.

    Args:
        in_channels: C of the front end.
        window: W, steps per frame window (16 for log-mel and DeepSpeech, 2 for HuBERT).
        cfg: ``encoder_channels`` (four conv widths), ``dim``; ``use_encoder=False`` replaces the
            conv stack by the window mean and one linear layer (the paper's "w/o Audio Encoder").
    """

    def __init__(self, in_channels: int, window: int, cfg: AudioConfig = AudioConfig()):
        super().__init__()
        if window < 1 or in_channels < 1:
            raise InputError(f"audio encoder needs window >= 1 and channels >= 1, got {window}, {in_channels}")
        if len(cfg.encoder_channels) != 4:
            raise InputError(f"encoder_channels must have 4 entries, got {cfg.encoder_channels}")
        self.in_channels = int(in_channels)
        self.window = int(window)
        self.cfg = cfg
        self.register_buffer("mean", torch.zeros(in_channels))
        self.register_buffer("std", torch.ones(in_channels))
        if cfg.use_encoder:
            layers, c_in = [], 2 * in_channels
            for c in cfg.encoder_channels:
                layers += [nn.Conv1d(c_in, c, kernel_size=3, stride=2, padding=1), nn.LeakyReLU(0.02)]
                c_in = c
            self.convs = nn.Sequential(*layers)
            length = max(window - 1, 1)  # W steps give W-1 pairs ...
            for _ in range(4):
                length = (length + 1) // 2  # ... halved (ceil) by each stride-2 convolution
            self.proj = nn.Sequential(nn.Linear(c_in * length, cfg.dim * 2), nn.LeakyReLU(0.02), nn.Linear(cfg.dim * 2, cfg.dim))
        else:
            self.convs = None
            self.proj = nn.Linear(in_channels, cfg.dim)

    @torch.no_grad()
    def fit_normalization(self, features: torch.Tensor) -> None:
        """Set the per-channel mean and std from training features ``[N, W, C]``."""
        f = features.reshape(-1, features.shape[-1]).to(self.mean)
        self.mean.copy_(f.mean(0))
        self.std.copy_(f.std(0).clamp_min(1e-6) if f.shape[0] > 1 else torch.ones_like(self.std))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 3 or x.shape[1:] != (self.window, self.in_channels):
            raise InputError(
                f"audio encoder expects [N, {self.window}, {self.in_channels}] features, got shape {tuple(x.shape)}"
            )
        x = (x.to(self.mean) - self.mean) / self.std
        if self.convs is None:
            return self.proj(x.mean(dim=1))
        h = sliding_pairs(x).transpose(1, 2)  # [N, 2C, W-1]
        h = self.convs(h)  # [N, c4, L]
        return self.proj(h.flatten(1))


def frame_windows(seq: torch.Tensor, size: int = 8, index: torch.Tensor | None = None) -> torch.Tensor:
    """Windows ``seq[i - size/2 : i + size/2]`` of a per-frame sequence, zero-padded.

    Args:
        seq: ``[N, D]`` per-frame features.
        size: window length (8: frames i-4 ... i+3, as AD-NeRF / ER-NeRF).
        index: ``[B]`` frame indices; default all frames.

    Returns:
        ``[B, size, D]``.
    """
    n = seq.shape[0]
    idx = torch.arange(n, device=seq.device) if index is None else index.to(seq.device).long()
    offs = torch.arange(size, device=seq.device) - size // 2
    pos = idx[:, None] + offs[None]  # [B, size]
    valid = (pos >= 0) & (pos < n)
    out = seq[pos.clamp(0, max(n - 1, 0))]
    return out * valid.unsqueeze(-1).to(seq.dtype)


class AudioSmoother(nn.Module):
    """Attention over neighbouring frames (AD-NeRF ``AudioAttNet``): ``[B, S, D] -> [B, D]``.

    Five 1D convolutions (D -> 16 -> 8 -> 4 -> 2 -> 1, kernel 3) score each frame of the
    window, a linear layer mixes the S scores, a softmax makes them weights summing to one.
    """

    def __init__(self, dim: int, seq_len: int = 8):
        super().__init__()
        self.seq_len = int(seq_len)
        chans = [dim, 16, 8, 4, 2, 1]
        layers = []
        for a, b in zip(chans[:-1], chans[1:]):
            layers += [nn.Conv1d(a, b, kernel_size=3, padding=1), nn.LeakyReLU(0.02)]
        self.score = nn.Sequential(*layers)
        self.mix = nn.Linear(self.seq_len, self.seq_len)

    def weights(self, x: torch.Tensor) -> torch.Tensor:
        """Attention weights ``[B, S]`` (non-negative, summing to 1)."""
        if x.ndim != 3 or x.shape[1] != self.seq_len:
            raise InputError(f"smoother expects [B, {self.seq_len}, D] windows, got shape {tuple(x.shape)}")
        s = self.score(x.transpose(1, 2)).squeeze(1)  # [B, S]
        return torch.softmax(self.mix(s), dim=-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (self.weights(x).unsqueeze(-1) * x).sum(dim=1)


class AudioNet(nn.Module):
    """Audio Encoder + attention smoother: per-frame windows -> smoothed :math:`F_a` per frame.

    ``AudioNet(C, W, cfg)``; ``forward(features [N, W, C], index [B] | None) -> [B, dim]``: encodes every frame (the
    smoother needs the neighbours), then smooths frames ``index`` (all by default).
    """

    def __init__(self, in_channels: int, window: int, cfg: AudioConfig = AudioConfig()):
        super().__init__()
        self.cfg = cfg
        self.encoder = AudioEncoder(in_channels, window, cfg)
        self.smoother = AudioSmoother(cfg.dim, cfg.smooth_frames) if cfg.use_smoother else None

    @property
    def out_dim(self) -> int:
        return self.cfg.dim

    def encode(self, features: torch.Tensor) -> torch.Tensor:
        """Unsmoothed :math:`F_a` ``[N, dim]``."""
        return self.encoder(features)

    def forward(self, features: torch.Tensor, index: torch.Tensor | None = None) -> torch.Tensor:
        if self.smoother is None:
            fa = self.encoder(features if index is None else features[index.long().to(features.device, non_blocking=True)])
            return fa
        if index is not None:
            # only the frames inside the windows of ``index`` need encoding; which frames those are is
            # worked out where ``index`` lies (an index on the CPU: without waiting for a GPU) and sent over
            idx = index.long()
            need = torch.unique(frame_windows_index(idx, features.shape[0], self.smoother.seq_len))
            idx, need = idx.to(features.device, non_blocking=True), need.to(features.device, non_blocking=True)
            fa_all = features.new_zeros(features.shape[0], self.cfg.dim)
            fa_all[need] = self.encoder(features[need])
            return self.smoother(frame_windows(fa_all, self.smoother.seq_len, idx))
        return self.smoother(frame_windows(self.encoder(features), self.smoother.seq_len))


def frame_windows_index(index: torch.Tensor, n: int, size: int) -> torch.Tensor:
    """Valid frame indices covered by the windows of ``index`` (flat)."""
    pos = index[:, None] + torch.arange(size, device=index.device)[None] - size // 2
    return pos[(pos >= 0) & (pos < n)]

