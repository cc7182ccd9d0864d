"""Audio -> 68 3D facial landmarks per frame, and 3D landmark targets from 2D tracks.

The paper predicts the keypoints that guide Spatial Enhancement and Landmark Compensation with
GeneFace's pretrained audio-to-landmark network (Ye et al., "GeneFace", ICLR 2023). Its
weights cannot be had here, so :class:`LandmarkPredictor` is a **per-subject stand-in**: a
small temporal convolutional network trained on the subject's own training split
(:func:`fit_landmark_predictor`) that maps the audio feature windows to offsets from the
subject's mean landmark set, in a PCA basis of the training landmarks. It learns only what
one subject's few minutes of speech show; it is not GeneFace and does not generalise across
identities. :meth:`LandmarkPredictor.describe` says so in every record it feeds.

3D targets for real subjects: :func:`lift_2d_landmarks` back-projects the 68 ``.lms`` points of
each frame through the tracked camera with a depth from a face depth prior.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from lmgs.config import AudioConfig
from lmgs.errors import InputError
from lmgs.optim import fused_on_gpu

# Relative depth of the 68 landmarks (iBUG 300-W order) behind the nose tip, in units of the
# face width |p0 - p16|, for a frontal average adult face. Written from the proportions of the
# generic 3D face models used for head-pose estimation (nose tip 0; chin about 0.10; eye
# corners about 0.21; mouth corners about 0.19; jaw angle at the ears about 0.55).
_JAW = [0.55, 0.50, 0.44, 0.37, 0.30, 0.23, 0.17, 0.12, 0.10, 0.12, 0.17, 0.23, 0.30, 0.37, 0.44, 0.50, 0.55]
_BROWS = [0.30, 0.22, 0.17, 0.14, 0.13, 0.13, 0.14, 0.17, 0.22, 0.30]
_NOSE = [0.14, 0.10, 0.05, 0.0, 0.12, 0.08, 0.06, 0.08, 0.12]
_EYES = [0.22, 0.17, 0.17, 0.17, 0.18, 0.18, 0.17, 0.17, 0.17, 0.22, 0.18, 0.18]
_MOUTH = [0.19, 0.14, 0.11, 0.10, 0.11, 0.14, 0.19, 0.14, 0.12, 0.11, 0.12, 0.14, 0.18, 0.13, 0.115, 0.13, 0.18, 0.13, 0.12, 0.13]
MEAN_FACE_DEPTH = np.array(_JAW + _BROWS + _NOSE + _EYES + _MOUTH, dtype=np.float64)
assert MEAN_FACE_DEPTH.shape == (68,)

_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def lift_2d_landmarks(
    lms2d,
    c2w,
    focal: float,
    cx: float,
    cy: float,
    depth_prior=None,
    *,
    face_center=(0.0, 0.0, 0.0),
) -> torch.Tensor:
    """Back-project 2D landmarks to 3D world points with a face depth prior.

    Each landmark :math:`j` of frame :math:`n` at pixel :math:`(u, v)` is placed on its camera
    ray at depth (OpenCV camera, :math:`z` forward)

    .. math::

        z_{nj} = D_n + \\delta_{nj} - \\bar\\delta_n, \\qquad
        X_{cam} = \\Big(\\frac{u - c_x}{f} z,\\ \\frac{v - c_y}{f} z,\\ z\\Big)

    where :math:`D_n` is the depth of ``face_center`` (world; ER-NeRF/TalkingGaussian track the
    head at the origin) in camera :math:`n`, and :math:`\\delta` is the depth prior, centred per
    frame. The camera point is mapped to the world by the ER-NeRF ``transform_matrix``
    (camera-to-world, OpenGL axes: :math:`X_{gl} = (x, -y, -z)`). The prior assumes a roughly
    frontal face (depth offsets along the viewing axis); errors of the prior move points along
    their rays only, so the 2D reprojection is exact by construction.

    Args:
        lms2d: ``[N, 68, 2]`` pixel coordinates (``.lms`` files: x right, y down).
        c2w: ``[N, 4, 4]`` or ``[4, 4]`` camera-to-world (OpenGL, ER-NeRF ``transform_matrix``).
        focal, cx, cy: intrinsics in pixels (``focal_len``, ``cx``, ``cy`` of transforms json).
        depth_prior: per-landmark depth offsets in world units, ``[68]`` or ``[N, 68]``
            (positive = farther from the camera); ``None`` uses :data:`MEAN_FACE_DEPTH` scaled
            by each frame's face width, estimated from the jaw width in pixels
            (:math:`|p_0 - p_{16}| D_n / f`).
        face_center: world point whose camera depth is :math:`D_n`.

    Returns:
        ``[N, 68, 3]`` float32 world points.
    """
    lms = torch.as_tensor(np.asarray(lms2d), dtype=torch.float64)
    if lms.ndim != 3 or lms.shape[1:] != (68, 2):
        raise InputError(f"2D landmarks must be [N, 68, 2], got shape {tuple(lms.shape)}")
    N = lms.shape[0]
    M = torch.as_tensor(np.asarray(c2w), dtype=torch.float64)
    if M.shape == (4, 4):
        M = M.expand(N, 4, 4)
    if M.shape != (N, 4, 4):
        raise InputError(f"c2w must be [4, 4] or [N={N}, 4, 4], got shape {tuple(M.shape)}")
    if not focal > 0:
        raise InputError(f"focal must be positive, got {focal}")
    w2c_cv = torch.linalg.inv(M @ _GL_TO_CV)  # world -> OpenCV camera
    c = torch.tensor([*face_center, 1.0], dtype=torch.float64)
    D = (w2c_cv @ c)[:, 2]  # [N]
    if bool((D <= 0).any()):
        raise InputError("face_center is behind the camera in some frames: check c2w / face_center")
    if depth_prior is None:
        width_px = (lms[:, 0] - lms[:, 16]).norm(dim=-1)
        delta = torch.as_tensor(MEAN_FACE_DEPTH)[None] * (width_px * D / focal)[:, None]
    else:
        delta = torch.as_tensor(np.asarray(depth_prior), dtype=torch.float64)
        if delta.shape == (68,):
            delta = delta.expand(N, 68)
        if delta.shape != (N, 68):
            raise InputError(f"depth_prior must be [68] or [N, 68], got shape {tuple(delta.shape)}")
    z = D[:, None] + delta - delta.mean(dim=1, keepdim=True)  # [N, 68]
    x = (lms[..., 0] - cx) / focal * z
    y = (lms[..., 1] - cy) / focal * z
    p_cv = torch.stack([x, y, z, torch.ones_like(z)], dim=-1)  # [N, 68, 4]
    c2w_cv = M @ _GL_TO_CV
    world = p_cv @ c2w_cv.transpose(1, 2)
    return world[..., :3].float()


class LandmarkPredictor(nn.Module):
    """Per-subject audio -> 68 3D landmarks (stand-in for GeneFace's pretrained model).

    Per frame, the Audio Encoder of :mod:`lmgs.audio` summarises the feature window; dilated
    temporal 1D convolutions over the frame sequence (receptive field 9 frames, 360 ms) give
    whitened PCA coefficients :math:`c_t`, and

    .. math::

        \\hat L_t = \\bar L + s \\, (c_t \\odot \\sigma) B

    with :math:`\\bar L` the mean training landmark set ``[68,3]``, :math:`s` its RMS radius,
    :math:`B` the top-K principal directions of the normalised training offsets and
    :math:`\\sigma` their standard deviations. Fitted by :func:`fit_landmark_predictor`.

    Shapes:
        ``predict(features [N, W, C]) -> [N, 68, 3]``.
    """

    def __init__(self, in_channels: int, window: int, n_components: int = 16, hidden: int = 64):
        super().__init__()
        self.in_channels, self.window, self.n_components = int(in_channels), int(window), int(n_components)
        cfg = AudioConfig(dim=hidden, encoder_channels=(32, 32, 64, 64), use_smoother=False)
        from lmgs.audio.encoder import AudioEncoder

        self.frame_enc = AudioEncoder(in_channels, window, cfg)
        self.temporal = nn.Sequential(
            nn.Conv1d(hidden, hidden, 3, padding=1),
            nn.LeakyReLU(0.02),
            nn.Conv1d(hidden, hidden, 3, padding=2, dilation=2),
            nn.LeakyReLU(0.02),
            nn.Conv1d(hidden, hidden, 3, padding=1),
            nn.LeakyReLU(0.02),
            nn.Conv1d(hidden, n_components, 1),
        )
        self.register_buffer("mean_lms", torch.zeros(68, 3))
        self.register_buffer("scale", torch.ones(()))
        self.register_buffer("basis", torch.zeros(n_components, 204))
        self.register_buffer("coef_std", torch.ones(n_components))
        self.fitted_frames = 0

    def describe(self) -> dict:
        """What this predictor is, for results files and model cards."""
        return {
            "name": "lmgs.landmarks.LandmarkPredictor",
            "role": "audio-to-landmark predictor guiding Spatial Enhancement and Landmark Compensation",
            "note": (
                "per-subject stand-in for GeneFace's pretrained audio-to-landmark model (not available "
                "offline): a small temporal CNN trained on this subject's training split only; "
                "it does not generalise across identities"
            ),
            "n_components": self.n_components,
            "fitted_frames": int(self.fitted_frames),
            "in_shape": [self.window, self.in_channels],
        }

    def coefficients(self, features: torch.Tensor) -> torch.Tensor:
        """Whitened PCA coefficients ``[N, K]`` of a contiguous frame sequence."""
        if features.ndim != 3 or features.shape[1:] != (self.window, self.in_channels):
            raise InputError(
                f"landmark predictor expects [N, {self.window}, {self.in_channels}] features, got {tuple(features.shape)}"
            )
        h = self.frame_enc(features)  # [N, H]
        return self.temporal(h.T.unsqueeze(0)).squeeze(0).T  # [N, K]

    def decode(self, coef: torch.Tensor) -> torch.Tensor:
        """Coefficients ``[N, K]`` -> landmarks ``[N, 68, 3]``."""
        off = (coef * self.coef_std) @ self.basis
        return self.mean_lms + self.scale * off.view(-1, 68, 3)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.decode(self.coefficients(features))

    @torch.no_grad()
    def predict(self, features) -> torch.Tensor:
        """Landmarks ``[N, 68, 3]`` for a contiguous sequence of feature windows ``[N, W, C]``."""
        f = torch.as_tensor(features, dtype=torch.float32, device=self.mean_lms.device)
        if f.shape[0] == 0:
            return f.new_zeros(0, 68, 3)
        was = self.training
        self.eval()
        out = self(f)
        self.train(was)
        return out


def fit_landmark_predictor(
    features: torch.Tensor,
    landmarks3d: torch.Tensor,
    *,
    steps: int = 400,
    seed: int = 0,
    progress: Callable[[int, float], None] | None = None,
    n_components: int = 16,
    hidden: int = 64,
    lr: float = 3e-3,
) -> LandmarkPredictor:
    """Train a :class:`LandmarkPredictor` on one subject's training frames.

    Full-batch Adam on the whole (contiguous) training sequence, loss the mean squared
    landmark error in the normalised space:

    .. math::

        \\mathcal{L} = \\frac{1}{N \\cdot 204} \\sum_{t} \\big\\| (\\hat L_t - L_t) / s \\big\\|^2

    Deterministic for a given seed (the global RNG is left untouched). A few seconds for
    1,500 frames on 2 CPU cores at the default sizes.

    Args:
        features: ``[N, W, C]`` audio windows of consecutive frames.
        landmarks3d: ``[N, 68, 3]`` target landmarks (e.g. from :func:`lift_2d_landmarks`).
        steps: optimiser steps.
        seed: initialisation seed.
        progress: called as ``progress(step, loss)`` every 50 steps and at the end.
        n_components: PCA components kept (at most N - 1 and 204).
    """
    f = torch.as_tensor(features, dtype=torch.float32)
    y = torch.as_tensor(landmarks3d, dtype=torch.float32, device=f.device)
    if f.ndim != 3:
        raise InputError(f"features must be [N, W, C], got shape {tuple(f.shape)}")
    if y.shape != (f.shape[0], 68, 3):
        raise InputError(f"landmarks3d must be [N={f.shape[0]}, 68, 3], got shape {tuple(y.shape)}")
    if f.shape[0] < 4:
        raise InputError(f"need at least 4 frames to fit the landmark predictor, got {f.shape[0]}")
    if not (torch.isfinite(f).all() and torch.isfinite(y).all()):
        raise InputError("features or landmarks contain NaN/inf")
    mean = y.mean(0)
    scale = ((mean - mean.mean(0)) ** 2).sum(-1).mean().sqrt().clamp_min(1e-8)  # face radius
    off = ((y - mean) / scale).reshape(len(y), 204)
    _, S, Vh = torch.linalg.svd(off, full_matrices=False)
    k = int(min(n_components, len(y) - 1, 204, int((S > S[0] * 1e-6).sum()) if S[0] > 0 else 1))
    k = max(k, 1)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = LandmarkPredictor(f.shape[2], f.shape[1], k, hidden).to(f.device)
    model.mean_lms.copy_(mean)
    model.scale.copy_(scale)
    model.basis.copy_(Vh[:k])
    coef = off @ Vh[:k].T
    std = coef.std(0).clamp_min(1e-8)
    model.coef_std.copy_(std)
    model.frame_enc.fit_normalization(f)
    target = coef / std
    weight = (std**2) / (std**2).sum()  # whitened coefficients weighted back to landmark error
    params = list(model.parameters())
    opt = torch.optim.Adam(params, lr=lr, weight_decay=1e-5, fused=fused_on_gpu(params))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))
    model.train()
    for step in range(steps):
        pred = model.coefficients(f)
        loss = (((pred - target) ** 2) * weight).sum(-1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if progress is not None and (step % 50 == 0 or step == steps - 1):  # (reading the loss waits for a GPU)
            progress(step, float(loss.detach()))
    model.fitted_frames = int(len(y))
    model.eval()
    return model


MIN_FOLD_FRAMES = 8  # frames a cross-fitting block needs at least


def max_folds(n_frames: int) -> int:
    """The most folds :func:`cross_fit_landmarks` takes for a clip of ``n_frames`` (blocks of at least 8)."""
    return n_frames // MIN_FOLD_FRAMES


def cross_fit_landmarks(
    features: torch.Tensor,
    landmarks3d: torch.Tensor,
    *,
    folds: int = 5,
    steps: int = 400,
    seed: int = 0,
) -> torch.Tensor:
    """Out-of-fold predictions ``[N, 68, 3]`` of the landmark predictor on its own training clip.

    The paper's audio-to-landmark model (GeneFace's) never saw the subject's video, so the
    landmarks guiding training carry the same error as those guiding inference. The per-subject
    stand-in is fitted on the training split itself: its predictions there are 3-4x more
    accurate than on unseen audio (bundled subjects, mouth landmarks: 0.010 against 0.045 of
    the face radius), and a deformation trained on them learns to trust landmarks that are
    never that good at test time. Here the clip is cut into ``folds`` contiguous blocks; each
    block is predicted by a predictor fitted on the other blocks (joined end to end, one seam),
    so every training frame gets a landmark set of held-out quality. The predictor used at
    inference is still the one fitted on the whole split (:func:`fit_landmark_predictor`).

    Args:
        features: ``[N, W, C]`` audio windows of consecutive frames.
        landmarks3d: ``[N, 68, 3]`` targets.
        folds: contiguous blocks (at least 2, at most :func:`max_folds`: 8 frames a block).
        steps, seed: as :func:`fit_landmark_predictor` (fold ``k`` uses ``seed + k``).
    """
    f = torch.as_tensor(features, dtype=torch.float32)
    y = torch.as_tensor(landmarks3d, dtype=torch.float32, device=f.device)
    n = f.shape[0]
    if folds < 2:
        raise InputError(f"cross-fitting needs at least 2 folds, got {folds}")
    if folds > max_folds(n):
        raise InputError(f"{n} frames are too few for {folds}-fold cross-fitting of the landmark predictor")
    edges = np.linspace(0, n, folds + 1).round().astype(int)
    out = torch.empty(n, 68, 3, dtype=torch.float32, device=f.device)
    for k in range(folds):
        a, b = int(edges[k]), int(edges[k + 1])
        keep = torch.cat([torch.arange(0, a), torch.arange(b, n)]).to(f.device)
        pred = fit_landmark_predictor(f[keep], y[keep], steps=steps, seed=seed + k)
        out[a:b] = pred.predict(f[a:b])
    return out
