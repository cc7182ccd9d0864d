"""The four NeRF adapters (``adnerf``, ``radnerf``, ``ernerf``, ``geneface``): budget, training
on the clip's rays and full-frame rendering (see :mod:`baselines.nerf`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from baselines.common import (
    Adapter,
    Budget,
    audio_windows,
    driving_background,
    driving_w2c,
    fit_mouth_model,
    head_box,
    landmark_targets,
    mean_background,
    mouth_model,
    n_frames_of,
    progress_bar,
    to_u8,
    with_generic_mouth,
)
from baselines.nerf.field import NeRFHead
from baselines.nerf.rays import STOP_TRANSMITTANCE, box_hits, camera_rays, march_rays, render_rays
from baselines.protocol import register
from lmgs.config import added_option
from lmgs.landmarks import fit_landmark_predictor

STANDINS = ("audio front end: the project's log-mel windows (DeepSpeech / HuBERT features cannot be had offline)",)


@dataclass(frozen=True)
class NeRFBudget(Budget):
    """Training and rendering budget of a NeRF baseline (each field's meaning under it)."""

    steps: int = 1500
    """Optimiser steps (one training frame per step)."""
    rays: int = 1024
    """Random rays per step (drawn among the rays that cross the head box)."""
    head_share: float = 0.75
    """Share of those rays drawn from the pixels where the frame differs from its background (the
    head; AD-NeRF likewise samples the head region more): without it, a head that covers a small
    part of the box lets the density collapse to zero everywhere."""
    samples: int = 32
    """Stratified samples per ray."""
    hidden: int = 64
    """Width of the field MLP."""
    lr: float = 5e-3
    """Adam learning rate."""
    landmark_steps: int = 300
    """Steps of the audio-to-landmark predictor (GeneFace only)."""
    landmark_source: str = added_option("subject")
    """Where the mouth (48-67) of GeneFace's predicted landmarks comes from at test time: ``subject`` (its
    predictor), ``generic`` or ``generic-tuned`` (the generic lip model of :mod:`lmgs.lips`, retargeted to the
    subject; fine-tuned on its training split), as lmgs's key. The NeRF trains on the tracked landmarks either way."""
    lip_weights: str = added_option("lips_generic.pt")
    """The generic lip model's weights under ``generic`` / ``generic-tuned``, as lmgs's ``train.lip_weights``."""
    chunk: int = 2048
    """Rays per chunk when rendering full frames."""
    occupancy: int = 32
    """Cells per side of the occupancy grid that rendering skips empty space with (ER-NeRF and
    RAD-NeRF only; 0: none)."""

    TINY = {"steps": 200, "rays": 384, "samples": 24, "hidden": 32, "lr": 1e-2, "landmark_steps": 40}


OCCUPANCY_METHODS = ("ernerf", "radnerf")
"""The flavours whose originals march rays through an occupancy grid."""
OCCUPANCY_FRAMES = 32
"""Training conditions the occupancy grid is made from (evenly spread over the clip)."""


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
        args, lips = mouth_model(build)
        head = NeRFHead(self.name, **args)
        head.lips = lips  # lmgs.lips.RetargetedLips (not a submodule: its weights are the shipped file's or in build)
        return head

    def _train(self, clip, seed: int, progress: bool):
        dev, rng, n, feats = self._start(clip, seed)
        b = self.cfg
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
            lips = fit_mouth_model(b.landmark_source, clip, targets.cpu().numpy(), seed, b.lip_weights)
            if lips is not None:
                build["lips"] = lips
        model = self._build(build).to(dev)
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
        lips = getattr(m, "lips", None)
        if lips is None:
            conds = m.conditions(feats)
        else:  # the predictor's landmarks with the generic model's mouth, as coefficients of the predictor's basis
            lms = with_generic_mouth(lips, m.predictor.predict(feats), feats)
            conds = m.conditions(feats, _landmark_coefficients(m.predictor, lms))
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


@register("geneface", lip_model=True)
class GeneFace(NeRFMethod):
    name = "geneface"
    reads_landmarks = True
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
