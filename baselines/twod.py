"""2D family: Wav2Lip (lower-face inpainting) and IP_LAP (landmark-guided warping), simplified.

Both are *video-editing* methods: they change the mouth of an existing video of the subject.
Here the video is the training split: for each driven frame the training frame whose camera
is nearest to the driving camera is the pose source (the training poses are replayed when the
driving input has no cameras), composited over the driving background where the subject has
head masks. A square face box, fixed per subject and covering the landmarks of every training
frame, is cropped, edited at low resolution and pasted back into its lower half with a
feathered seam.

* ``wav2lip`` (Prajwal et al., ACM MM 2020): a U-Net takes the target crop with its lower half
  masked plus a reference crop of another frame (6 channels) and, at its bottleneck, the
  audio window's embedding; it outputs the crop, trained with L1 on the lower half. Wav2Lip's
  expert lip-sync discriminator loss is the ``sync_loss`` hook (see :mod:`baselines.protocol`),
  used only when the toolkit passes one: a differentiable loss of its sync scorer.
* ``ip_lap`` (Zhong et al., CVPR 2023): audio -> 68 3D landmarks (the project's per-subject
  predictor), projected with the camera; a thin-plate spline driven by the reference frame's
  landmarks moved to the predicted ones warps the reference crop (backward map, anchored at
  the upper-face landmarks and the crop corners), and a small U-Net refines the warped crop
  with the masked target, the reference and a sketch (heat map) of the target landmarks,
  trained with L1 on tracked landmarks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from baselines.common import (Adapter, Budget, audio_windows, fit_mouth_model, landmark_targets, mouth_model, n_frames_of,
                              progress_bar, project, with_generic_mouth)
from baselines.protocol import register
from lmgs.audio.encoder import AudioEncoder
from lmgs.config import AudioConfig, added_option
from lmgs.landmarks import LandmarkPredictor, fit_landmark_predictor

STANDINS = ("audio front end: the project's log-mel windows (Wav2Lip's 16 x 80 mel windows at 16 kHz, same shape)",)
JAW_MOUTH = list(range(2, 15)) + list(range(48, 68))
UPPER = list(range(17, 48))


@dataclass(frozen=True)
class TwoDBudget(Budget):
    """Training budget of a 2D baseline.

    Attributes:
        steps: optimiser steps.
        batch: crops per step.
        crop: side of the square face crop the network sees (pixels).
        width: channels of the first U-Net level.
        lr: Adam learning rate.
        sync_weight: weight of the sync loss when a scorer is available (Wav2Lip: 0.03).
        landmark_steps: audio-to-landmark predictor steps (IP_LAP).
        landmark_source: where the mouth (48-67) of IP_LAP's predicted landmarks comes from: ``subject`` (its
            predictor, fitted on the training split), ``generic`` or ``generic-tuned`` (the generic lip model of
            :mod:`lmgs.lips`, retargeted to the subject; fine-tuned on its training split), as lmgs's key.
        lip_weights: the generic lip model's weights under ``generic`` / ``generic-tuned``, as lmgs's
            ``train.lip_weights``.
    """

    steps: int = 800
    batch: int = 8
    crop: int = 48
    width: int = 16
    lr: float = 1e-3
    sync_weight: float = 0.03
    landmark_steps: int = 300
    landmark_source: str = added_option("subject")
    lip_weights: str = added_option("lips_generic.pt")

    TINY = {"steps": 250, "batch": 4, "crop": 32, "width": 16, "lr": 2e-3, "landmark_steps": 60}


SyncLoss = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``sync_loss(lower_faces [B, 3, h, w] in [0, 1], audio_windows [B, 16, 80]) -> scalar``."""


# ----------------------------------------------------------------------------- geometry of the crop
def face_box(points2d: np.ndarray, height: int, width: int, pad: float = 0.15) -> tuple[int, int, int]:
    """Square box ``(x0, y0, side)`` covering 2D points ``[T, 68, 2]`` of all frames, padded, inside the image."""
    p = points2d.reshape(-1, 2)
    lo, hi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
    side = float((hi - lo).max()) * (1 + 2 * pad)
    side = int(np.clip(np.ceil(side), 8, min(height, width)))
    c = (lo + hi) / 2
    x0 = int(np.clip(round(c[0] - side / 2), 0, width - side))
    y0 = int(np.clip(round(c[1] - side / 2), 0, height - side))
    return x0, y0, side


