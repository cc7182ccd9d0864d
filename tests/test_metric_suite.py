"""The run's metric suite: each network built once and reused, same numbers as a fresh one, picklable."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import lmgs_eval.metrics.metric_suite as MS
from lmgs_eval.metrics.config import SuiteConfig


def _clip(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)


def test_each_metric_is_built_once_and_scores_as_a_fresh_one(monkeypatch):
    built = []
    real = MS.create_metric
    monkeypatch.setattr(MS, "create_metric", lambda name, **kw: built.append(name) or real(name, **kw))
    suite = MS.MetricSuite()
    gt = _clip(0)
    first = suite.score(_clip(1), gt, None, lmd=False)
    second = suite.score(_clip(2), gt, None, lmd=False)
    lp = suite.lpips_name
    assert sorted(built) == sorted(["psnr", "ssim", "lpips", "lse"])  # two clips, one build each
    assert first["psnr"].value != second["psnr"].value  # the reused metrics hold no state between clips
    fresh = MS.MetricSuite().score(_clip(2), gt, None, lmd=False)
    for name in ("psnr", "ssim", lp):
        assert second[name].value == pytest.approx(fresh[name].value, rel=1e-6, abs=1e-9)
    assert second["lse"].available is False  # no audio: LSE says so instead of a number
    clone = pickle.loads(pickle.dumps(suite))
    assert clone.config == suite.config and clone._metrics == {}  # a worker loads its own networks
    assert clone.sync.names == suite.sync.names  # and resolves the run's --sync choice from the config


def test_a_ground_truth_of_another_shape_is_one_line():
    from lmgs.errors import InputError

    with pytest.raises(InputError, match=r"rendered frames \(3, 64, 64, 3\) and ground truth \(3, 32, 32, 3\) differ"):
        MS.MetricSuite().score(_clip(1), _clip(0)[:, :32, :32], None)


# ----------------------------------------------------------------------------- the ground truth's side, once
def _face_clip(n: int = 24, size: int = 96, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    import cv2
    from skimage import data

    face = cv2.resize(data.astronaut()[0:280, 90:370], (size, size), interpolation=cv2.INTER_AREA)  # the head
    rng = np.random.default_rng(seed)
    gt = np.stack([np.roll(face, (i % 5) - 2, axis=1) for i in range(n)])
    pred = np.clip(gt.astype(np.int16) + rng.integers(-12, 13, gt.shape), 0, 255).astype(np.uint8)
    return gt, pred


class _Counting:
    """Wraps an LPIPS metric's ``features`` and counts the frames it is run on."""

    def __init__(self, metric, monkeypatch):
        self.frames = 0
        real = metric.features

        def counted(x):
            self.frames += len(x)
            return real(x)

        monkeypatch.setattr(metric, "features", counted)


def test_lpips_ground_truth_features_are_computed_once_and_give_the_same_distances(monkeypatch):
    from lmgs_eval.metrics.lpips import LPIPS

    gt, pred = _face_clip(10, 64)
    gf, pf = gt.astype(np.float32) / 255, pred.astype(np.float32) / 255
    plain = LPIPS("stlpips-alex", batch=4).distances(pf, gf)  # no key: nothing kept
    m = LPIPS("stlpips-alex", batch=4)
    count = _Counting(m, monkeypatch)
    assert np.all(m.distances(gf, gf, gt_key="k", same=True) == 0.0)  # the ground truth row
    assert count.frames == 10  # its features once, not twice
    cached = m.distances(pf, gf, gt_key="k")
    assert count.frames == 20  # then only the prediction's frames
    np.testing.assert_allclose(cached, plain, rtol=1e-5, atol=1e-7)
    assert plain.min() > 0.0
    other = m.distances(pf, pf, gt_key="other")  # another key: computed afresh, not the cached features
    assert count.frames == 40 and np.all(np.abs(other) < 1e-6)


def test_lpips_features_over_the_budget_are_kept_in_part_and_say_so(monkeypatch):
    from lmgs_eval.metrics.lpips import LPIPS

    gt, pred = _face_clip(8, 64)
    gf, pf = gt.astype(np.float32) / 255, pred.astype(np.float32) / 255
    m = LPIPS("stlpips-alex", batch=4)
    per_batch = sum(f.nbytes for f in m.features(gf[:4]))
    m.cache_bytes = per_batch + 1  # room for the first batch of 4 frames only
    count = _Counting(m, monkeypatch)
    a = m.distances(pf, gf, gt_key="k")
    assert count.frames == 16 and "cached for 4 of 8 frames" in m.cache_note
    b = m.distances(pf, gf, gt_key="k")
    assert count.frames == 16 + 4 + 8  # the first batch's ground truth from the cache, the second recomputed
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    m.cache_bytes = 0
    m.distances(pf, gf, gt_key="k2")
    assert "cached for 0 of 8 frames" in m.cache_note and "LMGS_GT_CACHE_GB" in m.cache_note


def test_the_suite_scores_the_ground_truth_side_once_and_lse_reads_lmds_landmarks(monkeypatch):
    from lmgs_eval.metrics import landmarks as L
    from lmgs_eval.metrics.sync.scorers import load
    from lmgs_eval.metrics.sync.scoring import lse

    gt, pred = _face_clip(40, 128)
    audio = (0.1 * np.random.default_rng(3).standard_normal(40 * 640)).astype(np.float32)
    suite = MS.MetricSuite(SuiteConfig(sync="landmark"))
    suite.score(gt, gt, audio, in_sync=True)
    lp = suite.metric("lpips")
    count = _Counting(lp, monkeypatch)
    calls = []
    real = L.DlibBackend.landmarks
    monkeypatch.setattr(L.DlibBackend, "landmarks", lambda self, f: calls.append(len(f)) or real(self, f))
    res = suite.score(pred, gt, audio)
    assert count.frames == 40  # the prediction only: the ground truth's features were kept
    assert calls == [40]  # one landmark pass (LMD's on the prediction), reused by LSE; the ground truth's from cache
    assert set(suite.timings) >= {"psnr", "ssim", suite.lpips_name, "lmd", "lse", "total"}
    sc, _ = load("landmark")
    alone = lse(pred, audio, scorer=sc)  # LSE finding its own landmarks
    assert res["lse"].values["lse_d"] == pytest.approx(alone.values["lse_d"], abs=1e-9)
    assert res["lse"].values["offset"] == alone.values["offset"]
    assert "given with the clip" in " ".join(res["lse"].notes)
