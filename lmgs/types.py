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
