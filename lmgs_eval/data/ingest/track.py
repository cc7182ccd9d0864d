"""Face tracking with dlib: detect, follow by landmarks, re-detect when lost; gaps and smoothing.

dlib's HOG detector (its 68-point shape predictor's own detector, from
``face_recognition_models``) is run on the first frame, every ``REDETECT`` frames and whenever
the track is lost; in between, the box for frame ``k`` comes from the landmarks of frame
``k - 1`` (the box-to-landmark relation measured at the last detection), so the predictor
follows the face at a few milliseconds a frame. A tracked shape is rejected (and the face
re-detected) when it jumps or changes scale more than a head can between two frames, or when its
upper face no longer looks like the last detection's (something before the face). After the
first detection the track keeps to its face: see :func:`_detect`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from lmgs_eval.errors import UserError

REDETECT = 25  # frames between detections while the track holds
MAX_GAP = 12  # frames: shorter gaps without a face are interpolated, longer ones left out
DETECT_SIDE = 640  # the detector runs on a copy scaled to at most this side (faces from ~80 px
# there are found at once; smaller ones by a second pass at twice the size)


@dataclass
class Track:
    """68 landmarks per frame in the coordinates of the frames given to :func:`track_faces`.

    Attributes:
        lms: ``[N, 68, 2]`` float64, NaN where no face was found.
        faces: ``[N]`` faces the detector saw (-1 on frames where it did not run).
        detected: ``[N]`` bool, the detector ran on this frame.
        others: ``[N]`` faces the detector saw that were not the tracked one.
    """

    lms: np.ndarray
    faces: np.ndarray
    detected: np.ndarray
    others: np.ndarray

    @property
    def found(self) -> np.ndarray:
        return np.all(np.isfinite(self.lms), axis=(1, 2))


def _models():
    from lmgs_eval.data.bundled.photo import _dlib_models

    return _dlib_models()


def _spread(l: np.ndarray) -> float:
    return float(np.sqrt(((l - l.mean(0)) ** 2).sum(1).mean()))


def _shape(sp, img, box) -> np.ndarray:
    import dlib

    r = dlib.rectangle(*[int(round(v)) for v in box])
    s = sp(img, r)
    return np.array([[p.x + 0.5, p.y + 0.5] for p in s.parts()], np.float64)


UPPER = slice(17, 48)  # brows, nose and eyes: the part of the face that speech does not move
PATCH = (32, 20)  # the upper face is compared at this size (width, height)
MIN_LIKENESS = 0.35  # normalised correlation with the upper face at the last detection below which a
# tracked shape is not believed (a hand or an object before the face) and the detector runs


def _upper_face(grey: np.ndarray, shape: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The upper face of ``shape`` in ``grey``, warped onto ``ref``'s upper face by a similarity
    and sampled to :data:`PATCH`, zero-mean and unit-norm (for a normalised correlation)."""
    import cv2

    m, _ = cv2.estimateAffinePartial2D(shape[UPPER].astype(np.float32), ref[UPPER].astype(np.float32))
    if m is None:
        return np.zeros(PATCH[0] * PATCH[1], np.float32)
    (x0, y0), (x1, y1) = ref[UPPER].min(0), ref[UPPER].max(0)
    to_patch = np.array([[PATCH[0] / max(x1 - x0, 1.0), 0, 0], [0, PATCH[1] / max(y1 - y0, 1.0), 0]])
    to_patch[:, 2] = -to_patch[:, :2] @ np.array([x0, y0])
    full = to_patch @ np.vstack([m, [0, 0, 1]])
    p = cv2.warpAffine(grey, full, PATCH, flags=cv2.INTER_AREA).astype(np.float32).ravel()
    p -= p.mean()
    return p / max(float(np.linalg.norm(p)), 1e-6)


