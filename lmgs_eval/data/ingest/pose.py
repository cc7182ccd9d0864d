"""Head pose and camera: the subject's shape fitted to the dense face mesh, one focal length per clip.

The fit, in four steps:

1. **Template, once per subject.** The 68-point template's ``x, y`` are the subject's own median
   landmark layout over the frames nearest frontal (:data:`FRONTAL_SHARE` of them, by the nose's
   place between the jaw's ends: :func:`yaw_asymmetry`; each aligned to the most frontal one by a
   similarity transform, then the per-point median), scaled so the jaw (landmarks 0-16) spans
   :data:`JAW_WIDTH` metres; its depth ``z`` is the generic relief
   :data:`lmgs.landmarks.MEAN_FACE_DEPTH` (nose tip in front, jaw angle behind) times the same
   width times :data:`lmgs_eval.data.geometry.RELIEF`. The template defines the world (its axes
   and size) and lifts the 2D landmarks to ``lms3d``. The median over every frame would be a
   turned face's layout wherever the head looks to one side for most of the clip, and the fit
   would take that turn for frontal: on a bundled head that turns from 0 to 30 deg and back
   (astronaut, 256 px, 3 s) it did (yaw -13..+9 deg, 5.5 deg mean rotation error); from the
   frontal quarter 2.8 deg.
2. **Focal length**: given (``--focal``, or :mod:`focal`'s joint fit on the dense mesh). Of the
   68 points and a generic template it cannot be had: a search over focal lengths found the
   reprojection error falling steadily to the longest lens tried (a flatter projection hides
   the template's depth error) on the bundled subjects and on 4 of 5 real clips.
3. **Pose, per frame**, with that focal. From the dense mesh (:func:`mesh_poses`): the
   subject's own shape (93 skull vertices of MediaPipe's canonical face, fitted with the poses
   of 60 frames) posed on each frame's tracked mesh, then carried into the template's world by
   one similarity fitted over the clip (:func:`_into_template_world`). The 68-point template on
   dlib's points (``mesh=None``, ``--pose-from landmarks``) reads a turn short: dlib's nose and
   mouth points lag the surface by a third on a turning head, and the jaw's are silhouette
   points. Given the frames, the poses are refined by corners of the upper head tracked from a
   reference frame (:mod:`align`: every frame or none).
4. **Smoothing** over time, within each run of frames: a Gaussian of ``sigma`` frames (the
   ingest's default is none), or Whittaker's smoother with its weight by generalised
   cross-validation (:func:`smooth_gcv`; ``sigma=None``). A Gaussian of 2 frames moved a
   hand-held phone clip's head 3.4 px on average and up to 14 px from its tracked mesh (512 px),
   where the camera's shake is motion, not noise, and cost a method trained on it 3 dB.

The head is the world (fixed at the origin, OpenGL axes: x right, y up, z towards the
camera at rest); the camera moves: ``transform_matrix = c2w`` (ER-NeRF's convention).

Against a 3DMM tracker (ER-NeRF's BFM fit): no expression basis (the mesh's skull vertices
are posed, the mouth and jaw left out; a frown still moves the brows a little), the subject's
shape is fitted but held near a generic face, the images enter only through the tracked
corners of :mod:`align`, whose depth is a generic ellipsoid's, and not at all when the head
turns far. It needs no model download; once the mesh is tracked, the shape, 500 frames' poses and the
similarity take about 1.4 s on one core (the 68-point fit alone 0.4 s), the texture tracking
about 250 frames a second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lmgs_eval.data.geometry import RELIEF

if TYPE_CHECKING:
    from lmgs_eval.data.ingest.align import Refined

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
MESH_SHAPE_FRAMES = 60  # frames the subject's shape is fitted on, with their poses (dense-mesh poses)
SIMILARITY_FRAMES = 100  # frames the template's place in the shape's world is fitted on

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
        texture: the refinement by tracked texture (:class:`align.Refined`: which frames it
            refined, from which reference, how many could be and how many carry the correction),
            or None without images.
    """

    template: np.ndarray
    focal: float
    w2c: np.ndarray
    c2w: np.ndarray
    euler: np.ndarray
    trans: np.ndarray
    reproj_px: np.ndarray
    texture: Refined | None = None
    source: str = "landmarks"
    mesh_reproj_px: np.ndarray | None = None

    @property
    def aligned(self) -> np.ndarray | None:
        """``[N]`` bool, the frames whose pose the images refined, or None without images."""
        return None if self.texture is None else self.texture.used

    @property
    def reference(self) -> int:
        """The frame the others were tracked from (-1 without images)."""
        return -1 if self.texture is None else self.texture.reference


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


@dataclass
class MeshPoses:
    """Per-frame poses of the subject's shape fitted to the dense mesh: ``shape [P, 3]`` (metres,
    OpenCV axes, MediaPipe's canonical face's frame), rotation / translation vectors ``[N, 3]``
    (OpenCV camera; NaN where the frame has no mesh), the mean reprojection error of the points
    ``[N]`` (pixels, NaN without a mesh) and the canonical vertices used."""

    shape: np.ndarray
    rv: np.ndarray
    tv: np.ndarray
    reproj_px: np.ndarray
    vertices: np.ndarray


