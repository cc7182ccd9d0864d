"""Initial Gaussians of the face and mouth branches from a training clip.

* Face: with a depth map (bundled subjects, or maps a user provides), pixels of the head
  in the first frame are back-projected to 3D and take the frame's colours; otherwise
  points are drawn in the box around the 3D landmarks (TalkingGaussian initialises in a box).
* Mouth: points in a small ellipsoid just behind the inner lips (landmarks 60-67).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import ConvexHull, QhullError

from lmgs.gaussians import GaussianSet, knn_scale
from lmgs.types import TrainingClip

INNER_LIPS = slice(60, 68)


def face_area_px(clip: TrainingClip) -> float:
    """Mean head area in pixels: the parsing mask if present, else the landmark hull x 1.6."""
    if clip.head_masks is not None:
        return float(clip.head_masks[:: max(1, len(clip) // 20)].sum(axis=(1, 2)).mean())
    if clip.landmarks2d is not None:
        areas = [hull_area(l) for l in clip.landmarks2d[:: max(1, len(clip) // 20)]]
        return float(np.mean(areas)) * 1.6
    return 0.25 * clip.width * clip.height


def scene_box(gs: GaussianSet) -> tuple[list[float], list[float], float]:
    """The box a model's deformation encoders cover, from its initial Gaussians: their bounding
    box grown on each side by a quarter of its size plus 1 mm (``box_min``, ``box_max`` as lists),
    and the scene extent the densification scales by (the bounding box's diagonal)."""
    pts = gs.means.detach()
    lo, hi = pts.min(0).values, pts.max(0).values
    margin = (hi - lo) * 0.25 + 1e-3
    return (lo - margin).tolist(), (hi + margin).tolist(), float((hi - lo).norm())


def hull_area(points: np.ndarray) -> float:
    """Area in pixels of the convex hull of 2D points ``[K, 2]``; 0 when they span no area.

    The points are rounded to float32 first, as OpenCV's ``contourArea(convexHull(...))``
    (which this replaces, so that the model library needs no OpenCV) takes them.
    """
    pts = np.asarray(points, np.float32).astype(np.float64)
    try:
        return float(ConvexHull(pts).volume)  # in 2D, qhull's "volume" is the area
    except (QhullError, ValueError):  # fewer than 3 points, or all on one line
        return 0.0


def _backproject(clip: TrainingClip, i: int, mask: np.ndarray, n: int, rng: np.random.Generator):
    ys, xs = np.nonzero(mask & (clip.depth[i].astype(np.float32) > 0))
    if len(ys) == 0:
        return None
    pick = rng.choice(len(ys), size=min(n, len(ys)), replace=False)
    ys, xs = ys[pick], xs[pick]
    z = clip.depth[i].astype(np.float32)[ys, xs]
    x = (xs + 0.5 - clip.cx) / clip.focal * z
    y = (ys + 0.5 - clip.cy) / clip.focal * z
    cam = np.stack([x, y, z, np.ones_like(z)], axis=1)
    world = cam @ np.linalg.inv(clip.w2c[i]).T
    cols = clip.frames[i][ys, xs].astype(np.float32) / 255.0
    return world[:, :3], cols


def _landmarks3d(clip: TrainingClip) -> np.ndarray:
    if clip.landmarks3d is None:
        from lmgs.errors import InputError

        raise InputError("the training clip has neither depth maps nor 3D landmarks to place the initial Gaussians")
    return clip.landmarks3d


def init_face(clip: TrainingClip, n: int, seed: int) -> GaussianSet:
    rng = np.random.default_rng(seed)
    got = None
    if clip.depth is not None:
        mask = clip.head_masks[0] if clip.head_masks is not None else np.ones((clip.height, clip.width), bool)
        if clip.mouth_masks is not None:
            mask = mask & ~clip.mouth_masks[0]
        got = _backproject(clip, 0, mask, n, rng)
    if got is None:
        lms = _landmarks3d(clip)[0]
        lo, hi = lms.min(0), lms.max(0)
        pad = (hi - lo) * np.array([0.35, 0.5, 0.3])
        pts = rng.uniform(lo - pad, hi + pad, size=(n, 3))
        cols = np.full((n, 3), 0.5)
        got = (pts, cols)
    pts = torch.from_numpy(np.asarray(got[0], np.float32))
    cols = torch.from_numpy(np.asarray(got[1], np.float32))
    return GaussianSet(pts, cols, knn_scale(pts), opacity=0.6)


def init_mouth(clip: TrainingClip, n: int, seed: int) -> GaussianSet:
    """Points in an ellipsoid behind the inner lips of the first frame (dark mouth colours)."""
    rng = np.random.default_rng(seed + 1)
    lms = _landmarks3d(clip)[0]
    inner = lms[INNER_LIPS]
    centre = inner.mean(0)
    width = float(np.linalg.norm(lms[64] - lms[60]))
    # Push the mouth volume behind the lips, away from the camera of frame 0.
    cam_pos = np.linalg.inv(clip.w2c[0])[:3, 3]
    back = centre - cam_pos
    back /= np.linalg.norm(back) + 1e-9
    centre = centre + back * 0.3 * width
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = rng.uniform(0, 1, size=(n, 1)) ** (1 / 3)
    pts = centre + u * r * np.array([0.5 * width, 0.35 * width, 0.3 * width])
    cols = np.clip(rng.normal([0.45, 0.2, 0.2], 0.05, size=(n, 3)), 0, 1)
    p = torch.from_numpy(pts.astype(np.float32))
    return GaussianSet(p, torch.from_numpy(cols.astype(np.float32)), knn_scale(p), opacity=0.6)
