"""The clip's focal length from the dense face mesh: a joint fit with a metric face as the prior.

A face that moves in front of a camera shows the focal length only through perspective: the
near parts of the head (nose, brows) are magnified more than the far ones (cheeks, temples), and
by how much depends on the distance in head sizes, i.e. on the focal length for the head's size in
pixels. Two things blur that: the subject's own shape is not known (a flatter face at a short
distance projects like a deeper one further away), and the effect is small (a 15 cm deep head at
one metre: a few pixels across a 200 px face).

The fit: for each focal length ``f`` on a grid (in frame widths, :data:`GRID`), the subject's
shape (the canonical face's :data:`POINTS` vertices, free to move) and every sampled frame's pose
are fitted together to the tracked mesh points by least squares (:func:`scipy.optimize.least_squares`
with the problem's sparsity), the shape held near MediaPipe's canonical face (metric: centimetres;
an adult face) with a spread of :data:`SHAPE_MM` per coordinate. The profile of that cost over
``f`` is the evidence; its minimum (refined by a parabola in ``log f``) is the estimate, and the
interval where the profile rises by less than one (the chi-square in units of the residual
variance, divided by the number of coordinates in one frame: frames, not points, are taken as
the independent observations, since a landmark's error repeats from frame to frame) is its
stated uncertainty.
Without the prior any focal fits as well as any other (on a bundled clip the free-shape residual
changes by 4 % between one and six frame widths); with it the profile has an inner minimum on
real faces, but a shallow one: across one to ten frame widths the evidence of a 20 s clip
rises by about one unit on the clips measured (``design.md``), so a talking head's own motion
seldom decides the focal length. The estimate therefore also carries a prior on the focal
length (:data:`PRIOR_WIDTHS`, :data:`PRIOR_LOG_SD`), and the record says how far the clip moved
it: ``evidence`` (the profile's rise over the grid) beside the interval. A head that is not a
human face (a generated one) pulls the evidence by its shape.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lmgs_eval.errors import UserError

CANONICAL = "canonical_face_model.obj"  # in the shipped models (:mod:`vendored`)
GRID = (0.8, 1.0, 1.25, 1.6, 2.0, 2.5, 3.2, 4.0, 5.0, 6.4, 8.0, 10.0)  # frame widths
# The prior on the focal length itself: log-normal about the field's processed subjects (about 2.5
# frame widths at 512 px, a camera about a metre away from a head framed the same way), one
# standard deviation a factor 1.65 either side. It decides where the clip's own evidence is flat.
PRIOR_WIDTHS, PRIOR_LOG_SD = 2.5, 0.5
SHAPE_MM = 5.0  # prior spread of the subject's shape about the canonical face, per coordinate
FRAMES = 30  # frames sampled over the clip
# Vertices of the canonical face that move with the skull (forehead, brows' base, eyes' corners,
# nose, cheekbones, temples): every third of those above the upper lip and off the jaw line.
_STRIDE = 3


def canonical_face(path: Path | None = None) -> np.ndarray:
    """MediaPipe's canonical face ``[468, 3]`` in metres, OpenCV axes (x right, y down, z away from
    a camera it faces); default the shipped file; a missing or altered file is a :class:`UserError` naming it."""
    from lmgs_eval.data.ingest import vendored

    path = vendored.model(CANONICAL, path)
    v = [line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")]
    return np.asarray(v, np.float64) / 100.0 * np.array([1.0, -1.0, -1.0])


def canonical_triangles(path: Path | None = None) -> np.ndarray:
    """The canonical face's triangles ``[898, 3]`` (0-based indices of its 468 vertices, as the
    tracked mesh numbers them): one surface from the hairline to the chin, the eyes and the mouth
    closed over (an open mouth stretches its triangles across the gap)."""
    from lmgs_eval.data.ingest import vendored

    path = vendored.model(CANONICAL, path)
    f = [[int(t.split("/")[0]) - 1 for t in line.split()[1:4]] for line in path.read_text().splitlines() if line.startswith("f ")]
    return np.asarray(f, np.int64)


def rigid_points(face: np.ndarray) -> np.ndarray:
    """Indices of the canonical vertices the fit uses: above the upper lip (y < 1.5 cm below the
    model's origin, OpenCV axes), every :data:`_STRIDE`-th."""
    return np.nonzero(face[:, 1] < 0.015)[0][::_STRIDE]


@dataclass
class FocalFit:
    """The estimate (pixels), its interval ``(lo, hi)`` in pixels, the profile ``[(f, cost)]`` (the
    clip's evidence plus the prior, per-frame units, 0 at the clip's best), and ``evidence``: how
    much the clip's own profile rises over the grid (below about 1: the prior decides)."""

    focal: float
    lo: float
    hi: float
    curve: list[tuple[float, float]]
    frames: int
    evidence: float

    def to_json(self, width: int) -> dict:
        return {"method": "joint fit of shape and poses on the dense mesh, canonical face as prior",
                "focal_widths": round(self.focal / width, 3),
                "interval_widths": [round(self.lo / width, 3), round(self.hi / width, 3)],
                "frames": self.frames, "evidence": round(self.evidence, 3),
                "prior_widths": PRIOR_WIDTHS, "prior_log_sd": PRIOR_LOG_SD, "profile": [[round(f / width, 3), round(c, 2)] for f, c in self.curve]}


def solve_pnp(shape: np.ndarray, img: np.ndarray, K: np.ndarray, guess: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``(rotation vector [3], translation [3])`` (OpenCV camera) that projects ``shape [P, 3]``
    onto ``img [P, 2]``: Levenberg-Marquardt from ``guess`` (rotation, translation), or from EPnP."""
    import cv2

    img = np.ascontiguousarray(img, np.float64)
    if guess is None:
        _, r, t = cv2.solvePnP(shape, img, K, None, flags=cv2.SOLVEPNP_EPNP)
    else:
        r, t = (np.asarray(g, np.float64).reshape(3, 1).copy() for g in guess)
    _, r, t = cv2.solvePnP(shape, img, K, None, r, t, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    return r.ravel(), t.ravel()


def _poses(shape: np.ndarray, obs: np.ndarray, f: float, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    rv, tv = np.zeros((len(obs), 3)), np.zeros((len(obs), 3))
    for k, img in enumerate(obs):
        rv[k], tv[k] = solve_pnp(shape, img, K)
    return rv, tv


def _rotate(rv: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``R(rv_k) @ pts_k`` for rotation vectors ``[F, 3]`` and points ``[F, P, 3]`` (Rodrigues)."""
    th = np.linalg.norm(rv, axis=1, keepdims=True)[:, None]
    k = np.where(th > 1e-12, rv[:, None] / np.maximum(th, 1e-12), 0.0)
    c, s = np.cos(th), np.sin(th)
    return pts * c + np.cross(k, pts) * s + k * (k * pts).sum(-1, keepdims=True) * (1 - c)


def _profile_point(prior: np.ndarray, obs: np.ndarray, f: float, w: int, h: int) -> tuple[float, float]:
    """``(sum of squared pixel residuals, sum of squared prior residuals in prior units)`` at the
    best shape and poses for focal ``f``."""
    return fit_shape(prior, obs, f, w, h)[3:]


def fit_shape(prior: np.ndarray, obs: np.ndarray, f: float, w: int, h: int):
    """The subject's shape and the frames' poses fitted jointly to tracked points ``obs [F, P, 2]``
    (pixels) seen with focal ``f``, the shape held near ``prior [P, 3]`` (metres, OpenCV axes) with
    :data:`SHAPE_MM` per coordinate: ``(shape [P, 3], rotation vectors [F, 3], translations [F, 3],
    sum of squared pixel residuals, sum of squared prior residuals in prior units)``."""
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    n_f, n_p = obs.shape[:2]
    rv, tv = _poses(prior, obs, f, w, h)
    x0 = np.concatenate([prior.ravel(), rv.ravel(), tv.ravel()])
    o_rot, o_t = 3 * n_p, 3 * n_p + 3 * n_f  # shape first, then rotations, then translations
    scale = 1e-3 * SHAPE_MM

    def residuals(x):
        shape = x[: o_rot].reshape(n_p, 3)
        r, t = x[o_rot:o_t].reshape(n_f, 3), x[o_t:].reshape(n_f, 3)
        pc = _rotate(r, np.broadcast_to(shape, (n_f, n_p, 3))) + t[:, None]
        uv = f * pc[..., :2] / pc[..., 2:3] + (w / 2, h / 2)
        return np.concatenate([(uv - obs).ravel(), ((shape - prior) / scale).ravel()])

    # sparsity: each pixel residual depends on its point's 3 coordinates and its frame's 6 pose values
    fr, pt = np.meshgrid(np.arange(n_f), np.arange(n_p), indexing="ij")
    row = (2 * (fr * n_p + pt))[..., None, None] + np.arange(2)[:, None]  # [F, P, 2, 1]
    cols = np.concatenate([np.broadcast_to((3 * pt)[..., None] + np.arange(3), (n_f, n_p, 3)),
                           np.broadcast_to((o_rot + 3 * fr)[..., None] + np.arange(3), (n_f, n_p, 3)),
                           np.broadcast_to((o_t + 3 * fr)[..., None] + np.arange(3), (n_f, n_p, 3))], -1)[:, :, None, :]
    rr, cc = np.broadcast_arrays(row, cols)
    prior_rows = 2 * n_f * n_p + np.arange(3 * n_p)
    r_all = np.concatenate([rr.ravel(), prior_rows])
    c_all = np.concatenate([cc.ravel(), np.arange(3 * n_p)])
    sparsity = coo_matrix((np.ones(len(r_all), np.int8), (r_all, c_all)), shape=(2 * n_f * n_p + 3 * n_p, len(x0)))
    fit = least_squares(residuals, x0, jac_sparsity=sparsity, method="trf", x_scale="jac", max_nfev=40)
    res, x = fit.fun, fit.x
    return (x[:o_rot].reshape(n_p, 3), x[o_rot:o_t].reshape(n_f, 3), x[o_t:].reshape(n_f, 3),
            float((res[: 2 * n_f * n_p] ** 2).sum()), float((res[2 * n_f * n_p:] ** 2).sum()))


def fit_focal(mesh: np.ndarray, w: int, h: int, frames: int = FRAMES, progress=None, mapper=None) -> FocalFit:
    """The focal length (pixels) of a clip from its tracked mesh ``[N, 478, 2+]`` (frame pixels,
    NaN where no face), with its interval and profile. ``mapper``: a ``map`` that may spread the
    grid's fits (each on its own) over processes, ``Executor.map``; default the built-in one."""
    face = canonical_face()
    idx = rigid_points(face)
    good = np.nonzero(np.isfinite(mesh[:, 0, 0]))[0]
    if len(good) < 3:
        raise UserError(f"the face mesh was found on {len(good)} frames: too few to estimate the focal length (pass --focal)")
    pick = good[np.linspace(0, len(good) - 1, min(frames, len(good))).round().astype(int)]
    obs = np.ascontiguousarray(mesh[pick][:, idx, :2], np.float64)
    prior = face[idx]
    pix, pri = [], []
    n = len(GRID)
    for a, b in (mapper or map)(_profile_point, [prior] * n, [obs] * n, [fw * w for fw in GRID], [w] * n, [h] * n):
        pix.append(a)
        pri.append(b)
        if progress is not None:
            progress(1)
    pix, pri = np.asarray(pix), np.asarray(pri)
    sigma2 = pix.min() / obs[..., 0].size  # per-coordinate residual variance at the best focal
    cost = pix / sigma2 + pri
    per_frame = cost / obs[0].size  # frames as the independent observations: one frame's coordinates count once
    per_frame = per_frame - per_frame.min()
    evidence = float(per_frame.max())
    per_frame = per_frame + ((np.log(np.asarray(GRID)) - np.log(PRIOR_WIDTHS)) / PRIOR_LOG_SD) ** 2
    logf = np.log(np.asarray(GRID) * w)
    k = int(np.argmin(per_frame))
    best = float(np.exp(logf[k]))
    if 0 < k < len(GRID) - 1:  # parabola through the minimum and its neighbours
        a, b, _ = np.polyfit(logf[k - 1 : k + 2], per_frame[k - 1 : k + 2], 2)
        if a > 0:
            best = float(np.exp(np.clip(-b / (2 * a), logf[k - 1], logf[k + 1])))
    # interval: where the per-frame profile stays within one unit of its minimum (linear in log f between grid points)
    fine = np.linspace(logf[0], logf[-1], 400)
    prof = np.interp(fine, logf, per_frame)
    inside = fine[prof <= per_frame.min() + 1.0]
    lo, hi = float(np.exp(inside.min())), float(np.exp(inside.max()))
    curve = [(float(np.exp(lf)), float(c)) for lf, c in zip(logf, per_frame)]
    return FocalFit(best, min(lo, best), max(hi, best), curve, len(pick), evidence)
