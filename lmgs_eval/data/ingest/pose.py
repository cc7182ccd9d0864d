"""Head pose and camera from 2D landmarks: a 68-point 3D template, one focal length per clip.

The fit, in three steps:

1. **Shape, once per subject.** The template's ``x, y`` are the subject's own median landmark
   layout over the frames nearest frontal (:data:`FRONTAL_SHARE` of them, by the nose's place
   between the jaw's ends: :func:`yaw_asymmetry`; each aligned to the most frontal one by a
   similarity transform, then the per-point median), scaled so the jaw (landmarks 0-16) spans
   :data:`JAW_WIDTH` metres; its depth ``z`` is the generic relief
   :data:`lmgs.landmarks.MEAN_FACE_DEPTH` (nose tip in front, jaw angle behind) times the same
   width times :data:`lmgs_eval.data.geometry.RELIEF`. The median over every frame would be a
   turned face's layout wherever the head looks to one side for most of the clip, and the fit
   would take that turn for frontal: on a bundled head that turns from 0 to 30 deg and back
   (astronaut, 256 px, 3 s) it did (yaw -13..+9 deg, 5.5 deg mean rotation error); from the
   frontal quarter 2.8 deg.
2. **Focal length**: given (``--focal``, or :mod:`focal`'s joint fit on the dense mesh). Of the
   68 points and a generic template it cannot be had: a search over focal lengths found the
   reprojection error falling steadily to the longest lens tried (a flatter projection hides
   the template's depth error) on the bundled subjects and on 4 of 5 real clips.
3. **Pose, per frame**, with that focal; given the frames, refined by corners of the upper
   head tracked from a reference frame (:mod:`align`: every frame or none); then smoothed
   over time (Gaussian, ``sigma`` frames).

The head is the world (fixed at the origin, OpenGL axes: x right, y up, z towards the
camera at rest); the camera moves: ``transform_matrix = c2w`` (ER-NeRF's convention).

Against a 3DMM tracker (ER-NeRF's BFM fit): no identity or expression basis, so the template's
depth is generic and expression is not separated from pose (a wide-open mouth pulls the pose
a little); the images enter only through the tracked corners of :mod:`align`, whose depth
is a generic ellipsoid's, and not at all when the head turns far (the 68 points alone then);
and jaw landmarks of a real face are silhouette points that slide under yaw, read here as
fixed surface points. It needs no model download; the landmark fit runs at hundreds of frames
a second, the tracking at about 250.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lmgs_eval.data.geometry import RELIEF

JAW_WIDTH = 0.135  # metres between landmarks 0 and 16 (an adult face; the bundled heads use the same)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# Points that move with the skull, for the rigid fit: nose and eyes. The jaw line is left out
# (a detector's jaw points are silhouette points that slide when the head turns), and so are
# the brows (they rise with expression). On a bundled subject's own video (astronaut, 256 px,
# 4 s) this set gave 0.84 deg mean rotation error from dlib's landmarks, against 1.22 deg with
# jaw line and brows in. (On the generator's own landmarks, which are surface points, the jaw
# line helps instead: 0.34 deg with it, 1.8 without; that is the generic relief of nose and
# eyes differing from the bundled head's, a limit of the template.)
RIGID = np.r_[27:48]
# The template's layout: the median of this share of the frames, those nearest frontal (at least 10).
FRONTAL_SHARE = 0.25

@dataclass
class PoseFit:
    """The fitted template and cameras.

    Attributes:
        template: ``[68, 3]`` world points (metres, OpenGL axes, head at the origin).
        focal: pixels (square pixels, principal point at the frame centre).
        w2c: ``[N, 4, 4]`` world-to-camera, OpenCV axes.
        c2w: ``[N, 4, 4]`` camera-to-world, OpenGL axes (``transform_matrix``).
        euler: ``[N, 3]`` head (pitch, yaw, roll) in radians, relative to facing the camera.
        trans: ``[N, 3]`` head translation in the camera frame (OpenGL axes), metres.
        reproj_px: ``[N]`` mean reprojection error of the rigid points after smoothing.
        aligned: ``[N]`` bool, the frames whose pose the images refined (:mod:`align`), or None.
        reference: the frame the others were tracked from (-1 without images).
        refinable: how many frames the images could refine (all are, or none: ``align.MIN_SHARE``).
    """

    template: np.ndarray
    focal: float
    w2c: np.ndarray
    c2w: np.ndarray
    euler: np.ndarray
    trans: np.ndarray
    reproj_px: np.ndarray
    aligned: np.ndarray | None = None
    reference: int = -1
    refinable: int = 0


def _similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``src`` mapped onto ``dst`` by the least-squares similarity transform (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, d]) @ vt
    scale = (s * [1.0, d]).sum() / (a**2).sum()
    return (a @ r.T) * scale + md


def yaw_asymmetry(lms: np.ndarray) -> np.ndarray:
    """How far the nose tip (30) sits from midway between the jaw's ends (0, 16) along the eye
    line, per frame ``[N]``: ``(a - b) / (a + b)`` with ``a``, ``b`` its distances to either end;
    near 0 for a frontal face, positive when the nose is nearer landmark 16, unchanged by roll
    and scale."""
    u = lms[:, 42:48].mean(1) - lms[:, 36:42].mean(1)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    a = ((lms[:, 30] - lms[:, 0]) * u).sum(1)
    b = ((lms[:, 16] - lms[:, 30]) * u).sum(1)
    return (a - b) / np.maximum(a + b, 1e-9)


def build_template(lms: np.ndarray) -> np.ndarray:
    """The subject's 3D template ``[68, 3]`` from its 2D landmark track ``[N, 68, 2]``."""
    from lmgs.landmarks import MEAN_FACE_DEPTH

    off = np.abs(yaw_asymmetry(lms))
    m = min(len(lms), max(10, int(round(FRONTAL_SHARE * len(lms)))))
    front = np.argsort(off, kind="stable")[:m]
    ref = lms[front[0]]
    step = max(1, m // 200)
    aligned = np.stack([_similarity(l, ref) for l in lms[np.sort(front)[::step]]])
    mean2d = np.median(aligned, axis=0)
    k = JAW_WIDTH / np.linalg.norm(mean2d[16] - mean2d[0])
    x = (mean2d[:, 0] - mean2d[:, 0].mean()) * k
    y = -(mean2d[:, 1] - mean2d[:, 1].mean()) * k
    # level the eyes: the median layout may carry the subject's habitual roll
    ang = np.arctan2(y[45] - y[36], x[45] - x[36])
    c, s = np.cos(-ang), np.sin(-ang)
    x, y = c * x - s * y, s * x + c * y
    z = -MEAN_FACE_DEPTH * JAW_WIDTH * RELIEF
    z = z - z.mean()
    return np.stack([x, y, z], 1)


def _solve(obj: np.ndarray, img: np.ndarray, f: float, w: int, h: int, guess=None):
    import cv2

    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], np.float64)
    if guess is None:
        jaw_px = np.linalg.norm(img[16] - img[0])
        rvec = np.array([np.pi, 0.0, 0.0])  # OpenGL world -> OpenCV camera, facing it
        tvec = np.array([(img[:, 0].mean() - w / 2) * JAW_WIDTH / jaw_px, (img[:, 1].mean() - h / 2) * JAW_WIDTH / jaw_px,
                         f * JAW_WIDTH / jaw_px])
    else:
        rvec, tvec = guess
    ok, rvec, tvec = cv2.solvePnP(obj[RIGID], img[RIGID], K, None, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy(),
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    rvec, tvec = rvec.ravel(), tvec.ravel()
    proj, _ = cv2.projectPoints(obj[RIGID], rvec, tvec, K, None)
    err = float(np.linalg.norm(proj[:, 0] - img[RIGID], axis=1).mean())
    return rvec, tvec, err


def _rodrigues(v: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(v, np.float64).reshape(3, 1))[0]


def euler_pyr(R: np.ndarray) -> np.ndarray:
    """(pitch, yaw, roll) with ``R = Ry(yaw) Rx(pitch) Rz(roll)`` (the bundled generator's order)."""
    pitch = np.arcsin(np.clip(-R[1, 2], -1, 1))
    yaw = np.arctan2(R[0, 2], R[2, 2])
    roll = np.arctan2(R[1, 0], R[1, 1])
    return np.array([pitch, yaw, roll])


def fit_poses(lms: np.ndarray, w: int, h: int, *, focal: float, sigma: float = 2.0,
              frames: list | None = None, runs: list[slice] | None = None) -> PoseFit:
    """Template and smoothed per-frame poses for landmarks ``[N, 68, 2]`` (output pixels) seen with ``focal`` (pixels).

    ``frames``: the frames' image paths; with them each landmark pose is refined by the upper
    head's texture tracked from a reference frame (:mod:`align`) before the smoothing.
    ``runs``: runs of consecutive source frames (where frames were left out between them),
    each smoothed on its own; default one run.
    """
    from scipy.ndimage import gaussian_filter1d
    from scipy.spatial.transform import Rotation

    obj = build_template(lms)
    n = len(lms)
    rv, tv = np.zeros((n, 3)), np.zeros((n, 3))
    guess = None
    for i in range(n):
        r, t, _ = _solve(obj, lms[i], focal, w, h, guess)
        rv[i], tv[i] = r, t
        guess = (r, t)
    aligned, ref, refinable = None, -1, 0
    if frames is not None and n > 1:
        from lmgs_eval.data.ingest.align import refine

        rf = refine(frames, lms, rv, tv, focal, w, h, obj, RIGID)
        rv, tv, aligned, ref, refinable = rf.rv, rf.tv, rf.used, rf.reference, rf.refinable
    # smooth rotations as small rotations about their mean (no wrap-around at +-pi)
    rots = Rotation.from_rotvec(rv)
    mean = rots.mean()
    rel = (mean.inv() * rots).as_rotvec()
    for run in runs or [slice(0, n)]:
        if sigma > 0 and run.stop - run.start > 2:
            rel[run] = gaussian_filter1d(rel[run], sigma, axis=0, mode="nearest")
            tv[run] = gaussian_filter1d(tv[run], sigma, axis=0, mode="nearest")
    R = (mean * Rotation.from_rotvec(rel)).as_matrix()
    w2c = np.tile(np.eye(4), (n, 1, 1))
    w2c[:, :3, :3], w2c[:, :3, 3] = R, tv
    c2w = np.linalg.inv(w2c) @ GL_TO_CV
    # head pose in the frame of a camera facing it: R_head = flip @ R_cv (flip: OpenCV -> OpenGL axes)
    flip = GL_TO_CV[:3, :3]
    euler = np.stack([euler_pyr(flip @ R[i]) for i in range(n)])
    trans = (flip @ tv.T).T
    err = np.array([_reproj(obj, lms[i], w2c[i], focal, w, h) for i in range(n)])
    return PoseFit(obj, float(focal), w2c, c2w, euler, trans, err, aligned, ref, refinable)


def project(pts: np.ndarray, w2c: np.ndarray, f: float, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """World points ``[..., 3]`` to pixels ``[..., 2]`` and camera depth ``[...]`` (OpenCV camera)."""
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[..., 2]
    return np.stack([f * pc[..., 0] / z + w / 2, f * pc[..., 1] / z + h / 2], -1), z


def _reproj(obj, img, w2c, f, w, h) -> float:
    p, _ = project(obj[RIGID], w2c, f, w, h)
    return float(np.linalg.norm(p - img[RIGID], axis=1).mean())


def lift_landmarks(fit: PoseFit, lms: np.ndarray, w: int, h: int) -> np.ndarray:
    """World 3D landmarks ``[N, 68, 3]``: each 2D landmark on its camera ray, at the depth of the
    posed template point. They reproject exactly onto the tracked 2D landmarks (so they carry
    the mouth's motion) and keep the template's depth relief."""
    out = np.zeros((len(lms), 68, 3))
    for i in range(len(lms)):
        _, z = project(fit.template, fit.w2c[i], fit.focal, w, h)
        cam = np.stack([(lms[i, :, 0] - w / 2) / fit.focal * z, (lms[i, :, 1] - h / 2) / fit.focal * z, z], 1)
        c2w_cv = np.linalg.inv(fit.w2c[i])
        out[i] = cam @ c2w_cv[:3, :3].T + c2w_cv[:3, 3]
    return out.astype(np.float32)
