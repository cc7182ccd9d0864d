"""Small input types of the model library.

:mod:`lmgs_eval` converts subjects into these; nothing here knows a folder layout.

Camera convention: ``world_to_camera`` is OpenCV-style (x right, y down, z forward, the
convention of gsplat's ``viewmats`` and of 3DGS). The ER-NeRF / TalkingGaussian
``transform_matrix`` is camera-to-world in the OpenGL convention (y up, z backward);
:func:`Camera.from_nerf_c2w` converts it exactly as TalkingGaussian's reader does
(flip the y and z camera axes, then invert).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
        world_to_camera: ``[4, 4]`` float tensor, OpenCV convention.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (pixel centres at integer + 0.5).
        width, height: image size in pixels.
    """

    world_to_camera: torch.Tensor  # [4, 4]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @staticmethod
    def from_nerf_c2w(
        c2w: np.ndarray, focal: float, width: int, height: int, cx: float | None = None, cy: float | None = None
    ) -> "Camera":
        """Build from an ER-NeRF/TalkingGaussian ``transform_matrix`` (camera-to-world, OpenGL)."""
        c2w = np.asarray(c2w, dtype=np.float64).reshape(4, 4)
        w2c = np.linalg.inv(c2w @ _GL_TO_CV)
        return Camera(
            world_to_camera=torch.from_numpy(w2c).float(),
            fx=float(focal),
            fy=float(focal),
            cx=float(width / 2 if cx is None else cx),
            cy=float(height / 2 if cy is None else cy),
            width=int(width),
            height=int(height),
        )

    def to_nerf_c2w(self) -> np.ndarray:
        """Inverse of :meth:`from_nerf_c2w`: the ``transform_matrix`` of this camera."""
        w2c = self.world_to_camera.double().cpu().numpy()
        return np.linalg.inv(w2c) @ _GL_TO_CV

    def to(self, device: torch.device | str) -> "Camera":
        return Camera(self.world_to_camera.to(device), self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Project world points ``[..., 3]`` to pixel coordinates ``[..., 2]``."""
        R = self.world_to_camera[:3, :3].to(points)
        t = self.world_to_camera[:3, 3].to(points)
        p = points @ R.T + t
        z = p[..., 2:3].clamp_min(1e-9)
        return torch.cat([self.fx * p[..., 0:1] / z + self.cx, self.fy * p[..., 1:2] / z + self.cy], dim=-1)


@dataclass
class TrainingClip:
    """What the model trains and renders from: frames, cameras, audio and guidance signals.

    Images are stored compactly (uint8, float16) and turned into float tensors per frame.

    Attributes:
        frames: ``[T, H, W, 3]`` uint8 ground-truth frames.
        backgrounds: ``[T, H, W, 3]`` uint8 what lies behind the head in each frame (the
            subject's torso composited over ``bc.jpg``, the field's protocol), or ``[1, H, W, 3]``
            for a static background.
        w2c: ``[T, 4, 4]`` float32 OpenCV world-to-camera per frame.
        focal, cx, cy: intrinsics in pixels.
        audio: ``[S]`` float32 16 kHz mono waveform covering the T frames (640 samples each).
        blink: ``[T]`` float32 AU45 intensity.
        landmarks2d: ``[T, 68, 2]`` pixels, or None.
        landmarks3d: ``[T, 68, 3]`` world units (targets of the audio-to-landmark predictor), or None.
        audio_features: precomputed per-frame features by kind (``"ds"`` ``[T, 16, 29]``...).
        mouth_masks: ``[T, H, W]`` bool inside-mouth masks, or None.
        head_masks: ``[T, H, W]`` bool head masks (face parsing), or None.
        depth: ``[T, H, W]`` float16 camera-z depth (0 = none), or None.
        normal: ``[T, H, W, 3]`` int8 camera-space normals x127, or None.
        priors_derived: True when ``depth`` / ``normal`` are priors derived from the tracking (a
            head ellipsoid, a fitted face mesh) rather than a measured surface: the Geometry
            Regularizer weighs them by ``train.derived_depth_weight`` / ``derived_normal_weight``.
    """

    frames: np.ndarray
    backgrounds: np.ndarray
    w2c: np.ndarray
    focal: float
    cx: float
    cy: float
    audio: np.ndarray
    blink: np.ndarray
    landmarks2d: np.ndarray | None = None
    landmarks3d: np.ndarray | None = None
    audio_features: dict | None = None
    mouth_masks: np.ndarray | None = None
    head_masks: np.ndarray | None = None
    depth: np.ndarray | None = None
    normal: np.ndarray | None = None
    priors_derived: bool = False
    fps: int = 25
    sample_rate: int = 16000

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    def camera(self, i: int) -> Camera:
        return Camera(torch.from_numpy(np.asarray(self.w2c[i], np.float32)), self.focal, self.focal, self.cx, self.cy, self.width, self.height)

    def background(self, i: int) -> np.ndarray:
        return self.backgrounds[i if self.backgrounds.shape[0] > 1 else 0]


@dataclass
class DrivingAudio:
    """What drives a trained model at inference: audio (and optional extra signals).

    Attributes:
        audio: ``[S]`` float32 16 kHz mono waveform; the clip has ``S // 640`` frames.
        w2c: ``[T, 4, 4]`` camera per frame, or None to reuse the training poses cyclically.
        backgrounds: ``[T, H, W, 3]`` uint8 backgrounds, or None for the model's own.
        blink: ``[T]`` AU45, or None (eyes open).
        audio_features: precomputed features by kind, or None.
    """

    audio: np.ndarray
    w2c: np.ndarray | None = None
    backgrounds: np.ndarray | None = None
    blink: np.ndarray | None = None
    audio_features: dict | None = None
    fps: int = 25
    sample_rate: int = 16000

    @property
    def n_frames(self) -> int:
        if self.w2c is not None:
            return int(self.w2c.shape[0])
        return int(len(self.audio) // (self.sample_rate // self.fps))
