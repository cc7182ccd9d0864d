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

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from lmgs.audio import AudioNet, compute_features, frontend_from_array
from lmgs.clipdata import as_image
from lmgs.config import GuidanceConfig
from lmgs.deform import DeformNet
from lmgs.errors import InputError
from lmgs.guidance import MOUTH_STATE_DIM, mouth_state
from lmgs.gaussians import GaussianSet
from lmgs.render import rasterize
from lmgs.render._projection import first_non_finite
from lmgs.types import Camera


RENDER_CHUNK = 32  # frames :meth:`LMGSModel.render` moves between host and device at a time


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
    # share of face points Spatial Enhancement selected: a 0-d tensor (``float()`` reads it back from
    # the device), nan when SE is off
    se_fraction: torch.Tensor | float = float("nan")


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
    check_values: bool = True,
) -> FrameRender:
    """Render (means, quats, log_scales, opacity_logits, colors) of both branches and composite.

    ``geometry=False`` (rendering a trained model) leaves out the face's depth and normal maps,
    which only the Geometry Regularizer reads (``depth`` and ``normal`` are None);
    ``check_values`` is :func:`~lmgs.render.rasterize`'s.
    """
    face = rasterize(*face_params, camera, None, backend=backend, render_mode="RGB+D+N" if geometry else "RGB",
                     check_values=check_values)
    mouth = rasterize(*mouth_params, camera, None, backend=backend, render_mode="RGB", check_values=check_values)
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


def prepared_params(gs: GaussianSet, deform, prep, audio: torch.Tensor, landmarks, blink, exp=None) -> tuple[tuple[torch.Tensor, ...], float | None]:
    """:meth:`LMGSModel.branch_params` of a dynamic branch at inference, from ``deform.prepare``'s parts."""
    out = deform.forward_prepared(prep, audio, landmarks, blink, exp)
    return (gs.means + out.d_xyz, gs.quats + out.d_rot, gs.log_scales + out.d_scale, gs.opacity_logits, gs.colors()), out.se_fraction