def _detect(det, grey: np.ndarray, prev_box, lost: int = 0, size: float | None = None) -> tuple[list, int]:
    """Face boxes ``(l, t, r, b)`` in ``grey``'s pixels, best first, and how many were seen.

    With a track (``prev_box``, the tracked face's box, last seen ``lost`` frames ago; ``size``,
    the width of its last detected box, else ``prev_box``'s) only boxes that can be that face
    are returned, nearest first: a width within 1.5x of ``size`` and a centre within a box
    width of ``prev_box``'s, and two more per second it has been lost. Another face
    (a second person, a face on a poster or a screen) is never taken over when the tracked
    one is briefly missed (a hand before it, a turn away): the frame goes without a face.
    """
    import cv2

    h, w = grey.shape
    s = min(1.0, DETECT_SIDE / max(h, w))
    small = cv2.resize(grey, (int(round(w * s)), int(round(h * s))), interpolation=cv2.INTER_AREA) if s < 1 else grey
    rects = det(small, 0)
    if len(rects) == 0:
        rects = det(small, 1)
    boxes = [(r.left() / s, r.top() / s, r.right() / s, r.bottom() / s) for r in rects]
    if not boxes:
        return [], 0

    if prev_box is not None:  # stay with the face being tracked
        size = size or prev_box[2] - prev_box[0]
        reach = size * (1.0 + 2.0 * lost / 25)
        centre = np.array([(prev_box[0] + prev_box[2]) / 2, (prev_box[1] + prev_box[3]) / 2])

        def dist(b):
            return float(np.hypot((b[0] + b[2]) / 2 - centre[0], (b[1] + b[3]) / 2 - centre[1]))

        same = [b for b in boxes if 1 / 1.5 < (b[2] - b[0]) / size < 1.5 and dist(b) < reach]
        return sorted(same, key=dist), len(boxes)

    def score(b):
        area = (b[2] - b[0]) * (b[3] - b[1])
        cx, cy = (b[0] + b[2]) / 2 / w - 0.5, (b[1] + b[3]) / 2 / h - 0.5
        return area * (1.0 - min(0.9, np.hypot(cx, cy)))  # largest, most central

    return sorted(boxes, key=score, reverse=True), len(boxes)


def track_faces(frames: Iterable[tuple[int, np.ndarray]], n: int, progress=None) -> Track:
    """Track one face through ``frames`` (``(k, rgb uint8)`` for ``k = 0..n-1``)."""
    import cv2

    det, sp = _models()
    lms = np.full((n, 68, 2), np.nan)
    faces = np.full(n, -1, np.int64)
    detected = np.zeros(n, bool)
    others = np.zeros(n, np.int64)
    lost = 0  # frames since the tracked face was last found
    size = None  # width of its last detected box (the shape predictor can follow a hand for a while; a detection cannot)
    anchor = look = None  # landmarks and upper face at the last detection
    prev = None  # landmarks of the previous frame
    rel = None  # box relative to the landmarks: (dx, dy, half size) in units of their spread
    box = None
    for k, img in frames:
        grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        cur = None
        if prev is not None and k % REDETECT != 0:
            c, s = prev.mean(0), _spread(prev)
            box = (c[0] + rel[0] * s - rel[2] * s, c[1] + rel[1] * s - rel[2] * s,
                   c[0] + rel[0] * s + rel[2] * s, c[1] + rel[1] * s + rel[2] * s)
            cand = _shape(sp, grey, box)
            jump = np.linalg.norm(cand.mean(0) - c) / s
            ratio = _spread(cand) / s
            if jump < 0.25 and 0.85 < ratio < 1.18 and float(look @ _upper_face(grey, cand, anchor)) > MIN_LIKENESS:
                cur = cand
        if cur is None:
            boxes, count = _detect(det, grey, box, lost, size)
            detected[k], faces[k], others[k] = True, count, count - min(1, len(boxes))
            if boxes:
                box = boxes[0]
                size = box[2] - box[0]
                cur = _shape(sp, grey, box)
                anchor, look = cur, _upper_face(grey, cur, cur)
                c, s = cur.mean(0), _spread(cur)
                bc = ((box[0] + box[2]) / 2, (box[1] + box[3]) / 2)
                rel = ((bc[0] - c[0]) / s, (bc[1] - c[1]) / s, (box[2] - box[0]) / 2 / s)
        if cur is not None:
            lms[k] = cur
        lost = 0 if cur is not None else lost + 1
        prev = cur
        if progress is not None:
            progress.update(1)
    return Track(lms, faces, detected, others)


