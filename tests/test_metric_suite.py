"""The run's metric suite: each network built once and reused, same numbers as a fresh one, picklable."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import lmgs_eval.metrics.metric_suite as MS


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
    assert sorted(built) == sorted(["psnr", "ssim", lp])  # two clips, one build each
    assert first["psnr"].value != second["psnr"].value  # the reused metrics hold no state between clips
    fresh = MS.MetricSuite().score(_clip(2), gt, None, lmd=False)
    for name in ("psnr", "ssim", lp):
        assert second[name].value == pytest.approx(fresh[name].value, rel=1e-6, abs=1e-9)
    assert second["lse"].available is False  # no audio: LSE says so instead of a number
    clone = pickle.loads(pickle.dumps(suite))
    assert clone.alexnet == suite.alexnet and clone._metrics == {}  # a worker loads its own networks


def test_a_ground_truth_of_another_shape_is_one_line():
    from lmgs.errors import InputError

    with pytest.raises(InputError, match=r"rendered frames \(3, 64, 64, 3\) and ground truth \(3, 32, 32, 3\) differ"):
        MS.MetricSuite().score(_clip(1), _clip(0)[:, :32, :32], None)
