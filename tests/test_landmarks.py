"""Audio-to-landmark stand-in and 2D -> 3D lifting."""

import numpy as np
import pytest
import torch

from lmgs.errors import InputError
from lmgs.landmarks import MEAN_FACE_DEPTH, fit_landmark_predictor, lift_2d_landmarks
from lmgs.types import Camera


def _synthetic(n=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    raw = torch.randn(n + 16, 4, generator=g)
    k = torch.ones(1, 1, 5) / 5
    smooth = torch.stack([torch.conv1d(raw[:, c].view(1, 1, -1), k, padding=2).view(-1) for c in range(4)], 1)
    feats = torch.stack([smooth[i : i + 16] for i in range(n)])  # [n, 16, 4] windows
    jaw = torch.tanh(2 * feats[:, 6:10, 0].mean(1))  # opening = known function of channel 0
    base = torch.randn(68, 3, generator=g)
    direction = torch.zeros(68, 3)
    direction[5:12, 1] = -0.5  # chin and jaw drop
    direction[56:59, 1] = -0.3  # lower lip
    direction[65:68, 1] = -0.2
    lms = base + jaw[:, None, None] * direction + 0.003 * torch.randn(n, 68, 3, generator=g)
    return feats, lms, jaw


def test_predictor_learns_a_synthetic_jaw_mapping():
    feats, lms, jaw = _synthetic()
    tr = 240
    seen = []
    model = fit_landmark_predictor(feats[:tr], lms[:tr], steps=200, seed=0, progress=lambda s, l: seen.append(s))
    pred = model.predict(feats)
    assert pred.shape == (300, 68, 3)
    held = (pred[tr:] - lms[tr:]).norm(dim=-1).mean()
    mean_only = (lms[:tr].mean(0) - lms[tr:]).norm(dim=-1).mean()
    assert held < 0.4 * mean_only
    # the chin's vertical position follows the jaw signal on held-out frames
    r = np.corrcoef(pred[tr:, 8, 1].numpy(), -jaw[tr:].numpy())[0, 1]
    assert r > 0.9
    assert seen[0] == 0 and seen[-1] == 199
    assert "stand-in for GeneFace" in model.describe()["note"]


def test_predictor_is_deterministic_with_seed():
    feats, lms, _ = _synthetic(60)
    a = fit_landmark_predictor(feats, lms, steps=10, seed=3).predict(feats)
    b = fit_landmark_predictor(feats, lms, steps=10, seed=3).predict(feats)
    c = fit_landmark_predictor(feats, lms, steps=10, seed=4).predict(feats)
    assert torch.equal(a, b) and not torch.equal(a, c)
    with pytest.raises(InputError):
        fit_landmark_predictor(feats, lms[:10], steps=1)


def _camera_c2w(tz=4.0, yaw=0.2):
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = R @ np.array([0.1, -0.05, tz])  # camera on +z looking at the origin (OpenGL: looks down -z)
    return M


def test_lift_inverts_projection_with_the_true_depths():
    rng = np.random.default_rng(0)
    c2w = np.stack([_camera_c2w(4.0, 0.1), _camera_c2w(3.5, -0.2)])
    focal, W, H = 1200.0, 512, 512
    # Ground truth: a face around the origin, moved along each camera's axis so that its mean
    # depth is the origin's (the lift places the prior's mean there); the lift given the true
    # depth offsets must then give back these very points.
    pts = rng.normal(scale=0.3, size=(2, 68, 3))
    lms2d, delta = [], []
    for n in range(2):
        cam = Camera.from_nerf_c2w(c2w[n], focal, W, H)
        w2c = cam.world_to_camera.double().numpy()
        z = (pts[n] @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]
        pts[n] -= (z - w2c[2, 3]).mean() * w2c[2, :3]  # camera z axis in world coordinates
        z = (pts[n] @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]
        lms2d.append(cam.project(torch.from_numpy(pts[n]).float()).double().numpy())
        delta.append(z - w2c[2, 3])
    delta = np.stack(delta)
    assert np.abs(delta.mean(1)).max() < 1e-6 and delta.std() > 0.1
    lifted = lift_2d_landmarks(np.stack(lms2d), c2w, focal, W / 2, H / 2, delta, face_center=(0, 0, 0))
    assert lifted.shape == (2, 68, 3)
    np.testing.assert_allclose(lifted.numpy(), pts, atol=2e-4)
    # a prior off by a constant per frame is removed by the per-frame centring: the same points
    again = lift_2d_landmarks(np.stack(lms2d), c2w, focal, W / 2, H / 2, delta + np.array([[0.5], [-0.2]]))
    np.testing.assert_allclose(again.numpy(), pts, atol=2e-4)
    for n in range(2):
        cam = Camera.from_nerf_c2w(c2w[n], focal, W, H)
        np.testing.assert_allclose(cam.project(lifted[n]).numpy(), lms2d[n], atol=1e-2)  # exact reprojection


def test_lift_with_mean_face_prior_is_plausible():
    c2w = _camera_c2w(4.0, 0.0)
    focal = 1200.0
    # a frontal 2D face 200 px wide centred in the image
    u = np.linspace(-100, 100, 17)
    lms2d = np.zeros((1, 68, 2))
    lms2d[0, :, 0] = 256 + np.resize(u, 68)
    lms2d[0, :, 1] = 256 + np.linspace(-80, 100, 68)
    lms2d[0, 0], lms2d[0, 16] = (156, 200), (356, 200)
    out = lift_2d_landmarks(lms2d, c2w, focal, 256, 256)
    assert np.isfinite(out.numpy()).all()
    cam = Camera.from_nerf_c2w(c2w, focal, 512, 512)
    np.testing.assert_allclose(cam.project(out[0]).numpy(), lms2d[0], atol=1e-2)
    # nose tip (30) nearer the camera than the jaw ends (0, 16), by about 0.55 face widths
    w2c = cam.world_to_camera.double().numpy()
    z = (out[0].double().numpy() @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]
    face_width = 200 * w2c[2, 3] / focal
    assert z[0] - z[30] == pytest.approx(MEAN_FACE_DEPTH[0] * face_width, rel=1e-3)
    with pytest.raises(InputError):
        lift_2d_landmarks(np.zeros((2, 68, 3)), c2w, focal, 256, 256)


def test_cross_fit_predicts_each_block_without_its_targets():
    from lmgs.landmarks import cross_fit_landmarks

    feats, lms, _ = _synthetic(60)
    out = cross_fit_landmarks(feats, lms, folds=3, steps=10, seed=0)
    assert out.shape == (60, 68, 3)
    moved = lms.clone()
    moved[20:40] += 5.0  # block 1's targets only
    out2 = cross_fit_landmarks(feats, moved, folds=3, steps=10, seed=0)
    assert torch.equal(out[20:40], out2[20:40])  # predicted by a fit that never saw them
    assert not torch.allclose(out[:20], out2[:20]) and not torch.allclose(out[40:], out2[40:])  # the others did
    with pytest.raises(InputError, match="at least 2 folds"):
        cross_fit_landmarks(feats, lms, folds=1)
    with pytest.raises(InputError, match="too few"):
        cross_fit_landmarks(feats[:20], lms[:20], folds=5)
    # one rule for how many folds a clip takes (train.fit caps landmark_folds with it): 8 frames a block
    from lmgs.landmarks import max_folds

    assert max_folds(24) == 3 and max_folds(23) == 2 and max_folds(12) == 1
    assert cross_fit_landmarks(feats[:24], lms[:24], folds=3, steps=2).shape == (24, 68, 3)
    with pytest.raises(InputError, match="too few"):
        cross_fit_landmarks(feats[:23], lms[:23], folds=3, steps=2)


def test_cross_fit_error_is_the_held_out_error_not_the_in_sample_one():
    """In-sample predictions of an over-parameterised predictor are better than it is on new
    audio; the out-of-fold ones are as good as on new audio (the point of cross-fitting)."""
    from lmgs.landmarks import cross_fit_landmarks

    g = torch.Generator().manual_seed(1)
    feats, lms, _ = _synthetic(300)
    # per-frame jitter along one landmark pattern, which the audio cannot explain
    pattern = torch.randn(68, 3, generator=g)
    lms = lms + 0.2 * torch.randn(len(lms), 1, 1, generator=g) * pattern
    tr = 240

    def err(p, y):
        return float((p - y).norm(dim=-1).mean())

    full = fit_landmark_predictor(feats[:tr], lms[:tr], steps=300, seed=0)
    in_sample = err(full.predict(feats[:tr]), lms[:tr])
    held_out = err(full.predict(feats[tr:]), lms[tr:])
    oof = err(cross_fit_landmarks(feats[:tr], lms[:tr], folds=4, steps=300, seed=0), lms[:tr])
    assert in_sample < 0.2 * held_out  # the predictor memorises the jitter of its own frames (0.006 / 0.294)
    assert 0.7 * held_out < oof < 1.5 * held_out  # out of fold: new-audio quality (0.361, fitted on 3/4 of the frames)
