"""The landmark-guided 3DGS talking head: face and mouth branches, deformation, compositing.

Structure (paper, Method; TalkingGaussian's face/mouth decomposition):

* two :class:`~lmgs.gaussians.GaussianSet` branches: the face and the inside of the mouth,
  each a canonical (static) field;
* per frame, an audio feature :math:`F_a` (Audio Encoder + 8-frame attention smoother), the
  blink signal (AU45) and 68 audio-predicted 3D landmarks drive a region-attention
  deformation network per branch, predicting offsets of position, rotation and scale;
* Spatial Enhancement adds the best-matching landmark's tri-plane feature to points whose
  cosine similarity passes :math:`\\theta`; Landmark Compensation adds
  :math:`MLP_{offset}(h_i) \\cdot \\tau_i` to the face offsets;
* the two branches are rendered separately and composited face-over-mouth, then over the
  frame's background (the GT torso over ``bc.jpg``, the field's protocol).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from lmgs.audio import AudioNet, compute_features, frontend_from_array
from lmgs.config import GuidanceConfig
from lmgs.deform import DeformNet
from lmgs.errors import InputError
from lmgs.gaussians import GaussianSet
from lmgs.render import rasterize
from lmgs.types import Camera


@dataclass
class FrameRender:
    """One rendered frame: the composite and the pieces the losses need."""

    rgb: torch.Tensor  # [H, W, 3] composite over the background
    head_rgb: torch.Tensor  # [H, W, 3] premultiplied head (face over mouth)
    head_alpha: torch.Tensor  # [H, W, 1]
    face_alpha: torch.Tensor  # [H, W, 1]
    mouth_alpha: torch.Tensor  # [H, W, 1]
    depth: torch.Tensor | None  # [H, W, 1] expected depth of the face, alpha-normalised (None: geometry=False)
    normal: torch.Tensor | None  # [H, W, 3] face normals, alpha-normalised (None: geometry=False)
    face_means2d: torch.Tensor
    face_visible: torch.Tensor
    mouth_means2d: torch.Tensor
    mouth_visible: torch.Tensor
    se_fraction: float = float("nan")


def composite(face, mouth, background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Face over mouth over background (premultiplied alpha).

    .. math:: C = C_f + (1 - \\alpha_f) C_m, \\quad \\alpha = \\alpha_f + (1 - \\alpha_f)\\alpha_m,
       \\quad I = C + (1 - \\alpha) B
    """
    head_rgb = face.rgb + (1 - face.alpha) * mouth.rgb
    head_alpha = face.alpha + (1 - face.alpha) * mouth.alpha
    return head_rgb + (1 - head_alpha) * background, head_rgb, head_alpha


def render_branches(
    face_params: tuple[torch.Tensor, ...],
    mouth_params: tuple[torch.Tensor, ...],
    camera: Camera,
    background: torch.Tensor,
    backend: str = "auto",
    geometry: bool = True,
) -> FrameRender:
    """Render (means, quats, log_scales, opacity_logits, colors) of both branches and composite.

    ``geometry=False`` (rendering a trained model) leaves out the face's depth and normal maps,
    which only the Geometry Regularizer reads (``depth`` and ``normal`` are None).
    """
    face = rasterize(*face_params, camera, None, backend=backend, render_mode="RGB+D+N" if geometry else "RGB")
    mouth = rasterize(*mouth_params, camera, None, backend=backend, render_mode="RGB")
    rgb, head_rgb, head_alpha = composite(face, mouth, background)
    a = face.alpha.clamp_min(1e-6)
    return FrameRender(
        rgb=rgb,
        head_rgb=head_rgb,
        head_alpha=head_alpha,
        face_alpha=face.alpha,
        mouth_alpha=mouth.alpha,
        depth=face.depth / a if geometry else None,
        normal=face.normal / a if geometry else None,
        face_means2d=face.means2d,
        face_visible=face.visible,
        mouth_means2d=mouth.means2d,
        mouth_visible=mouth.visible,
    )


