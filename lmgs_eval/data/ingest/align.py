"""Sub-pixel head motion from the images: the per-frame poses (the dense mesh's or the
landmarks', :mod:`pose`) refined by tracked texture.

A detector's 68 points jitter by about a pixel from frame to frame, and the pose fitted to
them (:mod:`pose`) jitters with them: a degree of rotation moves the top of the hair by a
pixel or two at 256 px, enough to blur what a method learns of the hair and to misplace it at
test time. The skull's upper part (forehead, brows, eyes, nose, upper cheeks) moves rigidly
and carries far more texture than 68 points. So corners are picked there in one reference
frame (the frame nearest the mean pose), placed in 3D on the head ellipsoid the depth priors
use (:mod:`geometry`) as that frame's pose sees it, and followed into every other frame by
pyramidal Lucas-Kanade flow (OpenCV), started where the frame's landmark pose projects them
and kept only where the flow back to the reference returns within half a pixel. The pose is
then solved again from those 2D-3D pairs (least squares from the landmark pose, twice, the
worst-fitting corners dropped in between). The result depends on the reference frame: on the
generator's 60 s head, forced to each of six frames, the refined poses' error spans 0.29-0.44 deg,
and neither re-anchoring the reference pose nor averaging references takes that out (design.md,
"Against the goals").

A frame cannot be refined when it is turned more than :data:`MAX_TURN_DEG` from the reference
(its texture no longer looks like the reference's), when too few corners survive, or when the
new pose moves its rigid landmarks' projections further from the detections than
:data:`MAX_SHIFT` face heights. The two kinds of pose differ by a bias of their own that grows
with the turn (on the generator's head turning +-28 deg, the dense mesh's poses are 3 deg off
where the refined ones are 1.2, and the correction reaches 8 deg at a 17 deg turn), so a clip of
both kinds would jump between them. Each frame that cannot be refined therefore *carries* the
correction of its refined neighbours (:func:`carry`): its own pose, corrected by the refined
frames' rotation and translation offsets interpolated in time (held beyond the first and the last
refined frame). Its frame-to-frame motion stays its own pose's; its bias becomes the refined
frames'. Unless :data:`MIN_SHARE` of the frames can be refined, every frame keeps its own pose
(too few offsets to carry).

The refinement is there to take the detector's jitter out of the poses, so it is kept only where
it does: where the refined poses' rotation is no rougher than the poses it started from
(:func:`roughness`, the mean second difference over runs of refined frames, at most
:data:`MAX_ROUGHER` times theirs). On the generator's turning heads and on a still studio clip
it is smoother (0.86-0.95 and 0.87 times the dense mesh's); on a hand-held phone clip whose head
turns +-20 deg it was 1.66 times rougher (the camera moves the head's texture against the
ellipsoid the corners sit on), and every frame keeps its own pose.

Nor is it kept where its poses turn less far than the poses it started from (:func:`follows`, the
slope of the one's smoothed rotation on the other's, under :data:`MIN_FOLLOW`): the tracked
texture then reads the head's turn short. On generated heads the refined poses turn 0.85-1.22 times
as far as the dense mesh's (which reads a photographed head's turn short); on five real clips,
1.15 and 1.21 on two where lmgs trained on the refined poses gained 2.1 and 0.6 dB over the dense
mesh's, 0.77 on one (+0.5), and 0.62 and 0.63 on two where it lost 3.4 and 0.5 dB (design.md,
"Refined poses that read the turn short").

What it gives up: the corners' depth is the ellipsoid's, not the face's. A wrong relief is not an
error the same in every frame: the rotation that moves corners of the wrong depth as far as the
image moved them is too large or too small by the relief's ratio, so the pose's error grows with the
turn (a gain), largest where the head is furthest from the face's centre (the hair's top and
outline), where a method sees the texture misplaced. On the generator's head the refined poses turn
0.84 times as far as the truth in pitch and 1.05 times in yaw; with the corners on the truth's own
depth, 0.93 and 1.09; on the tracked face mesh's depth, 0.49 and 0.53, as its relief over the upper
head slopes against the truth's (design.md, "Where the end-to-end gap lies"). The region is drawn
from landmarks, so a fringe over the forehead or a hand over the face enters it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_CORNERS = 200
MIN_TRACKED = 12  # fewer corners followed: the landmark pose stays
MAX_TURN_DEG = 12.0  # a frame turned further than this from the reference keeps its landmark pose
MAX_SHIFT = 0.05  # the new pose's rigid landmarks further than this share of the face height from the detections: rejected
MIN_SHARE = 0.25  # the share of the frames that must be refined for the rest to carry their correction, or none is
MAX_ROUGHER = 1.0  # the refined poses' roughness over the input's: above it, none is kept
MIN_FOLLOW = 0.7  # the refined poses turn less than this share of the input's turn (:func:`follows`): none is kept
FOLLOW_SIGMA = 2.0  # frames: the Gaussian both rotations are smoothed by before :func:`follows` compares them
MIN_SPAN_DEG = 1.0  # the input's smoothed rotation about its mean, RMS: below it the input turns too little to compare
FB_PX = 0.5  # forward-backward flow disagreement allowed, pixels
OUTLIER_PX = 1.0  # a corner further than this (at 256 px) from the solved pose's projection is dropped


@dataclass
class Refined:
    """Per frame: rotation and translation vectors (OpenCV), whether the images set them, how
    many corners did; the reference frame, how many frames could be refined (none is when fewer
    than :data:`MIN_SHARE` could, or when the refined poses are rougher than the input's or turn
    short of it), how many carry their refined neighbours' correction, the roughness
    (:func:`roughness`) of the input's and of the refined poses, how far the refined poses turn where the input's do
    (:func:`follows`; NaN where the input turns too little to tell), and why none was kept where
    none was (``"few"``: under :data:`MIN_SHARE` refinable; ``"rough"``: rougher than the input;
    ``"flat"``: turning less than :data:`MIN_FOLLOW` times as far as the input; ``""`` otherwise)."""

    rv: np.ndarray
    tv: np.ndarray
    used: np.ndarray
    tracked: np.ndarray
    reference: int
    refinable: int = 0
    carried: int = 0
    roughness: tuple[float, float] = (float("nan"), float("nan"))
    follows: float = float("nan")
    refused: str = ""


def upper_head_mask(lms: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The skull's rigid upper part in one frame, bool ``[H, W]``: the hull of the brows raised
    by 0.3 face heights, the jaw's upper ends (0-2, 14-16) and the nose's base (31-35)."""
    import cv2

    fh = lms[8, 1] - lms[17:27, 1].mean()
    brows = lms[17:27] - [0.0, 0.3 * fh]
    pts = np.concatenate([lms[[0, 1, 2, 14, 15, 16]], lms[31:36], brows]).astype(np.float32)
    m = np.zeros(shape, np.uint8)
    hull = np.round(cv2.convexHull(pts)[:, 0] * 16).astype(np.int32)
    cv2.fillConvexPoly(m, hull, 1, cv2.LINE_8, 4)
    return m.astype(bool)