def mesh_poses(mesh: np.ndarray, w: int, h: int, focal: float, frames: int = MESH_SHAPE_FRAMES) -> MeshPoses:
    """Head poses from the dense mesh ``[N, 478, 2+]`` (output pixels, NaN rows without a face) seen
    with ``focal``: the subject's shape (the skull's vertices of the canonical face, :func:`focal.rigid_points`)
    fitted once with the poses of ``frames`` frames spread over the clip (:func:`focal.fit_shape`),
    then each frame's pose by perspective-n-point on that shape, started from the previous frame's."""
    from lmgs_eval.data.ingest.focal import canonical_face, fit_shape, rigid_points, solve_pnp

    face = canonical_face()
    idx = rigid_points(face)
    n = len(mesh)
    good = np.nonzero(np.isfinite(mesh[:, idx, :2]).all((1, 2)))[0]
    rv, tv, err = np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.full(n, np.nan)
    if len(good) < 3:
        return MeshPoses(face[idx], rv, tv, err, idx)
    pick = good[np.linspace(0, len(good) - 1, min(frames, len(good))).round().astype(int)]
    shape = fit_shape(face[idx], np.ascontiguousarray(mesh[pick][:, idx, :2], np.float64), focal, w, h)[0]
    K = np.array([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1.0]])
    guess = None
    for i in good:
        img = mesh[i, idx, :2]
        rv[i], tv[i] = guess = solve_pnp(shape, img, K, guess)
        err[i] = np.linalg.norm(project_cv(shape, rv[i], tv[i], focal, w, h) - img, axis=1).mean()
    return MeshPoses(shape, rv, tv, err, idx)


def project_cv(pts: np.ndarray, rv: np.ndarray, tv: np.ndarray, f: float, w: int, h: int) -> np.ndarray:
    """Points ``[P, 3]`` posed by rotation vector ``rv`` and translation ``tv`` (OpenCV camera) to pixels ``[P, 2]``."""
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = _rodrigues(rv), tv
    return project(pts, w2c, f, w, h)[0]