def to_image(x: np.ndarray, device) -> torch.Tensor:
    """uint8 ``[H, W, 3]`` -> float ``[H, W, 3]`` in [0, 1] on ``device``."""
    return torch.from_numpy(np.ascontiguousarray(x)).to(device).float() / 255.0


def prepared_params(gs: GaussianSet, deform, prep, audio: torch.Tensor, landmarks, blink) -> tuple[tuple[torch.Tensor, ...], float | None]:
    """:meth:`LMGSModel.branch_params` of a dynamic branch at inference, from ``deform.prepare``'s parts."""
    out = deform.forward_prepared(prep, audio, landmarks, blink)
    return (gs.means + out.d_xyz, gs.quats + out.d_rot, gs.log_scales + out.d_scale, gs.opacity_logits, gs.colors()), out.se_fraction


class LMGSModel(nn.Module):
    """The trained talking head: two Gaussian branches, the audio net, two deformation
    networks and the per-subject audio-to-landmark predictor.

    Args:
        cfg: the full :class:`~lmgs.presets.LMGSConfig`.
        face, mouth: canonical Gaussians of the two branches.
        in_channels, window: shape of the audio front end's per-frame windows ``[W, C]``.
        box_min, box_max: tri-plane bounding box (canonical face extent plus a margin).
        intrinsics: ``(focal, cx, cy, width, height)`` of the subject's camera.
    """

    def __init__(self, cfg, face: GaussianSet, mouth: GaussianSet, in_channels: int, window: int, box_min, box_max, intrinsics):
        super().__init__()

        self.cfg = cfg
        self.face = face
        self.mouth = mouth
        self.audio_net = AudioNet(in_channels, window, cfg.audio)
        self.face_deform = DeformNet(self.audio_net.out_dim, cfg.deform_face, cfg.triplane, cfg.guidance, box_min, box_max)
        # The mouth branch is driven by audio alone (TalkingGaussian); guidance is the face's.
        no_guidance = GuidanceConfig(se=False, lc=False, theta=cfg.guidance.theta)
        self.mouth_deform = DeformNet(self.audio_net.out_dim, cfg.deform_mouth, cfg.triplane, no_guidance, box_min, box_max)
        self.predictor = None  # LandmarkPredictor, fitted per subject when SE or LC is on
        self.lips = None  # lmgs.lips.RetargetedLips: the mouth landmarks under train.landmark_source = generic*
        self.intrinsics = tuple(float(v) for v in intrinsics)
        self.register_buffer("train_w2c", torch.zeros(0, 4, 4))
        self.register_buffer("default_background", torch.zeros(1, 1, 3))

    @property
    def uses_landmarks(self) -> bool:
        return bool(self.cfg.guidance.se or self.cfg.guidance.lc)

    def n_gaussians(self) -> int:
        return len(self.face) + len(self.mouth)

    def camera(self, w2c: torch.Tensor) -> Camera:
        f, cx, cy, w, h = self.intrinsics
        return Camera(w2c, f, f, cx, cy, int(w), int(h))

    # ------------------------------------------------------------------ per frame
    def branch_params(
        self, gs: GaussianSet, deform, dynamic: bool, audio: torch.Tensor | None, landmarks, blink, point_features=None
    ) -> tuple[tuple[torch.Tensor, ...], float | None]:
        """Deformed (means, quats, log_scales, opacity_logits, colors) of one branch for one frame."""
        if not dynamic:
            return (gs.means, gs.quats, gs.log_scales, gs.opacity_logits, gs.colors()), None
        out = deform(gs.means, audio, landmarks, blink, point_features=point_features)
        return (gs.means + out.d_xyz, gs.quats + out.d_rot, gs.log_scales + out.d_scale, gs.opacity_logits, gs.colors()), out.se_fraction

    def render_frame(
        self, w2c: torch.Tensor, background: torch.Tensor, *, dynamic: bool = True, audio=None, landmarks=None, blink=None,
        face_features=None, mouth_features=None,
    ) -> FrameRender:
        face_p, frac = self.branch_params(self.face, self.face_deform, dynamic, audio, landmarks, blink, face_features)
        mouth_p, _ = self.branch_params(self.mouth, self.mouth_deform, dynamic, audio, None, None, mouth_features)
        r = render_branches(face_p, mouth_p, self.camera(w2c), background)
        r.se_fraction = float("nan") if frac is None else float(frac)
        return r

    # ------------------------------------------------------------------ inference
    def audio_windows(self, audio: np.ndarray, n_frames: int, features: dict | None = None) -> torch.Tensor:
        """Per-frame audio windows ``[T, W, C]`` from the configured front end."""
        kind = self.cfg.audio.frontend
        if kind in ("logmel", "mfcc"):
            arr = compute_features(audio, 16000, self.cfg.audio, n_frames=n_frames)
        else:
            if not features or kind not in features:
                raise InputError(f"the model uses precomputed '{kind}' audio features; none were given with the audio")
            arr = frontend_from_array(kind, features[kind])[:n_frames]
        return torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))

    @torch.no_grad()
    def render(self, driving, *, progress: bool = False, timings: dict | None = None) -> np.ndarray:
        """Audio in, frames out: ``[T, H, W, 3]`` uint8.

        Cameras, backgrounds and blinks come from ``driving`` when given; otherwise the
        training poses are replayed in order, the mean background is used and eyes stay open.
        ``timings`` (if a dict) receives seconds spent in ``audio``, ``network`` and ``raster``,
        and, with Spatial Enhancement on, ``se_fraction``: the mean fraction of face points selected.
        """
        dev = self.face.means.device
        t0 = time.perf_counter()
        n = driving.n_frames
        feats = self.audio_windows(driving.audio, n, driving.audio_features).to(dev)
        fa = self.audio_net(feats)
        lms = self.predictor.predict(feats).to(dev) if (self.uses_landmarks and self.predictor is not None) else None
        if lms is not None and self.lips is not None:
            lms = self.lips.replace_mouth(lms, driving.audio, n)
        t_audio = time.perf_counter() - t0
        face_prep = self.face_deform.prepare(self.face.means)
        mouth_prep = self.mouth_deform.prepare(self.mouth.means)
        out = np.empty((n, int(self.intrinsics[4]), int(self.intrinsics[3]), 3), np.uint8)
        t_net = t_ras = 0.0
        fracs = []
        it = range(n)
        if progress:
            it = tqdm(it, desc="rendering", unit="frame", leave=False)
        for t in it:
            w2c = torch.from_numpy(np.asarray(driving.w2c[t], np.float32)) if driving.w2c is not None else self.train_w2c[t % len(self.train_w2c)]
            bg = to_image(driving.backgrounds[t], dev) if driving.backgrounds is not None else self.default_background
            blink = float(driving.blink[t]) if driving.blink is not None else 0.0
            a = time.perf_counter()
            face_p, frac = prepared_params(self.face, self.face_deform, face_prep, fa[t], None if lms is None else lms[t], blink)
            if frac is not None:
                fracs.append(float(frac))
            mouth_p, _ = prepared_params(self.mouth, self.mouth_deform, mouth_prep, fa[t], None, None)
            b = time.perf_counter()
            r = render_branches(face_p, mouth_p, self.camera(w2c.to(dev)), bg, geometry=False)
            out[t] = (r.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
            c = time.perf_counter()
            t_net += b - a
            t_ras += c - b
        if timings is not None:
            timings.update(audio=t_audio, network=t_net, raster=t_ras, frames=n)
            if fracs:
                timings["se_fraction"] = float(np.mean(fracs))
        return out
