"""Bootstrap intervals and paired tests against numpy / scipy references and analytic cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from lmgs_eval.report.stats import bootstrap_ci, bootstrap_ci_seeds, mean_over_seeds, paired_test


def test_bootstrap_ci_matches_numpy_percentile_reference():
    x = np.array([2.0, 3.5, 1.0, 4.0, 2.5, 3.0, 5.0, 0.5, 2.0, 3.25])
    # Reference written out with numpy alone: same generator, same draw, percentile method.
    rng = np.random.default_rng(7)
    idx = rng.integers(0, x.size, size=(2000, x.size))
    boot = np.array([x[row].mean() for row in idx])
    lo, hi = np.percentile(boot, [2.5, 97.5])
    ci = bootstrap_ci(list(x), n_resamples=2000, seed=7)
    assert ci.mean == pytest.approx(x.mean())
    assert (ci.lo, ci.hi) == (pytest.approx(lo, abs=1e-12), pytest.approx(hi, abs=1e-12))
    assert ci.n == 10 and ci.lo < ci.mean < ci.hi


def test_bootstrap_ci_close_to_normal_theory_and_drops_nan():
    rng = np.random.default_rng(0)
    x = rng.normal(5.0, 2.0, size=400)
    ci = bootstrap_ci(list(x) + [None, float("nan")], seed=0)
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


def test_paired_test_better_on_every_item_is_significant():
    rng = np.random.default_rng(1)
    b = rng.uniform(0.1, 0.3, size=60)
    a = b - rng.uniform(0.005, 0.02, size=60)  # a lower (better for a lower-is-better metric) everywhere
    t = paired_test(a, b)
    assert t.mean_diff < 0 and t.ci.hi < 0
    assert t.p_bootstrap < 0.01 and t.p_wilcoxon < 1e-6 and t.significant()
    assert t.p_wilcoxon == pytest.approx(sps.wilcoxon(a - b).pvalue, rel=1e-12)


def test_paired_test_on_noise_is_not_significant():
    rng = np.random.default_rng(2)
    a = rng.normal(0, 1, size=50)
    b = rng.normal(0, 1, size=50)
    t = paired_test(a, b)
    assert t.p_wilcoxon == pytest.approx(sps.wilcoxon(a, b).pvalue, rel=1e-12)
    assert t.p_bootstrap >= 0.05 and t.p_wilcoxon >= 0.05 and not t.significant()
    assert t.ci.lo < 0 < t.ci.hi


def test_paired_test_edge_cases():
    assert paired_test([1.0, 2.0], [1.0, 2.0]).p == 1.0
    assert paired_test([1.0, None, 3.0], [2.0, 2.0, None]) is None  # one complete pair
    with pytest.raises(ValueError, match="same items"):
        paired_test([1.0, 2.0], [1.0])
