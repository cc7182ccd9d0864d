"""Bootstrap intervals and tests against numpy / scipy references, analytic cases and AR(1) ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from lmgs_eval.report.stats import (block_indices, block_length, bootstrap_ci, bootstrap_ci_seeds, mean_over_seeds,
                                    paired_test, seed_test)


def test_bootstrap_ci_matches_numpy_percentile_reference():
    x = np.array([2.0, 3.5, 1.0, 4.0, 2.5, 3.0, 5.0, 0.5, 2.0, 3.25])
    # Reference written out with numpy alone: same generator, same draw, percentile method.
    rng = np.random.default_rng(7)
    idx = rng.integers(0, x.size, size=(2000, x.size))
    boot = np.array([x[row].mean() for row in idx])
    lo, hi = np.percentile(boot, [2.5, 97.5])
    ci = bootstrap_ci(list(x), n_resamples=2000, seed=7, block=1)
    assert ci.mean == pytest.approx(x.mean())
    assert (ci.lo, ci.hi) == (pytest.approx(lo, abs=1e-12), pytest.approx(hi, abs=1e-12))
    assert ci.n == 10 and ci.lo < ci.mean < ci.hi


def test_bootstrap_ci_close_to_normal_theory_and_drops_nan():
    rng = np.random.default_rng(0)
    x = rng.normal(5.0, 2.0, size=400)
    ci = bootstrap_ci(list(x) + [None, float("nan")], seed=0)
    assert ci.block <= 3  # independent draws: (nearly) the ordinary bootstrap
    half = 1.959964 * x.std(ddof=1) / math.sqrt(x.size)
    assert ci.n == 400
    assert ci.hi - ci.lo == pytest.approx(2 * half, rel=0.1)
    assert bootstrap_ci([None, float("nan")]) is None


def test_seed_level_interval():
    a = [1.0, 2.0, 3.0, 4.0]
    assert bootstrap_ci_seeds([a]) == bootstrap_ci(a)
    ci = bootstrap_ci_seeds([a, [v + 1 for v in a], [v + 2 for v in a]], seed=3)
    assert ci.mean == pytest.approx(3.5)
    assert ci.lo < 3.5 < ci.hi
    # Seeds that disagree widen the interval beyond the item-only one of a single seed.
    assert ci.hi - ci.lo > bootstrap_ci(a, seed=3).hi - bootstrap_ci(a, seed=3).lo - 1e-9
    assert mean_over_seeds([[1.0, None], [3.0, 4.0]]) == [2.0, 4.0]
    assert mean_over_seeds([[1.0], [1.0, 2.0]]) is None


def ar1(phi: float, n: int, rng: np.random.Generator, burn: int = 200) -> np.ndarray:
    e = rng.normal(size=n + burn)
    x = np.zeros_like(e)
    for t in range(1, e.size):
        x[t] = phi * x[t - 1] + e[t]
    return x[burn:]


@pytest.mark.parametrize("phi", [0.3, 0.6, 0.8])
def test_block_length_follows_the_ar1_optimum(phi):
    # For AR(1), R(k) = s^2 phi^|k|, so G = 2 s^2 phi / (1 - phi)^2 and the long-run variance is
    # s^2 (1 + phi) / (1 - phi): the circular-block optimum is (6 phi^2 / (1 - phi^2)^2)^(1/3) n^(1/3).
    rng = np.random.default_rng(11)
    n = 4000
    truth = (6 * phi ** 2 / (1 - phi ** 2) ** 2) ** (1 / 3) * n ** (1 / 3)
    got = np.median([block_length(ar1(phi, n, rng)) for _ in range(15)])
    assert got == pytest.approx(truth, rel=0.25)


def test_block_length_edges():
    rng = np.random.default_rng(3)
    assert block_length(rng.normal(size=5)) == 1
    assert block_length(np.full(100, 2.0)) == 1
    assert np.median([block_length(rng.normal(size=500)) for _ in range(10)]) <= 2
    # a random walk: long blocks, never beyond min(3 sqrt(n), n / 3)
    walks = [block_length(np.cumsum(rng.normal(size=137))) for _ in range(10)]
    assert min(walks) >= 10 and max(walks) <= math.ceil(min(3 * math.sqrt(137), 137 / 3))


def test_block_indices_are_circular_runs():
    rng = np.random.default_rng(0)
    idx = block_indices(10, 4, 3, rng)
    assert idx.shape == (3, 10)
    for row in idx:
        for start in (0, 4):
            run = row[start:start + 4]
            assert np.array_equal(run, (run[0] + np.arange(4)) % 10)
    assert np.array_equal(block_indices(7, 1, 2, np.random.default_rng(5)),
                          np.random.default_rng(5).integers(0, 7, size=(2, 7)))


def test_block_bootstrap_covers_the_mean_of_correlated_frames():
    # 137 frames of an AR(1) series with phi 0.7 (consecutive frames alike): the frame-by-frame
    # bootstrap's 95% interval misses the true mean (0) far more often than 5%; the block one does not.
    rng = np.random.default_rng(4)
    hit_block = hit_iid = 0
    trials = 200
    for t in range(trials):
        x = ar1(0.7, 137, rng)
        cb = bootstrap_ci(x, n_resamples=500, seed=t)
        ci = bootstrap_ci(x, n_resamples=500, seed=t, block=1)
        hit_block += cb.lo <= 0.0 <= cb.hi
        hit_iid += ci.lo <= 0.0 <= ci.hi
    assert hit_iid / trials < 0.80
    assert hit_block / trials > 0.85


def test_paired_test_better_on_every_item_is_significant():
    rng = np.random.default_rng(1)
    b = rng.uniform(0.1, 0.3, size=60)
    a = b - rng.uniform(0.005, 0.02, size=60)  # a lower (better for a lower-is-better metric) everywhere
    t = paired_test(a, b)
    assert t.mean_diff < 0 and t.ci.hi < 0
    assert t.p < 0.01 and t.significant() and t.unit == "frames"


def test_paired_test_on_noise_is_not_significant():
    rng = np.random.default_rng(2)
    a = rng.normal(0, 1, size=50)
    b = rng.normal(0, 1, size=50)
    t = paired_test(a, b)
    assert t.p >= 0.05 and not t.significant()
    assert t.ci.lo < 0 < t.ci.hi


def test_paired_test_false_alarms_on_correlated_frames():
    # Two methods equal in expectation whose per-frame difference drifts slowly (AR(1), phi 0.8):
    # at alpha 0.05 the block test rejects near 5% of the time, frame-by-frame resampling far more.
    rng = np.random.default_rng(9)
    trials = 150
    rej_block = rej_iid = 0
    for t in range(trials):
        d = ar1(0.8, 137, rng)
        rej_block += paired_test(d, np.zeros_like(d), n_resamples=400, seed=t).significant()
        rej_iid += paired_test(d, np.zeros_like(d), n_resamples=400, seed=t, block=1).significant()
    assert rej_iid / trials > 0.25
    assert rej_block / trials < 0.15


def test_seed_test_is_welch():
    a = [36.7, 36.5, 36.9, 36.6, 36.8]
    b = [36.9, 37.1, 36.6, 36.8, 36.95]
    t = seed_test(a, b)
    ref = sps.ttest_ind(a, b, equal_var=False)
    assert t.p == pytest.approx(ref.pvalue, rel=1e-12) and t.unit == "seeds" and (t.n_a, t.n_b) == (5, 5)
    assert t.mean_diff == pytest.approx(np.mean(a) - np.mean(b))
    assert "Welch" in t.how and "5 vs 5 seeds" in t.how
    assert seed_test([1.0], [1.0, 2.0]) is None
    assert seed_test([1.0, 1.0], [2.0, 2.0]).p == 0.0 and seed_test([1.0, 1.0], [1.0, 1.0]).p == 1.0


def test_paired_test_edge_cases():
    assert paired_test([1.0, 2.0], [1.0, 2.0]).p == 1.0
    assert paired_test([1.0, None, 3.0], [2.0, 2.0, None]) is None  # one complete pair
    with pytest.raises(ValueError, match="same items"):
        paired_test([1.0, 2.0], [1.0])