def _into_template_world(obj: np.ndarray, lms: np.ndarray, rv_t: np.ndarray, tv_t: np.ndarray, mp: MeshPoses,
                         focal: float, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """The mesh poses ``mp`` expressed in the template's world: the similarity ``p -> s R p + t``
    that takes the template into the shape's world is fitted over the frames (the template's
    rigid points, so placed and seen by the mesh poses, against the detected landmarks), and the
    scene is scaled by ``1 / s`` (the images do not change), so that the world keeps the
    template's axes and size. Frames without a mesh pose keep their landmark pose ``rv_t, tv_t``."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    ok = np.nonzero(np.isfinite(mp.rv[:, 0]))[0]
    Rm, Rt = Rotation.from_rotvec(mp.rv[ok]), Rotation.from_rotvec(rv_t[ok])
    # start: per frame, the mesh camera point is the template's scaled by the depth ratio
    sig = np.median(mp.tv[ok, 2] / tv_t[ok, 2])
    R_s = (Rm.inv() * Rt).mean()
    t_s = np.median(Rm.inv().apply(sig * tv_t[ok] - mp.tv[ok]), axis=0)
    sub = ok[np.linspace(0, len(ok) - 1, min(SIMILARITY_FRAMES, len(ok))).round().astype(int)]
    Msub, tsub, img = Rotation.from_rotvec(mp.rv[sub]).as_matrix(), mp.tv[sub], lms[sub][:, RIGID]
    pts = obj[RIGID]

    def residuals(x):
        p = np.exp(x[6]) * Rotation.from_rotvec(x[:3]).apply(pts) + x[3:6]  # [P, 3] in the shape's world
        cam = np.einsum("kij,pj->kpi", Msub, p) + tsub[:, None]  # [K, P, 3]: every sampled frame's camera
        uv = focal * cam[..., :2] / cam[..., 2:3] + (w / 2, h / 2)
        return (uv - img).ravel()

    x = least_squares(residuals, np.r_[R_s.as_rotvec(), t_s, np.log(sig)], method="lm").x
    R_s, t_s, s = Rotation.from_rotvec(x[:3]), x[3:6], float(np.exp(x[6]))
    rv, tv = rv_t.copy(), tv_t.copy()
    rv[ok] = (Rm * R_s).as_rotvec()
    tv[ok] = (Rm.apply(t_s) + mp.tv[ok]) / s
    return rv, tv


def smooth_gcv(y: np.ndarray, lams: np.ndarray = np.logspace(-2, 7, 37)) -> tuple[np.ndarray, np.ndarray]:
    """Whittaker's smoother with its weight chosen by generalised cross-validation, per column of
    ``y [N, K]``: ``z = argmin |y - z|^2 + lam |D2 z|^2`` (``D2`` the second difference), ``lam`` for
    each column the one of ``lams`` that minimises ``GCV = (RSS / N) / (1 - tr(H) / N)^2`` (``H`` the
    smoother's hat matrix). A series whose steps are mostly noise is smoothed hard; one whose motion
    stands above its noise (a hand-held camera's shake, a quick turn) is followed. Returns ``(z,
    lam per column)``; fewer than five rows are returned as they are."""
    from scipy.linalg import eigvals_banded, solveh_banded

    y = np.asarray(y, np.float64)
    n = len(y)
    if n < 5:
        return y.copy(), np.zeros(y.shape[1])
    # D2' D2 in upper banded form (pentadiagonal): diagonals 0, 1, 2
    d0 = np.full(n, 6.0)
    d0[[0, -1]], d0[[1, -2]] = 1.0, 5.0
    d1 = np.full(n - 1, -4.0)
    d1[[0, -1]] = -2.0
    d2 = np.ones(n - 2)
    ab = np.zeros((3, n))
    ab[0, 2:], ab[1, 1:], ab[2] = d2, d1, d0
    eig = np.clip(eigvals_banded(ab), 0.0, None)
    best = np.full(y.shape[1], np.inf)
    z, lam_of = y.copy(), np.zeros(y.shape[1])
    for lam in lams:
        band = lam * ab
        band[2] += 1.0
        zz = solveh_banded(band, y)
        gcv = ((y - zz) ** 2).sum(0) / n / (1.0 - (1.0 / (1.0 + lam * eig)).sum() / n) ** 2
        better = gcv < best
        best[better], z[:, better], lam_of[better] = gcv[better], zz[:, better], lam
    return z, lam_of


def fit_poses(lms: np.ndarray, w: int, h: int, *, focal: float, sigma: float | None = 2.0,
              frames: list | None = None, runs: list[slice] | None = None, mesh: np.ndarray | None = None) -> PoseFit:
    """Template and smoothed per-frame poses for landmarks ``[N, 68, 2]`` (output pixels) seen with ``focal`` (pixels).

    ``mesh``: the dense mesh ``[N, 478, 2+]`` in the same pixels; with it each frame's pose is the
    subject's fitted shape's (:func:`mesh_poses`), expressed in the template's world, and the
    landmark pose only where the frame has no mesh.
    ``frames``: the frames' image paths; with them each pose is refined by the upper
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
    source, mesh_err = "landmarks", None
    if mesh is not None:
        mp = mesh_poses(mesh, w, h, focal)
        if np.isfinite(mp.rv[:, 0]).sum() >= 3:
            rv, tv = _into_template_world(obj, lms, rv, tv, mp, focal, w, h)
            source, mesh_err = "mesh", mp.reproj_px
    texture = None
    if frames is not None and n > 1:
        from lmgs_eval.data.ingest.align import refine

        texture = refine(frames, lms, rv, tv, focal, w, h, obj, RIGID)
        rv, tv = texture.rv, texture.tv
    # smooth rotations as small rotations about their mean (no wrap-around at +-pi)
    rots = Rotation.from_rotvec(rv)
    mean = rots.mean()
    rel = (mean.inv() * rots).as_rotvec()
    for run in runs or [slice(0, n)]:
        if sigma is None:
            rel[run], tv[run] = smooth_gcv(rel[run])[0], smooth_gcv(tv[run])[0]
        elif sigma > 0 and run.stop - run.start > 2:
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
    return PoseFit(obj, float(focal), w2c, c2w, euler, trans, err, texture, source, mesh_err)


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


def lift_mesh(template: np.ndarray, w2c: np.ndarray, focal: float, mesh: np.ndarray, w: int, h: int) -> np.ndarray:
    """Camera coordinates ``[N, 468, 3]`` (OpenCV axes) of the dense mesh ``[N, 478, 3]`` (output
    pixels) face vertices, for the fitted ``template`` ``[68, 3]`` posed by ``w2c`` ``[N, 4, 4]``: each on
    its camera ray, at the depth the tracker gives it relative to the face (its z, in the same
    pixels as x and y, in metres at the head's depth: times the posed template's median depth over
    the focal length), the whole placed so that the template's brows, nose, eyes and lips (the 68
    points but the jaw, whose depth the template only guesses) lie at their posed depth in the
    median. They reproject exactly onto the tracked mesh, and the face they span meets the
    template's 3D landmarks (:func:`lift_landmarks`). NaN where a frame has no mesh."""
    from lmgs_eval.data.ingest.lips import MESH_TO_68

    m = np.asarray(mesh, np.float64)[:, :468]
    pc = np.einsum("nij,pj->npi", w2c[:, :3, :3], template) + w2c[:, None, :3, 3]  # [N, 68, 3]: the posed template
    zt = pc[..., 2]
    per_px = np.median(zt, axis=1) / focal  # metres per pixel of the tracker's z at the head's depth
    inner = np.asarray(MESH_TO_68)[17:]
    off = np.median(zt[:, 17:] - per_px[:, None] * m[:, inner, 2], axis=1)
    z = off[:, None] + per_px[:, None] * m[..., 2]
    return np.stack([(m[..., 0] - w / 2) / focal * z, (m[..., 1] - h / 2) / focal * z, z], -1)