# 1 % of the eye corners' distance: under a pixel of lip motion on a 512 px head
MOUTH_STATE_MIN_SPREAD = 0.01


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
        face_cfg, mouth_cfg = cfg.deform_face, cfg.deform_mouth
        if cfg.guidance.mouth_state:  # both branches read it as their expression input
            if face_cfg.exp_dim or mouth_cfg.exp_dim:
                raise InputError("guidance.mouth_state fills the expression input: it cannot be combined with deform_*.exp_dim")
            face_cfg = dataclasses.replace(face_cfg, exp_dim=MOUTH_STATE_DIM)
            mouth_cfg = dataclasses.replace(mouth_cfg, exp_dim=MOUTH_STATE_DIM)
            # centre and spread of the training frames' mouth state (set by :meth:`fit_mouth_state`)
            self.register_buffer("mouth_state_norm", torch.tensor([[0.0] * MOUTH_STATE_DIM, [1.0] * MOUTH_STATE_DIM]))
        self.face_deform = DeformNet(self.audio_net.out_dim, face_cfg, cfg.triplane, cfg.guidance, box_min, box_max)
        # The mouth branch is driven by audio alone (TalkingGaussian); guidance is the face's.
        no_guidance = GuidanceConfig(se=False, lc=False, theta=cfg.guidance.theta)
        self.mouth_deform = DeformNet(self.audio_net.out_dim, mouth_cfg, cfg.triplane, no_guidance, box_min, box_max)
        self.predictor = None  # LandmarkPredictor, fitted per subject when SE, LC or the mouth state read landmarks
        self.lips = None  # lmgs.lips.RetargetedLips: the mouth landmarks under train.landmark_source = generic*
        self.intrinsics = tuple(float(v) for v in intrinsics)
        self.register_buffer("train_w2c", torch.zeros(0, 4, 4))
        self.register_buffer("default_background", torch.zeros(1, 1, 3))

    @property
    def uses_landmarks(self) -> bool:
        return self.cfg.guidance.reads_landmarks

    def fit_mouth_state(self, landmarks: torch.Tensor) -> None:
        """Centre (median) and spread (standard deviation) of the mouth state over the training
        frames' landmarks ``[T, 68, 3]``, kept with the model. The spread is floored at
        :data:`MOUTH_STATE_MIN_SPREAD`: a mouth that hardly moves is not blown up into one that does."""
        s = mouth_state(landmarks.detach().float())
        spread = s.std(dim=0).clamp_min(MOUTH_STATE_MIN_SPREAD) if len(s) > 1 else torch.ones_like(s[0])
        self.mouth_state_norm.copy_(torch.stack([s.median(dim=0).values, spread]).to(self.mouth_state_norm))

    def mouth_states(self, landmarks: torch.Tensor | None) -> torch.Tensor | None:
        """The normalised mouth state ``[T, 2]`` the deformations read, from landmarks ``[T, 68, 3]``
        (None when the model does not read it)."""
        if not self.cfg.guidance.mouth_state:
            return None
        if landmarks is None:
            raise InputError("guidance.mouth_state is on: the frames' landmarks are needed")
        norm = self.mouth_state_norm
        return (mouth_state(landmarks.to(norm)) - norm[0]) / norm[1]

    def n_gaussians(self) -> int:
        return len(self.face) + len(self.mouth)

    def camera(self, w2c: torch.Tensor) -> Camera:
        f, cx, cy, w, h = self.intrinsics
        return Camera(w2c, f, f, cx, cy, int(w), int(h))

    # ------------------------------------------------------------------ per frame
    def branch_params(
        self, gs: GaussianSet, deform, dynamic: bool, audio: torch.Tensor | None, landmarks, blink, point_features=None, exp=None
    ) -> tuple[tuple[torch.Tensor, ...], float | None]:
        """Deformed (means, quats, log_scales, opacity_logits, colors) of one branch for one frame."""
        if not dynamic:
            return (gs.means, gs.quats, gs.log_scales, gs.opacity_logits, gs.colors()), None
        out = deform(gs.means, audio, landmarks, blink, exp=exp, point_features=point_features)
        return (gs.means + out.d_xyz, gs.quats + out.d_rot, gs.log_scales + out.d_scale, gs.opacity_logits, gs.colors()), out.se_fraction

    def render_frame(
        self, w2c: torch.Tensor, background: torch.Tensor, *, dynamic: bool = True, audio=None, landmarks=None, blink=None,
        face_features=None, mouth_features=None, check_values: bool = True, mouth=None,
    ) -> FrameRender:
        """One frame, differentiable (training). ``mouth``: the frame's normalised mouth state
        ``[2]`` (:meth:`mouth_states`) when the model reads it. ``check_values=False`` leaves out the
        rasterizer's finiteness check, a read-back from the device per branch (the training step's
        own loss check catches parameters gone non-finite)."""
        face_p, frac = self.branch_params(self.face, self.face_deform, dynamic, audio, landmarks, blink, face_features, mouth)
        mouth_p, _ = self.branch_params(self.mouth, self.mouth_deform, dynamic, audio, None, None, mouth_features, mouth)
        r = render_branches(face_p, mouth_p, self.camera(w2c), background, check_values=check_values)
        r.se_fraction = float("nan") if frac is None else frac
        return r

    # ------------------------------------------------------------------ inference
    def _check_finite(self) -> None:
        """Raise :class:`InputError` naming the first parameter that holds NaN or inf (one read-back)."""
        found = first_non_finite(dict(self.named_parameters()))
        if found is not None:
            name, _, bad = found
            raise InputError(f"the model's parameter {name} holds {int(bad.sum())} non-finite value(s)")

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
        mouths = self.mouth_states(lms)
        t_audio = time.perf_counter() - t0
        face_prep = self.face_deform.prepare(self.face.means)
        mouth_prep = self.mouth_deform.prepare(self.mouth.means)
        on_host = dev.type == "cpu"
        if not on_host:  # once for the clip, in one read-back, what the rasterizer would check per frame
            self._check_finite()
        out = np.empty((n, int(self.intrinsics[4]), int(self.intrinsics[3]), 3), np.uint8)
        t_net = t_ras = 0.0
        fracs = []
        bar = tqdm(total=n, desc="rendering", unit="frame", leave=False) if progress else None
        for s in range(0, n, RENDER_CHUNK):
            # a chunk's cameras, backgrounds and blinks go to the device in one copy each, and its frames
            # come back in one: on a GPU each copy makes the host wait for the queue (see lmgs.clipdata)
            e = min(n, s + RENDER_CHUNK)
            w2cs = torch.from_numpy(np.asarray(driving.w2c[s:e], np.float32)).to(dev) if driving.w2c is not None else None
            bgs = (torch.from_numpy(np.ascontiguousarray(driving.backgrounds[s:e])).to(dev)
                   if driving.backgrounds is not None else None)
            blinks = (torch.from_numpy(np.asarray(driving.blink[s:e], np.float32)).to(dev) if driving.blink is not None
                      else torch.zeros(e - s, device=dev))
            frames = torch.from_numpy(out[s:e]) if dev.type == "cpu" else torch.empty(out[s:e].shape, dtype=torch.uint8, device=dev)
            for k, t in enumerate(range(s, e)):
                w2c = w2cs[k] if w2cs is not None else self.train_w2c[t % len(self.train_w2c)]
                bg = as_image(bgs[k]) if bgs is not None else self.default_background
                a = time.perf_counter()
                m = None if mouths is None else mouths[t]
                face_p, frac = prepared_params(self.face, self.face_deform, face_prep, fa[t], None if lms is None else lms[t],
                                               blinks[k], m)
                if frac is not None:
                    fracs.append(frac)
                mouth_p, _ = prepared_params(self.mouth, self.mouth_deform, mouth_prep, fa[t], None, None, m)
                b = time.perf_counter()
                r = render_branches(face_p, mouth_p, self.camera(w2c), bg, geometry=False, check_values=on_host)
                frames[k] = (r.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
                c = time.perf_counter()
                t_net += b - a
                t_ras += c - b
            if dev.type != "cpu":
                out[s:e] = frames.cpu().numpy()
            if bar is not None:
                bar.update(e - s)
        if bar is not None:
            bar.close()
        if timings is not None:
            timings.update(audio=t_audio, network=t_net, raster=t_ras, frames=n)
            if fracs:  # the mean of the per-frame shares, in float64 (read back once)
                timings["se_fraction"] = float(np.mean(torch.stack(fracs).cpu().numpy().astype(np.float64)))
        return out