def crop(frames_u8: np.ndarray, box: tuple[int, int, int], size: int) -> torch.Tensor:
    """uint8 ``[T, H, W, 3]`` -> float ``[T, 3, size, size]`` crops in [0, 1]."""
    x0, y0, s = box
    c = torch.from_numpy(np.ascontiguousarray(frames_u8[:, y0 : y0 + s, x0 : x0 + s])).permute(0, 3, 1, 2).float() / 255
    return F.interpolate(c, size=(size, size), mode="bilinear", align_corners=False, antialias=True)


def lower_mask(size: int, device=None) -> torch.Tensor:
    """``[1, 1, size, size]`` weights: 1 on the lower half, feathered at the middle and the sides."""
    y = (torch.arange(size, device=device).float() + 0.5) / size
    rows = ((y - 0.45) / 0.1).clamp(0, 1)
    cols = torch.minimum(y / 0.12, (1 - y) / 0.12).clamp(0, 1)
    return (rows[:, None] * cols[None, :])[None, None]


def paste(frame: np.ndarray, crop_img: torch.Tensor, box: tuple[int, int, int]) -> np.ndarray:
    """Blend a crop ``[3, s, s]`` back into the lower half of the box of a uint8 frame."""
    x0, y0, s = box
    up = F.interpolate(crop_img[None], size=(s, s), mode="bilinear", align_corners=False)[0]
    m = lower_mask(s, up.device)[0]
    base = torch.from_numpy(frame[y0 : y0 + s, x0 : x0 + s]).permute(2, 0, 1).float().to(up.device) / 255
    out = frame.copy()
    blend = torch.nan_to_num(up * m + base * (1 - m), nan=0.0).clamp(0, 1)
    out[y0 : y0 + s, x0 : x0 + s] = (blend.permute(1, 2, 0) * 255 + 0.5).to(torch.uint8).cpu().numpy()
    return out


# ----------------------------------------------------------------------------- networks
class UNet(nn.Module):
    """Three-level U-Net with an optional condition vector broadcast at the bottleneck."""

    def __init__(self, in_ch: int, width: int, cond_dim: int = 0):
        super().__init__()

        def block(a, b, stride):
            return nn.Sequential(nn.Conv2d(a, b, 3, stride, 1), nn.LeakyReLU(0.2), nn.Conv2d(b, b, 3, 1, 1), nn.LeakyReLU(0.2))

        w = width
        self.e1, self.e2, self.e3 = block(in_ch, w, 1), block(w, 2 * w, 2), block(2 * w, 4 * w, 2)
        self.mid = block(4 * w + cond_dim, 4 * w, 1)
        self.d2 = block(4 * w + 2 * w, 2 * w, 1)
        self.d1 = block(2 * w + w, w, 1)
        self.out = nn.Conv2d(w, 3, 1)

    def forward(self, x: torch.Tensor, cond: torch.Tensor | None = None) -> torch.Tensor:
        h1 = self.e1(x)
        h2 = self.e2(h1)
        h3 = self.e3(h2)
        if cond is not None:
            h3 = torch.cat([h3, cond[:, :, None, None].expand(-1, -1, *h3.shape[2:])], 1)
        h = self.mid(h3)
        h = self.d2(torch.cat([F.interpolate(h, size=h2.shape[2:], mode="nearest"), h2], 1))
        h = self.d1(torch.cat([F.interpolate(h, size=h1.shape[2:], mode="nearest"), h1], 1))
        return torch.sigmoid(self.out(h))


