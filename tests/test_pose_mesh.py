"""Head poses from the dense mesh (:func:`lmgs_eval.data.ingest.pose.mesh_poses`, ``fit_poses(...,
mesh=...)``) against synthetic views of a face whose poses are known."""

from __future__ import annotations

import numpy as np

from lmgs_eval.data.ingest import focal as focal_mod, pose as pose_mod
from lmgs_eval.data.ingest.lips import MESH_TO_68

W = 512
F = 2.5 * W


def _clip(yaw_deg: float, n: int = 60, seed: int = 0, noise_px: float = 0.3):
    """A face (the canonical one, each point moved by a few millimetres) 1 m from a camera of 2.5 frame
    widths, turning up to ``yaw_deg`` either way, nodding and rolling a third of that: ``(mesh [N, 478, 3]
    in pixels, its 68 iBUG points [N, 68, 2] with their own noise, the true rotations)``."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    face = focal_mod.canonical_face() + rng.normal(0, 0.003, (468, 3))
    face = np.concatenate([face, np.repeat(face[[468 - 1]], 10, 0)])  # iris points: not used by the fit
    t = np.linspace(0, 2 * np.pi, n)
    eul = np.stack([yaw_deg * np.sin(t), yaw_deg / 3 * np.sin(2 * t), yaw_deg / 3 * np.cos(t)], 1)
    rots = Rotation.from_euler("yxz", eul, degrees=True)
    pc = np.einsum("nij,pj->npi", rots.as_matrix(), face) + [0.02, -0.01, 1.0]
    uv = F * pc[..., :2] / pc[..., 2:3] + W / 2
    mesh = np.concatenate([uv + rng.normal(0, noise_px, uv.shape), np.zeros_like(uv[..., :1])], -1)
    lms = uv[:, list(MESH_TO_68)] + rng.normal(0, 2 * noise_px, (n, 68, 2))
    return mesh, lms, rots


def _rotation_error_deg(w2c_rot, truth) -> float:
    """Mean angle between the fitted and the true head rotations, one constant rotation removed
    (the fit's world axes are its own)."""
    from scipy.spatial.transform import Rotation

    rel = truth.inv() * Rotation.from_matrix(w2c_rot)
    return float(np.degrees((rel.mean().inv() * rel).magnitude()).mean())


def test_mesh_poses_follow_a_turning_head():
    """Turning +-25 deg: the subject's shape fitted to the mesh gives each frame's rotation within a
    fraction of a degree; a frame without a mesh has no pose."""
    from scipy.spatial.transform import Rotation

    mesh, _, truth = _clip(25.0)
    mesh[7] = np.nan
    mp = pose_mod.mesh_poses(mesh, W, W, F)
    ok = np.isfinite(mp.rv[:, 0])
    assert not ok[7] and ok.sum() == len(mesh) - 1
    err = _rotation_error_deg(Rotation.from_rotvec(mp.rv[ok]).as_matrix(), truth[ok])
    assert err < 0.3, err
    assert np.nanmean(mp.reproj_px) < 0.6  # the points' own noise: 0.3 px per coordinate


def test_fit_poses_from_the_mesh_beat_the_template_on_a_turning_head():
    """The 68-point template's generic relief misreads a turn; the mesh poses, expressed in the
    template's world, are within a degree of the truth, and the template they place projects onto
    the detected landmarks (the similarity between the two worlds is fitted)."""
    mesh, lms, truth = _clip(25.0)
    a = pose_mod.fit_poses(lms, W, W, focal=F, sigma=0)
    b = pose_mod.fit_poses(lms, W, W, focal=F, sigma=0, mesh=mesh)
    assert a.source == "landmarks" and b.source == "mesh"
    err_a, err_b = _rotation_error_deg(a.w2c[:, :3, :3], truth), _rotation_error_deg(b.w2c[:, :3, :3], truth)
    assert err_b < 0.5 and err_b < 0.5 * err_a, (err_a, err_b)
    assert b.reproj_px.mean() < 3.0, b.reproj_px.mean()
    # the world keeps the template's size: the camera stands where the landmark fit puts it, within a few per cent
    assert abs(np.linalg.norm(b.trans, axis=1).mean() / np.linalg.norm(a.trans, axis=1).mean() - 1) < 0.05


def test_gcv_smoother_removes_noise_and_keeps_fast_motion():
    """Whittaker's smoother with its weight by generalised cross-validation: on a still head's
    noisy pose it smooths hard; on a quick shake (a hand-held camera: a 6-frame period, ten times
    the noise) it follows the motion, where a Gaussian of 2 frames would flatten it."""
    from scipy.ndimage import gaussian_filter1d

    rng = np.random.default_rng(0)
    n = 300
    noise = rng.normal(0, 0.1, (n, 3))
    still, lam_still = pose_mod.smooth_gcv(5.0 + noise)
    assert np.sqrt(((still - 5.0) ** 2).mean()) < 0.3 * 0.1
    t = np.arange(n)
    shake = np.stack([np.sin(2 * np.pi * t / 6), np.cos(2 * np.pi * t / 9), np.sin(2 * np.pi * t / 40)], 1)
    followed, lam_shake = pose_mod.smooth_gcv(shake + noise)
    assert np.sqrt(((followed - shake) ** 2).mean(0)).max() < 0.12  # about the noise (0.1): the motion kept
    assert (lam_shake < lam_still).all()
    flattened = gaussian_filter1d(shake + noise, 2.0, axis=0)
    assert np.sqrt(((flattened[:, 0] - shake[:, 0]) ** 2).mean()) > 0.3
    short = np.ones((4, 2))
    assert np.array_equal(pose_mod.smooth_gcv(short)[0], short)


def test_unrefined_frames_carry_their_neighbours_correction():
    """Frames the texture cannot refine keep their own pose's motion and take the refined
    frames' offset, interpolated in time (held at the ends); refined frames stay as refined."""
    from scipy.spatial.transform import Rotation

    from lmgs_eval.data.ingest.align import carry

    rng = np.random.default_rng(0)
    n = 40
    rv = Rotation.from_euler("y", np.linspace(-25, 25, n)[:, None], degrees=True).as_rotvec() + rng.normal(0, 0.01, (n, 3))
    tv = np.column_stack([rng.normal(0, 0.01, n), rng.normal(0, 0.01, n), np.full(n, 1.5)])
    # the truth's correction grows with the frame index: 0 -> 6 deg about x, and a shift in x
    angle = np.linspace(0.0, 6.0, n)
    d = Rotation.from_euler("x", angle[:, None], degrees=True)
    e = np.column_stack([np.linspace(0.0, 0.02, n), np.zeros(n), np.zeros(n)])
    rv_true, tv_true = (d * Rotation.from_rotvec(rv)).as_rotvec(), d.apply(tv) + e
    used = np.zeros(n, bool)
    used[5:30:3] = True  # refined frames in the middle only
    r, t = carry(rv, tv, np.where(used[:, None], rv_true, rv), np.where(used[:, None], tv_true, tv), used)
    assert np.array_equal(r[used], rv_true[used]) and np.array_equal(t[used], tv_true[used])
    inside = ~used & (np.arange(n) > 5) & (np.arange(n) < 29)
    err = np.degrees((Rotation.from_rotvec(r) * Rotation.from_rotvec(rv_true).inv()).magnitude())
    assert err[inside].max() < 1e-6  # a correction linear in time is interpolated exactly
    assert np.abs(t[inside] - tv_true[inside]).max() < 1e-9
    # beyond the last refined frame (29, 4.46 deg) the correction is held, so the error is what it grew since
    assert abs(err[-1] - (6.0 - angle[29])) < 1e-6
    # their own motion stays theirs: frame-to-frame rotation of a carried run equals the input's where the correction is held
    step_in = (Rotation.from_rotvec(rv[31:]) * Rotation.from_rotvec(rv[30:-1]).inv()).magnitude()
    step_out = (Rotation.from_rotvec(r[31:]) * Rotation.from_rotvec(r[30:-1]).inv()).magnitude()
    assert np.allclose(step_in, step_out, atol=1e-9)
    # nothing refined, or all: returned as given
    r0, t0 = carry(rv, tv, rv, tv, np.zeros(n, bool))
    assert np.array_equal(r0, rv) and np.array_equal(t0, tv)


def test_roughness_reads_pose_noise_not_smooth_motion():
    """The gate on the texture refinement: a smooth turn is not rough, white noise of sd s
    (radians, per axis) reads as its second difference's mean norm, sqrt(6) s E|chi_3|."""
    from scipy.spatial.transform import Rotation

    from lmgs_eval.data.ingest.align import roughness

    n = 500
    t = np.arange(n) / 25.0
    turn = Rotation.from_euler("yx", np.column_stack([20 * np.sin(2 * np.pi * 0.3 * t), 8 * np.sin(2 * np.pi * 0.2 * t)]),
                               degrees=True).as_rotvec()
    every = np.ones(n, bool)
    assert roughness(turn, every) < 0.1  # degrees: a +-20 deg turn at 0.3 Hz
    s = np.radians(0.5)
    noisy = (Rotation.from_rotvec(np.random.default_rng(1).normal(0, s, (n, 3))) * Rotation.from_rotvec(turn)).as_rotvec()
    want = np.degrees(np.sqrt(6) * s * 2 * np.sqrt(2 / np.pi))  # E|chi_3| = 2 sqrt(2 / pi)
    assert abs(roughness(noisy, every) - want) < 0.1 * want, (roughness(noisy, every), want)
    # only where three frames in a row are selected: the noisy half alone
    half = np.where(np.arange(n)[:, None] < n // 2, noisy, turn)
    first = np.arange(n) < n // 2
    assert abs(roughness(half, first) - roughness(noisy[: n // 2], np.ones(n // 2, bool))) < 0.05 * want
    assert roughness(half, ~first) < 0.1
    assert np.isnan(roughness(turn, np.arange(n) % 2 == 0))  # no three in a row


def test_follows_reads_how_far_the_refined_poses_turn():
    """The second gate on the texture refinement: the refined poses' turn against the input's. A copy that
    turns half as far reads 0.5 however noisy the input is (both are smoothed before the regression); the
    input itself reads 1; an input that only jitters about a still pose turns too little to tell (NaN)."""
    from scipy.spatial.transform import Rotation

    from lmgs_eval.data.ingest.align import MIN_SPAN_DEG, follows

    n = 250
    t = np.arange(n) / 25.0
    turn = np.column_stack([4 * np.sin(2 * np.pi * 0.2 * t), 6 * np.sin(2 * np.pi * 0.13 * t + 1), np.zeros(n)])
    smooth = Rotation.from_euler("xyz", turn, degrees=True)
    half = Rotation.from_euler("xyz", turn / 2, degrees=True).as_rotvec()
    noise = Rotation.from_rotvec(np.random.default_rng(2).normal(0, np.radians(0.5), (n, 3)))
    noisy = (noise * smooth).as_rotvec()
    every = np.ones(n, bool)
    assert abs(follows(noisy, noisy, every) - 1) < 1e-9
    assert abs(follows(noisy, half, every) - 0.5) < 0.05, follows(noisy, half, every)
    assert abs(follows(smooth.as_rotvec(), half, every) - 0.5) < 0.01
    # over a subset of the frames (the refined ones)
    some = np.arange(n) % 3 != 0
    assert abs(follows(noisy, half, some) - 0.5) < 0.05
    # a still head's jitter: its smoothed turn is below MIN_SPAN_DEG
    still = noise.as_rotvec()
    assert np.isnan(follows(still, 0.5 * still, every))
    assert np.degrees(np.linalg.norm(still, axis=1)).mean() > MIN_SPAN_DEG / 2  # jitter of a visible size all the same
    assert np.isnan(follows(noisy, half, np.arange(n) < 2))
