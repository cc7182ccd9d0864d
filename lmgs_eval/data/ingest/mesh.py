"""The dense face mesh: MediaPipe's 478-point face landmark model, run in ONNX Runtime, tracked over a clip.

The model (``models/face_landmarks_detector.onnx``, Apache-2.0, shipped with the package and its
sha256 checked on load; ``models/README.md`` says where it comes from) sees a 256x256 crop of the
face, upright, and returns 478 points (x, y in crop pixels, z relative depth in the same scale),
the 468 of the face mesh plus ten iris points, and a face-presence logit.

Tracking follows MediaPipe's rule for the crop: a detector's box seeds the first crop; afterwards
each frame's crop is the previous mesh's extent, 1.5 times its larger side, turned by the angle of
the line through the outer eye corners, so a turning or tilting head stays centred and upright in
the crop. When the presence logit falls below :data:`PRESENCE` the face is detected again.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np


MODEL = "face_landmarks_detector.onnx"  # in the shipped models (:mod:`vendored`)
CROP = 256  # the model's input side
SCALE = 1.5  # crop side / the mesh's larger extent (MediaPipe's region of interest)
PRESENCE = 0.0  # presence logit below which the face counts as lost
RIGHT_EYE_OUTER, LEFT_EYE_OUTER = 33, 263  # mesh vertices (the subject's right and left)

Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in image pixels


def load_session(path: Path | None = None):
    """An ONNX Runtime session of the mesh model (default: the shipped one; another file is checked
    against the shipped one's sha256); a missing or altered file is a :class:`UserError` naming it."""
    import onnxruntime as ort

    from lmgs_eval.data.ingest import vendored

    path = vendored.model(MODEL, path)
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@functools.cache
def shipped_session():
    """The shipped mesh model's session, loaded (and its file checked) once per process: every
    :class:`FaceMesh` made without a session of its own shares it."""
    return load_session()


def crop_matrix(cx: float, cy: float, side: float, angle: float) -> np.ndarray:
    """The 2x3 affine map from image pixels to the crop: ``side`` pixels around ``(cx, cy)`` turned by ``-angle``."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, s], [-s, c]]) * (CROP / side)
    return np.hstack([rot, (np.array([CROP / 2, CROP / 2]) - rot @ (cx, cy))[:, None]]).astype(np.float32)


def region_from_box(box: Box) -> tuple[float, float, float, float]:
    """The first crop from a detector's box: its centre moved a tenth down (a face box stops at the brows;
    the mesh reaches the forehead and chin), 1.7 times its larger side, upright."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    return (x0 + x1) / 2, (y0 + y1) / 2 + 0.1 * h, 1.7 * max(w, h), 0.0


def region_from_mesh(points: np.ndarray) -> tuple[float, float, float, float]:
    """The next crop from a mesh ``[478, 2+]`` in image pixels: upright along the eye line, :data:`SCALE` x its extent."""
    p = points[:, :2]
    eye = p[LEFT_EYE_OUTER] - p[RIGHT_EYE_OUTER]
    angle = float(np.arctan2(eye[1], eye[0]))
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, s], [-s, c]])  # image -> upright
    q = p @ rot.T
    lo, hi = q.min(0), q.max(0)
    centre = ((lo + hi) / 2) @ rot  # upright -> image
    return float(centre[0]), float(centre[1]), float((hi - lo).max()) * SCALE, angle


class FaceMesh:
    """478 face points per frame. ``mesh(frame, region)`` for one crop; :meth:`track` over a clip."""

    def __init__(self, detect: Callable[[np.ndarray], Box | None] | None = None, session=None):
        self.session = session if session is not None else shipped_session()
        self._input = self.session.get_inputs()[0].name
        self.detect = detect if detect is not None else dlib_box
        self._region: tuple[float, float, float, float] | None = None

    def mesh(self, frame: np.ndarray, region: tuple[float, float, float, float]) -> tuple[np.ndarray, float]:
        """``(points [478, 3] in image pixels (z in pixels of the same scale), presence logit)`` of uint8 RGB ``frame``."""
        import cv2

        m = crop_matrix(*region)
        crop = cv2.warpAffine(frame, m, (CROP, CROP), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        x = (crop.astype(np.float32) / 255.0).transpose(2, 0, 1)[None].astype(np.float16)
        out = self.session.run(None, {self._input: x})
        local = np.asarray(out[0], np.float32).reshape(478, 3)
        inv = cv2.invertAffineTransform(m)
        pts = np.empty_like(local)
        pts[:, :2] = local[:, :2] @ inv[:, :2].T + inv[:, 2]
        pts[:, 2] = local[:, 2] * (region[2] / CROP)
        return pts, float(np.asarray(out[1], np.float32).ravel()[0])

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """The next frame of a clip: ``(points [478, 3], presence logit, detected)``; the crop follows the
        previous frame's mesh, a detector is run on the first frame and whenever the face is lost. No
        face: NaN points, presence -inf."""
        fresh = self._region is None
        if fresh:
            box = self.detect(frame)
            self._region = region_from_box(box) if box is not None else None
        p, logit = self.mesh(frame, self._region) if self._region is not None else (None, -np.inf)
        if p is not None and logit < PRESENCE and not fresh:  # lost: detect again on this frame
            box = self.detect(frame)
            fresh = True
            p, logit = self.mesh(frame, region_from_box(box)) if box is not None else (None, -np.inf)
        if p is None or logit < PRESENCE:
            self._region = None
            return np.full((478, 3), np.nan, np.float32), logit, fresh
        self._region = region_from_mesh(p)
        return p, logit, fresh

    def track(self, frames: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every frame's mesh: ``(points [T, 478, 3], presence [T], detected [T] bool)`` (:meth:`step` over a clip)."""
        self._region = None
        out = [self.step(frame) for frame in frames]
        if not out:
            return np.zeros((0, 478, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, bool)
        return (np.stack([o[0] for o in out]), np.asarray([o[1] for o in out], np.float32),
                np.asarray([o[2] for o in out]))


def dlib_box(frame: np.ndarray, max_side: int = 640) -> Box | None:
    """The largest face dlib's HOG detector (the ingest's, loaded once) finds on the frame shrunk to
    ``max_side``, or None.

    The frame goes to dlib C-contiguous: a decoder's frames are views with padded rows, and dlib
    20's detector, on the first such view of a process, found no face where it finds one on every later
    call (so an ingest's first mesh frame, and the whole track seeded from it, changed from run to run)."""
    import cv2

    from lmgs_eval.data.ingest.track import _models

    k = min(1.0, max_side / max(frame.shape[:2]))
    small = cv2.resize(frame, None, fx=k, fy=k, interpolation=cv2.INTER_AREA) if k < 1 else np.ascontiguousarray(frame)
    found = _models()[0](small, 1)
    if not found:
        return None
    r = max(found, key=lambda r: r.area())
    return r.left() / k, r.top() / k, r.right() / k, r.bottom() / k