class Wav2LipNet(nn.Module):
    """Masked target + reference crops (6 channels) and an audio window -> the crop."""

    def __init__(self, in_channels: int, window: int, width: int, box, crop_size: int):
        super().__init__()
        self.audio = AudioEncoder(in_channels, window, AudioConfig(dim=64, use_smoother=False))
        self.unet = UNet(6, width, cond_dim=64)
        self.box, self.crop_size = tuple(int(v) for v in box), int(crop_size)

    def forward(self, target_crop: torch.Tensor, ref_crop: torch.Tensor, windows: torch.Tensor) -> torch.Tensor:
        masked = target_crop * (1 - (lower_mask(target_crop.shape[-1], target_crop.device) > 0).float())
        return self.unet(torch.cat([masked, ref_crop], 1), self.audio(windows))


def tps_backward_grid(dst: torch.Tensor, src: torch.Tensor, size: int, reg: float = 1e-3) -> torch.Tensor:
    """Thin-plate spline mapping output points ``dst`` onto ``src``, sampled on a grid.

    Solves :math:`f(p) = a_0 + a_1 x + a_2 y + \\sum_i w_i U(\\|p - d_i\\|)`, :math:`U(r) = r^2 \\log r^2`,
    with :math:`f(d_i) = s_i` (Bookstein 1989; small ridge ``reg`` on the kernel), and returns
    ``f`` on the ``size x size`` pixel grid as a ``grid_sample`` grid ``[B, size, size, 2]``.

    Args:
        dst, src: ``[B, K, 2]`` control points in normalised crop coordinates ``[-1, 1]``.
    """
    B, K, _ = dst.shape

    def U(a, b):
        r2 = ((a[:, :, None] - b[:, None]) ** 2).sum(-1)
        return r2 * torch.log(r2 + 1e-9)

    P = torch.cat([torch.ones(B, K, 1, dtype=dst.dtype, device=dst.device), dst], -1)
    L = torch.zeros(B, K + 3, K + 3, dtype=dst.dtype, device=dst.device)
    L[:, :K, :K] = U(dst, dst) + reg * torch.eye(K, dtype=dst.dtype, device=dst.device)
    L[:, :K, K:] = P
    L[:, K:, :K] = P.transpose(1, 2)
    rhs = torch.cat([src, torch.zeros(B, 3, 2, dtype=dst.dtype, device=dst.device)], 1)
    params = torch.linalg.solve(L, rhs)  # [B, K + 3, 2]
    g = (torch.arange(size, dtype=dst.dtype, device=dst.device) + 0.5) / size * 2 - 1
    gy, gx = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack([gx, gy], -1).reshape(1, -1, 2).expand(B, -1, -1)
    Pg = torch.cat([torch.ones(B, pts.shape[1], 1, dtype=dst.dtype, device=dst.device), pts], -1)
    out = U(pts, dst) @ params[:, :K] + Pg @ params[:, K:]
    return out.view(B, size, size, 2)