@dataclass(frozen=True)
class Coverage:
    """Which frames keep a face after gap filling.

    Attributes:
        first, last: the kept range ``[first, last)`` (faceless ends are cut).
        missing: frames without a face inside short gaps (interpolated).
        cut: frames without a face at either end (dropped).
        dropped: frames of inner gaps longer than ``MAX_GAP`` (left out: the kept frames
            jump over them, as at a cut).
    """

    first: int
    last: int
    missing: tuple[int, ...]
    cut: tuple[int, ...]
    dropped: tuple[int, ...] = ()

    @property
    def kept(self) -> np.ndarray:
        """The source frames kept, in order: ``[first, last)`` less ``dropped``."""
        k = np.arange(self.first, self.last)
        return k[~np.isin(k, self.dropped)]


def fill_gaps(lms: np.ndarray, video: str) -> tuple[np.ndarray, Coverage]:
    """Cut faceless frames at either end, interpolate inner gaps up to ``MAX_GAP`` frames and
    leave longer ones out (a hand before the face, the head turned away for a while).

    Returns:
        ``[len(cov.kept), 68, 2]`` landmarks of the kept frames, and the :class:`Coverage`.

    Raises:
        UserError: no face in any frame.
    """
    ok = np.all(np.isfinite(lms), axis=(1, 2))
    if not ok.any():
        raise UserError(f"{video}: no face found in any frame (dlib's frontal face detector; faces must be at least ~80 px and roughly frontal)")
    idx = np.nonzero(ok)[0]
    first, last = int(idx[0]), int(idx[-1]) + 1
    cut = tuple(range(0, first)) + tuple(range(last, len(lms)))
    out = lms[first:last].copy()
    bad = ~ok[first:last]
    missing: tuple[int, ...] = ()
    dropped: tuple[int, ...] = ()
    if bad.any():
        edges = np.diff(np.concatenate([[0], bad.astype(np.int8), [0]]))
        starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
        long = [(a, b) for a, b in zip(starts, ends) if b - a > MAX_GAP]
        dropped = tuple(int(k) + first for a, b in long for k in range(a, b))
        missing = tuple(sorted(set(int(k) + first for k in np.nonzero(bad)[0]) - set(dropped)))
        good = np.nonzero(~bad)[0]
        flat = out.reshape(len(out), -1)
        for j in range(flat.shape[1]):
            flat[bad, j] = np.interp(np.nonzero(bad)[0], good, flat[good, j])
        out = flat.reshape(out.shape)
    cov = Coverage(first, last, missing, cut, dropped)
    return out[cov.kept - first], cov


def segments(source: np.ndarray) -> list[slice]:
    """Runs of consecutive source frames in ``source`` (the kept frames), as slices of it."""
    breaks = np.nonzero(np.diff(source) != 1)[0] + 1
    bounds = [0, *breaks.tolist(), len(source)]
    return [slice(a, b) for a, b in zip(bounds, bounds[1:])]


def smooth_landmarks(lms: np.ndarray, window: int = 5) -> np.ndarray:
    """Savitzky-Golay smoothing along time (quadratic, ``window`` frames), which removes the
    detector's frame-to-frame jitter but keeps the peaks of fast mouth motion that a moving
    average would flatten. Clips shorter than the window are returned unchanged."""
    from scipy.signal import savgol_filter

    if len(lms) < window:
        return lms.copy()
    return savgol_filter(lms, window, 2, axis=0, mode="interp")
