"""LMD on hand-made landmark shifts (exact pixels), dlib on a real photo, missing faces counted."""

from __future__ import annotations

import numpy as np
import pytest
from skimage import data

from lmgs_eval.errors import UserError
from lmgs_eval.metrics.landmarks import GivenBackend, LMD, dlib_model_path, lmd_per_frame, lmd_result


def _face_lms(seed=0):
    rng = np.random.default_rng(seed)
    lms = rng.uniform(100, 300, (68, 2))
    lms[36], lms[45] = (150.0, 180.0), (250.0, 180.0)  # inter-ocular distance exactly 100 px
    return lms


def test_pure_translation_of_mouth_is_zero():
    g = _face_lms()[None]
    p = g.copy()
    p[:, 48:68] += (7.0, -3.0)
    assert lmd_per_frame(p, g)[0] == pytest.approx(0.0, abs=1e-12)


def test_one_point_moved_by_2px_hand_computed():
    # moving one of the 20 mouth points by 2 px along x moves the mouth mean by 0.1 px:
    # after centring that point is off by 1.9 px and the 19 others by 0.1 px,
    # so LMD = (1.9 + 19 * 0.1) / 20 = 0.19 px (not 2/20: the definition centres each set).
    g = _face_lms()[None]
    p = g.copy()
    p[0, 55, 0] += 2.0
    assert lmd_per_frame(p, g)[0] == pytest.approx(0.19, abs=1e-12)
    assert lmd_per_frame(p, g, normalise=True)[0] == pytest.approx(0.0019, abs=1e-12)


def test_points_outside_mouth_do_not_count():
    g = _face_lms()[None]
    p = g.copy()
    p[0, :48] += 50.0
    assert lmd_per_frame(p, g)[0] == pytest.approx(0.0, abs=1e-12)


def test_missing_face_counted_and_flagged():
    g = np.stack([_face_lms(i) for i in range(3)])
    p = g.copy()
    p[:, 50, 1] += 2.0
    p[1] = np.nan
    r = lmd_result(p, g)
    assert r.n_original == 3 and r.n_effective == 2
    assert any("no_face: 1 of 3" in f for f in r.flags)
    assert np.isnan(r.per_item[1]) and r.value == pytest.approx(0.19, abs=1e-12)


def test_given_backend_checks_lengths():
    with pytest.raises(UserError, match="3 frames of landmarks for 2"):
        LMD(GivenBackend(np.zeros((3, 68, 2)))).update(np.zeros((2, 8, 8, 3), np.float32), np.zeros((2, 8, 8, 3), np.float32))


@pytest.mark.skipif(dlib_model_path() is None, reason="face-recognition-models not installed")
def test_dlib_on_astronaut_nose_tip_and_no_face():
    from lmgs_eval.metrics.landmarks import DlibBackend

    img = data.astronaut().astype(np.float32) / 255.0
    blank = np.full_like(img, 0.5)
    lms = DlibBackend().landmarks(np.stack([img, blank, img]))
    assert np.linalg.norm(lms[0, 30] - (225, 127)) <= 3.0  # docs/field.md, LMD: about (225, 127)
    assert np.isnan(lms[1]).all()
    np.testing.assert_allclose(lms[2], lms[0], atol=2.0)
    r = lmd_result(lms, lms)
    assert r.n_effective == 2 and r.value == pytest.approx(0.0, abs=1e-12)


class _CountingBackend:
    """Landmarks from the frame's mean brightness (distinct per clip), counting calls."""

    name = "counting"
    version = "counting-1"

    def __init__(self):
        self.calls = 0

    def landmarks(self, frames):
        self.calls += 1
        return np.repeat(frames.mean(axis=(1, 2, 3))[:, None, None], 68, axis=1).repeat(2, axis=2)


def test_gt_landmarks_are_cached_by_content_and_version(tmp_path, monkeypatch):
    from lmgs_eval.metrics.landmarks import cached_landmarks

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    rng = np.random.default_rng(0)
    a, b = rng.random((3, 16, 16, 3)).astype(np.float32), rng.random((3, 16, 16, 3)).astype(np.float32)
    be = _CountingBackend()
    first = cached_landmarks(be, a)
    np.testing.assert_array_equal(first, be.landmarks(a))
    be.calls = 0
    np.testing.assert_array_equal(cached_landmarks(be, a), first)
    assert be.calls == 0  # same frames, same backend: from the cache
    cached_landmarks(be, b)
    assert be.calls == 1  # other frames: computed
    be.version = "counting-2"
    cached_landmarks(be, a)
    assert be.calls == 2  # other backend version: computed
    files = list((tmp_path / "lmgs" / "landmarks").glob("*.npy"))
    assert len(files) == 3
    for f in files:
        f.write_bytes(b"not an npy file")
    np.testing.assert_array_equal(cached_landmarks(be, a), first)  # damaged entry: recomputed
    assert be.calls == 3
    # LMD reads ground truth through the cache and scores the same
    m = LMD(backend=GivenBackend(first), gt_backend=be)
    assert m.compute(m.update(a, a)).value == pytest.approx(0.0)
    assert be.calls == 3