def _grey(path: Path) -> np.ndarray:
    import cv2

    from lmgs_eval.data.images import read_rgb_u8

    return cv2.cvtColor(read_rgb_u8(path), cv2.COLOR_RGB2GRAY)


def refine(frame_paths: list[Path], lms: np.ndarray, rv: np.ndarray, tv: np.ndarray, focal: float, w: int, h: int,
           template: np.ndarray, rigid: np.ndarray) -> Refined:
    """Refine per-frame poses ``rv``, ``tv`` (``[N, 3]``, OpenCV world-to-camera; the dense mesh's
    or the landmarks') by tracked corners; ``template``: the fitted ``[68, 3]`` points, ``rigid`` the
    indices whose projections must stay near the detected landmarks."""
    import cv2
    from scipy.spatial.transform import Rotation

    from lmgs_eval.data.geometry import head_ellipsoid, render_prior

    n = len(frame_paths)
    rots = Rotation.from_rotvec(rv)
    ref = int(np.argmin(np.linalg.norm(about_mean(rv), axis=1)))
    turn = np.degrees((rots[ref].inv() * rots).magnitude())
    K = np.array([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1]], np.float64)
    w2c_ref = np.eye(4)
    w2c_ref[:3, :3], w2c_ref[:3, 3] = rots[ref].as_matrix(), tv[ref]
    g_ref = _grey(frame_paths[ref])
    mask = upper_head_mask(lms[ref], (h, w))
    centre, axes = head_ellipsoid(template)
    depth, _ = render_prior(w2c_ref, focal, w, h, centre, axes, mask, rim=False)  # corners on the surface only
    scale = max(h, w) / 256.0
    corners = cv2.goodFeaturesToTrack(g_ref, MAX_CORNERS, 0.01, max(2.0, 3 * scale), mask=(depth > 0).astype(np.uint8),
                                      blockSize=max(3, int(round(5 * scale)) | 1))
    out = Refined(rv.copy(), tv.copy(), np.zeros(n, bool), np.zeros(n, int), ref, refused="few")
    if corners is None or len(corners) < MIN_TRACKED:
        return out
    p_ref = corners[:, 0].astype(np.float32)  # OpenCV pixel coordinates (a pixel's centre at its index)
    z = depth[np.clip(np.rint(p_ref[:, 1]).astype(int), 0, h - 1), np.clip(np.rint(p_ref[:, 0]).astype(int), 0, w - 1)]
    cam = np.stack([(p_ref[:, 0] + 0.5 - w / 2) / focal * z, (p_ref[:, 1] + 0.5 - h / 2) / focal * z, z], 1)
    c2w = np.linalg.inv(w2c_ref)
    world = cam @ c2w[:3, :3].T + c2w[:3, 3]
    win = (max(9, int(round(15 * scale)) | 1),) * 2
    lk = dict(winSize=win, maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    fh = lms[:, 8, 1] - lms[:, 17:27, 1].mean(1)
    out.used[ref], out.tracked[ref] = True, len(p_ref)
    for i in range(n):
        if i == ref or turn[i] > MAX_TURN_DEG:
            continue
        guess, _ = cv2.projectPoints(world, rv[i], tv[i], K, None)
        guess = (guess[:, 0] - 0.5).astype(np.float32)
        g = _grey(frame_paths[i])
        fwd, ok1, _ = cv2.calcOpticalFlowPyrLK(g_ref, g, p_ref, guess.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(g, g_ref, fwd, p_ref.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        good = (ok1[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm(back - p_ref, axis=1) < FB_PX)
        if good.sum() < MIN_TRACKED:
            continue
        obj, img = world[good], fwd[good].astype(np.float64) + 0.5
        r, t = rv[i].reshape(3, 1).copy(), tv[i].reshape(3, 1).copy()
        keep = np.ones(len(obj), bool)
        for _ in range(2):  # least squares from the landmark pose, the worst corners dropped, again
            _, r, t = cv2.solvePnP(obj[keep], img[keep], K, None, r, t, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
            res = np.linalg.norm(cv2.projectPoints(obj, r, t, K, None)[0][:, 0] - img, axis=1)
            keep = res < max(OUTLIER_PX * scale, 2.5 * np.median(res))
        if keep.sum() < MIN_TRACKED or t[2, 0] <= 0:
            continue
        proj, _ = cv2.projectPoints(template[rigid], r, t, K, None)
        if np.median(np.linalg.norm(proj[:, 0] - lms[i, rigid], axis=1)) > MAX_SHIFT * fh[i]:
            continue
        out.rv[i], out.tv[i], out.used[i], out.tracked[i] = r.ravel(), t.ravel(), True, int(keep.sum())
    out.refinable = int(out.used.sum())
    out.roughness = (roughness(rv, out.used), roughness(out.rv, out.used))
    out.follows = follows(rv, out.rv, out.used)
    out.refused = ("few" if out.refinable < MIN_SHARE * n else
                   "rough" if out.roughness[1] > MAX_ROUGHER * out.roughness[0] else
                   "flat" if out.follows < MIN_FOLLOW else "")
    if out.refused:
        out.rv, out.tv, out.used[:] = rv.copy(), tv.copy(), False
    elif out.refinable < n:
        out.rv, out.tv = carry(rv, tv, out.rv, out.tv, out.used)
        out.carried = n - out.refinable
    return out


def about_mean(rv: np.ndarray) -> np.ndarray:
    """Rotations ``rv`` (``[N, 3]`` vectors) as rotation vectors about their mean rotation."""
    from scipy.spatial.transform import Rotation

    r = Rotation.from_rotvec(rv)
    return (r.mean().inv() * r).as_rotvec()


def roughness(rv: np.ndarray, sel: np.ndarray) -> float:
    """How rough a sequence of rotations (``[N, 3]`` vectors) is where ``sel`` holds three frames in a
    row: the mean norm of the second difference of the rotations (about their mean), degrees; NaN
    without such a triple. A head turns smoothly at 25 frames a second: what is rough is mostly
    the pose's noise."""
    v = about_mean(rv)
    triple = sel[2:] & sel[1:-1] & sel[:-2]
    if not triple.any():
        return float("nan")
    return float(np.degrees(np.linalg.norm(v[2:] - 2 * v[1:-1] + v[:-2], axis=1))[triple].mean())


def follows(rv: np.ndarray, rv_new: np.ndarray, sel: np.ndarray) -> float:
    """How far the rotations ``rv_new`` turn where ``rv`` turn (``[N, 3]`` vectors), over the frames
    ``sel``: the slope of ``rv_new``'s rotation about its mean regressed on ``rv``'s, the three axes
    pooled, both smoothed over time by a Gaussian of :data:`FOLLOW_SIGMA` frames first (jitter in
    the regressor would flatten the slope). 1 where the two turn alike; NaN where ``rv``'s smoothed
    rotation spans less than :data:`MIN_SPAN_DEG` (RMS about its mean), since its turn is then
    mostly its jitter, or where fewer than three frames are selected."""
    from scipy.ndimage import gaussian_filter1d

    if sel.sum() < 3:
        return float("nan")
    x = gaussian_filter1d(about_mean(rv[sel]), FOLLOW_SIGMA, axis=0, mode="nearest")
    y = gaussian_filter1d(about_mean(rv_new[sel]), FOLLOW_SIGMA, axis=0, mode="nearest")
    x, y = x - x.mean(0), y - y.mean(0)
    if np.degrees(np.sqrt((x ** 2).sum(1).mean())) < MIN_SPAN_DEG:
        return float("nan")
    return float((x * y).sum() / (x * x).sum())


def carry(rv: np.ndarray, tv: np.ndarray, rv_ref: np.ndarray, tv_ref: np.ndarray,
          used: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``rv``, ``tv`` (``[N, 3]``, OpenCV world-to-camera) where ``used`` holds the refined
    ones ``rv_ref``, ``tv_ref``, the others corrected as their refined neighbours were: with the
    offset ``D`` (a rotation in the camera's frame, ``R_ref = D R``) and ``e`` (``t_ref = D t + e``)
    of the refined frames, slerped and linearly interpolated at each other frame's index (held
    beyond the first and the last refined one)."""
    from scipy.spatial.transform import Rotation, Slerp

    idx = np.flatnonzero(used)
    miss = np.flatnonzero(~used)
    out_r, out_t = rv_ref.copy(), tv_ref.copy()
    if len(idx) == 0 or len(miss) == 0:
        return out_r, out_t
    d = Rotation.from_rotvec(rv_ref[idx]) * Rotation.from_rotvec(rv[idx]).inv()
    e = tv_ref[idx] - d.apply(tv[idx])
    at = np.clip(miss, idx[0], idx[-1]).astype(float)
    dm = Slerp(idx.astype(float), d)(at) if len(idx) > 1 else Rotation.from_rotvec(np.repeat(d.as_rotvec(), len(miss), 0))
    em = np.stack([np.interp(at, idx, e[:, c]) for c in range(3)], 1)
    out_r[miss] = (dm * Rotation.from_rotvec(rv[miss])).as_rotvec()
    out_t[miss] = dm.apply(tv[miss]) + em
    return out_r, out_t