class IPLAPNet(nn.Module):
    """Landmark-driven TPS warp of the reference crop + a refinement U-Net; owns the landmark predictor."""

    def __init__(self, in_channels: int, window: int, width: int, box, crop_size: int, n_components: int):
        super().__init__()

        self.predictor = LandmarkPredictor(in_channels, window, n_components)
        self.unet = UNet(10, width)
        self.box, self.crop_size = tuple(int(v) for v in box), int(crop_size)

    def sketch(self, lms: torch.Tensor, size: int) -> torch.Tensor:
        """IP_LAP's landmark sketch, as a heat map ``[B, 1, size, size]`` of the jaw and mouth points."""
        p = self.to_crop(lms)[:, JAW_MOUTH]  # [B, K, 2]
        g = (torch.arange(size, dtype=p.dtype, device=p.device) + 0.5) / size * 2 - 1
        dx = (g[None, None, :] - p[..., 0:1]) ** 2  # [B, K, size]
        dy = (g[None, None, :] - p[..., 1:2]) ** 2
        s2 = (3.0 / size) ** 2
        heat = torch.exp(-(dy[..., :, None] + dx[..., None, :]) / s2).amax(1)
        return heat[:, None]

    def to_crop(self, pts2d: torch.Tensor) -> torch.Tensor:
        """Pixel points -> normalised crop coordinates in [-1, 1]."""
        x0, y0, s = self.box
        return (pts2d - torch.tensor([x0, y0], dtype=pts2d.dtype, device=pts2d.device)) / s * 2 - 1

    def warp(self, ref_crop: torch.Tensor, ref_lms: torch.Tensor, target_lms: torch.Tensor) -> torch.Tensor:
        """Move the reference's jaw and mouth landmarks onto the target's; the upper face and the crop corners stay."""
        B = ref_crop.shape[0]
        corners = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [0.0, -1.0], [0.0, 1.0], [-1.0, 0.0], [1.0, 0.0]],
                               dtype=ref_crop.dtype, device=ref_crop.device).expand(B, -1, -1)
        r, t = self.to_crop(ref_lms), self.to_crop(target_lms)
        dst = torch.cat([t[:, JAW_MOUTH], r[:, UPPER], corners], 1)
        src = torch.cat([r[:, JAW_MOUTH], r[:, UPPER], corners], 1)
        grid = tps_backward_grid(dst, src, ref_crop.shape[-1])
        return F.grid_sample(ref_crop, grid, mode="bilinear", padding_mode="border", align_corners=False)

    def forward(self, target_crop, ref_crop, ref_lms, target_lms) -> torch.Tensor:
        warped = self.warp(ref_crop, ref_lms, target_lms)
        masked = target_crop * (1 - (lower_mask(target_crop.shape[-1], target_crop.device) > 0).float())
        return self.unet(torch.cat([warped, masked, ref_crop, self.sketch(target_lms, target_crop.shape[-1])], 1))


# ----------------------------------------------------------------------------- adapters
class TwoDMethod(Adapter):
    """Shared fit-time reference video, retrieval by camera and pasting."""

    budget_cls = TwoDBudget
    family = "2D"
    standins = STANDINS

    def fit(self, clip, *, seed: int, workdir, progress: bool = True) -> None:
        # The reference video (the training split) is input data, not model weights: kept, not saved.
        self.ref_frames = clip.frames
        self.ref_w2c = np.asarray(clip.w2c, np.float32)
        self.ref_head = clip.head_masks
        self.intr = (clip.focal, clip.cx, clip.cy)
        self.ref_lms3d = landmark_targets(clip) if (clip.landmarks3d is not None or clip.landmarks2d is not None) else None
        super().fit(clip, seed=seed, workdir=workdir, progress=progress)

    def _points2d(self, clip) -> np.ndarray:
        if clip.landmarks2d is not None:
            return np.asarray(clip.landmarks2d, np.float32)
        lms = landmark_targets(clip)
        return np.stack([project(lms[i], clip.w2c[i], clip.focal, clip.cx, clip.cy) for i in range(len(clip))]).astype(np.float32)

    def _nearest(self, w2c: np.ndarray | None, t: int) -> int:
        if w2c is None:
            return t % len(self.ref_frames)
        d = np.abs(self.ref_w2c[:, :3, :4] - w2c[None, :3, :4]).sum((1, 2))
        return int(np.argmin(d))

    def _base(self, driving, j: int, t: int) -> np.ndarray:
        frame = self.ref_frames[j]
        if driving.backgrounds is not None and self.ref_head is not None:
            b = driving.backgrounds[t if driving.backgrounds.shape[0] > 1 else 0]
            frame = np.where(self.ref_head[j][..., None], frame, b)
        return np.ascontiguousarray(frame)

    def _train_crops(self, crops: torch.Tensor, params, rng: np.random.Generator, predict, progress: bool,
                     extra_loss=None) -> None:
        """The 2D methods' training loop: ``steps`` Adam steps, each on ``batch`` target crops ``i``
        drawn at random and as many reference crops ``j``, with L1 to the target weighted towards
        its lower half (``0.2 +`` :func:`lower_mask`). ``predict(i, j)`` gives the network's crops;
        ``extra_loss(pred, i)``, when given, adds to the loss."""
        b, n = self.cfg, len(crops)
        opt = torch.optim.Adam(params, lr=b.lr)
        m = lower_mask(b.crop, crops.device)
        bar = progress_bar(b.steps, f"{self.name} fit", progress)
        for _ in range(b.steps):
            i = torch.from_numpy(rng.integers(0, n, size=b.batch)).to(crops.device)
            j = torch.from_numpy(rng.integers(0, n, size=b.batch)).to(crops.device)
            pred = predict(i, j)
            loss = ((pred - crops[i]).abs() * (0.2 + m)).mean()
            if extra_loss is not None:
                loss = loss + extra_loss(pred, i)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()

    @torch.no_grad()
    def render(self, driving) -> np.ndarray:
        """Each driven frame: the nearest training frame (:meth:`_base`), its face box edited by
        :meth:`_edit` and pasted back into its lower half."""
        self._check_fitted()
        m = self.model
        dev = next(m.parameters()).device
        n = n_frames_of(driving)
        H, W = self.ref_frames.shape[1:3]
        out = np.empty((n, H, W, 3), np.uint8)
        if n == 0:
            return out
        audio = self._audio(m, audio_windows(driving.audio, n).to(dev))
        for t in range(n):
            w2c = None if driving.w2c is None else np.asarray(driving.w2c[t], np.float32)
            j = self._nearest(w2c, t)
            base = self._base(driving, j, t)
            out[t] = paste(base, self._edit(m, dev, base, audio, w2c, j, t), m.box)
        return out

    def _audio(self, model, windows: torch.Tensor):  # pragma: no cover - abstract
        """What :meth:`_edit` reads of the driving audio windows ``[T, 16, 80]``."""
        raise NotImplementedError

    def _edit(self, model, dev, base: np.ndarray, audio, w2c: np.ndarray | None, j: int, t: int) -> torch.Tensor:  # pragma: no cover
        """The edited face crop ``[3, s, s]`` of frame ``t`` (``base``: training frame ``j`` over the driving background)."""
        raise NotImplementedError


