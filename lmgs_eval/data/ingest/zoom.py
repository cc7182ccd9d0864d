"""Does the whole frame scale with the face? A zooming camera told from a head that moves.

The layout has one focal length per subject, so the pose fit reads a face that grows in the
frame as a head (camera) that comes nearer. For the head's own pixels that reading is nearly
exact: a zoom and a camera that moves along its view so that the face scales alike differ only
through the face's depth relief, and the landmarks of the two differ by a tenth of a pixel or
less (a relief of +-5 cm at a metre, an 8 % zoom). The face alone cannot tell them apart.

What can is everything outside the head: a zoom scales the background and the torso with the
face, about the principal point; a head that moves before a still camera leaves them where they
were; a camera moving towards the person scales them by less, the farther they are. So a few
sampled frames are registered to a reference frame (the one at the median face scale) by an
affine warp (ECC: OpenCV's ``findTransformECC``) over the frame minus the head (a widened head
prior in both frames), and the warp's scale is set against the face's (the inverse of the
fitted camera distance). A zoom or a dolly is what the layout cannot hold: its plate and torso
assume a still frame.

The registration starts from no motion, so a background with too little texture to move the
estimate reads as still: a zoom in front of a blank wall goes unseen here (the face's own scale
range is recorded beside it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

SIDE = 128  # frames are registered at this size (grey, blurred)
SAMPLES = 40  # frames sampled over the clip
HEAD_GROW = 1.3  # the head prior widened by this factor about the face centre is left out
MIN_OUTSIDE = 0.1  # share of the frame outside the head needed to register it
MIN_SCALE_RANGE = 0.03  # the frame's scale must change by more than this (max - min) ...
MIN_CORR = 0.8  # ... in step with the face's (correlation) ...
MIN_SLOPE = 0.5  # ... by at least this share of the face's change, for the flag


@dataclass
class ScaleCheck:
    """The face's and the frame's scale over sampled frames, relative to a reference frame.

    Attributes:
        ids: ``[k]`` sampled frame indices; ref: the reference frame.
        face: ``[k]`` face scale (reference camera distance / this frame's).
        frame: ``[k]`` scale of the frame outside the head (NaN where it could not be registered:
            too little of it, or too little texture for ECC to converge).
        slope: least-squares slope of ``frame - 1`` on ``face - 1`` (1: a zoom; 0: a still camera).
        corr: their correlation (NaN when either is constant).
    """

    ids: np.ndarray
    ref: int
    face: np.ndarray
    frame: np.ndarray
    slope: float
    corr: float

    @property
    def face_range(self) -> float:
        return float(np.ptp(self.face))

    @property
    def frame_range(self) -> float:
        ok = np.isfinite(self.frame)
        return float(np.ptp(self.frame[ok])) if ok.sum() > 1 else 0.0

    @property
    def zooms(self) -> bool:
        """The frame scales with the face: a zoom, or a camera moving along its view."""
        return bool(self.frame_range > MIN_SCALE_RANGE and self.corr > MIN_CORR and self.slope > MIN_SLOPE)

    def to_json(self) -> dict:
        r = lambda x: None if not np.isfinite(x) else round(float(x), 4)  # noqa: E731
        return {"face_scale_range": r(self.face_range), "frame_scale_range": r(self.frame_range), "slope": r(self.slope),
                "corr": r(self.corr), "reference_frame": int(self.ref), "frames": [int(i) for i in self.ids],
                "face_scale": [r(x) for x in self.face], "frame_scale": [r(x) for x in self.frame]}


def _grey(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    small = cv2.resize(img, (SIDE, SIDE), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return cv2.GaussianBlur(small, (0, 0), 1.0)


def _outside_head(lms: np.ndarray, size: int) -> np.ndarray:
    from lmgs_eval.data.ingest.parsing import _poly, head_outline

    l = lms * (SIDE / size)
    prior = head_outline(l)
    c = l[:68].mean(0)
    return ~_poly(c + HEAD_GROW * (prior - c), (SIDE, SIDE))


def check_scale(img_dir: Path, lms: np.ndarray, c2w: np.ndarray, size: int, samples: int = SAMPLES) -> ScaleCheck:
    """:class:`ScaleCheck` of the frames ``img_dir/<i>.jpg`` (``size`` pixels square) with their
    landmarks ``[N, 68, 2]`` and fitted cameras ``[N, 4, 4]``."""
    import cv2

    n = len(lms)
    dist = np.linalg.norm(c2w[:, :3, 3], axis=1)
    ids = np.unique(np.linspace(0, n - 1, min(samples, n)).round().astype(int))
    ref = int(ids[np.argsort(dist[ids])[len(ids) // 2]])  # the median face scale
    face = dist[ref] / dist[ids]
    tmpl = _grey(img_dir / f"{ref}.jpg")
    keep_ref = _outside_head(lms[ref], size)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-6)
    frame = np.full(len(ids), np.nan)
    for k, i in enumerate(ids):
        if i == ref:
            frame[k] = 1.0
            continue
        mask = (keep_ref & _outside_head(lms[i], size)).astype(np.uint8)
        if mask.mean() < MIN_OUTSIDE:  # a tight head crop: too little frame to register
            continue
        warp = np.eye(2, 3, dtype=np.float32)
        try:
            _, warp = cv2.findTransformECC(tmpl, _grey(img_dir / f"{i}.jpg"), warp, cv2.MOTION_AFFINE, crit, mask, 5)
        except cv2.error:  # did not converge: too little texture outside the head
            continue
        frame[k] = float(np.sqrt(abs(np.linalg.det(warp[:, :2]))))
    ok = np.isfinite(frame)
    x, y = face[ok] - 1.0, frame[ok] - 1.0
    slope = float(x @ y / (x @ x)) if ok.sum() > 2 and x @ x > 0 else float("nan")
    corr = float(np.corrcoef(x, y)[0, 1]) if ok.sum() > 2 and x.std() > 0 and y.std() > 0 else float("nan")
    return ScaleCheck(ids, ref, face, frame, slope, corr)