@register("wav2lip")
class Wav2Lip(TwoDMethod):
    name = "wav2lip"
    display_name = "Wav2Lip"
    description = (
        "Kept: lower-face inpainting: a U-Net sees the target face crop with its lower half masked and a reference crop "
        "of another frame, plus the audio window's embedding at its bottleneck, and is trained with L1 to produce the "
        "lower half, which is pasted back into the source video (here: the training frame nearest to the driving "
        "camera). Simplified: a fixed face box per subject instead of per-frame detection, a small U-Net at low "
        "resolution, no GAN loss; the expert lip-sync loss is used only when the project's scorer provides a "
        "differentiable sync_loss ({sync})."
    )

    hooks = ("sync_loss",)

    def __init__(self, preset: str = "quick", device: str | None = None, sync_loss: SyncLoss | None = None, **overrides):
        super().__init__(preset, device, **overrides)
        self.sync_loss = sync_loss  # the toolkit's hook (see baselines.protocol); None: no sync loss

    def config(self) -> dict:
        return {**super().config(), "sync_loss": self.sync_loss is not None and self.cfg.sync_weight > 0}

    def describe(self):
        info = super().describe()
        sync = "on" if self.config()["sync_loss"] else "off: the project's sync scorer provides no differentiable sync_loss"
        return type(info)(**{**info.__dict__, "description": info.description.replace("{sync}", sync)})

    def _build(self, build: dict) -> Wav2LipNet:
        return Wav2LipNet(**build)

    def _train(self, clip, seed: int, progress: bool):
        dev, rng, n, feats = self._start(clip, seed)
        b = self.cfg
        box = face_box(self._points2d(clip), clip.height, clip.width)
        crops = crop(clip.frames, box, b.crop).to(dev)
        build = {"in_channels": int(feats.shape[2]), "window": int(feats.shape[1]), "width": b.width, "box": list(box), "crop_size": b.crop}
        model = Wav2LipNet(**build).to(dev)
        model.audio.fit_normalization(feats)
        sync = self.sync_loss if b.sync_weight > 0 else None
        extra = None if sync is None else (lambda pred, i: b.sync_weight * sync(pred[:, :, b.crop // 2 :], feats[i]))
        self._train_crops(crops, model.parameters(), rng, lambda i, j: model(crops[i], crops[j], feats[i]), progress, extra)
        return model, build

    def _audio(self, model, windows: torch.Tensor) -> torch.Tensor:
        return windows

    def _edit(self, model, dev, base, audio, w2c, j, t) -> torch.Tensor:
        c = crop(base[None], model.box, model.crop_size).to(dev)
        return model(c, c, audio[t : t + 1])[0]


@register("ip_lap", lip_model=True)
class IPLAP(TwoDMethod):
    name = "ip_lap"
    display_name = "IP_LAP"
    description = (
        "Kept: the two stages audio -> landmarks -> landmark-guided rendering: 68 3D landmarks predicted from audio are "
        "projected with the camera, a thin-plate spline moving the reference frame's jaw and mouth landmarks onto the "
        "predicted ones (upper face and crop corners anchored) warps the reference crop, and a U-Net refines it with "
        "the masked target and the reference (L1). Simplified: the audio-to-landmark stage is the project's "
        "per-subject temporal CNN (not IP_LAP's transformer with a pose/reference prior), one reference frame (the "
        "nearest camera) instead of several, TPS warping of pixels instead of learned feature-space flow, no GAN or "
        "perceptual loss, a fixed face box; low-resolution crop."
    )
    standins = STANDINS + (
        "audio-to-landmark: the project's per-subject temporal CNN trained on the training split (IP_LAP's pretrained transformer cannot be had offline)",
    )

    reads_landmarks = True

    def _build(self, build: dict) -> IPLAPNet:
        args, lips = mouth_model(build)
        net = IPLAPNet(**args)
        net.lips = lips  # lmgs.lips.RetargetedLips (not a submodule: its weights are the shipped file's or in build)
        return net

    def _lms2d(self, lms3d: np.ndarray, w2c: np.ndarray) -> np.ndarray:
        return np.stack([project(lms3d[k], w2c[k], *self.intr) for k in range(len(lms3d))]).astype(np.float32)

    def _train(self, clip, seed: int, progress: bool):
        dev, rng, n, feats = self._start(clip, seed)
        b = self.cfg
        targets = landmark_targets(clip)
        lms2d = torch.from_numpy(self._lms2d(targets, np.asarray(clip.w2c, np.float32))).to(dev)
        box = face_box(lms2d.cpu().numpy(), clip.height, clip.width)
        predictor = fit_landmark_predictor(feats, torch.from_numpy(targets).to(dev), steps=b.landmark_steps, seed=seed)
        build = {"in_channels": int(feats.shape[2]), "window": int(feats.shape[1]), "width": b.width, "box": list(box),
                 "crop_size": b.crop, "n_components": predictor.n_components}
        lips = fit_mouth_model(b.landmark_source, clip, targets, seed, b.lip_weights)
        if lips is not None:
            build["lips"] = lips
        model = self._build(build).to(dev)
        model.predictor.load_state_dict(predictor.state_dict())
        model.predictor.requires_grad_(False)
        crops = crop(clip.frames, box, b.crop).to(dev)
        self._train_crops(crops, model.unet.parameters(), rng, lambda i, j: model(crops[i], crops[j], lms2d[j], lms2d[i]),
                          progress)
        return model, build

    def _audio(self, model, windows: torch.Tensor) -> np.ndarray:
        lms = model.predictor.predict(windows)  # the predicted 3D landmarks
        return with_generic_mouth(getattr(model, "lips", None), lms, windows).cpu().numpy()

    def _edit(self, model, dev, base, audio, w2c, j, t) -> torch.Tensor:
        cam = self.ref_w2c[j] if w2c is None else w2c
        target = torch.from_numpy(project(audio[t], cam, *self.intr)[None].astype(np.float32)).to(dev)
        ref = torch.from_numpy(project(self.ref_lms3d[j], self.ref_w2c[j], *self.intr)[None].astype(np.float32)).to(dev)
        c = crop(base[None], model.box, model.crop_size).to(dev)
        rc = crop(self.ref_frames[j][None], model.box, model.crop_size).to(dev)
        return model(c, rc, ref, target)[0]
