"""Confidence intervals and paired tests over the per-item values kept in result records.

Every metric of the toolkit is a mean of per-frame (or per-window) values, and records keep
those values (``metrics.<key>.per_item``), so intervals and tests are computed from the
results store alone, never by re-running anything.

* :func:`bootstrap_ci`: percentile bootstrap of the mean over items,

  .. math:: \\bar x^{*}_b = \\frac1n \\sum_i x_{I_{bi}},\\quad I_{bi} \\sim U\\{1..n\\},\\qquad
            \\mathrm{CI}_{95} = [q_{2.5}(\\bar x^*), q_{97.5}(\\bar x^*)]

  with a fixed seed (2,000 resamples by default; Efron & Tibshirani 1993, ch. 13).
* :func:`bootstrap_ci_seeds`: the same with two levels when there are several seeds
  (resample seeds, then items within each resampled seed), so the interval covers both
  training noise and item noise.
* :func:`paired_test`: two methods scored on the same items: paired bootstrap of the mean
  difference :math:`d_i = a_i - b_i` (two-sided p from the null-centred bootstrap
  distribution, :math:`p = (1 + \\#\\{|\\bar d^*_b - \\bar d| \\ge |\\bar d|\\}) / (B + 1)`)
  and the Wilcoxon signed-rank test (:func:`scipy.stats.wilcoxon`, two-sided, zero
  differences dropped).

NaN items (e.g. frames where no face was found) are dropped; in a paired test a pair is
dropped when either side is NaN. All functions are deterministic for a given ``seed``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import wilcoxon

N_RESAMPLES = 2000
SEED = 0
ALPHA = 0.05


@dataclass(frozen=True)
class CI:
    """A mean and its bootstrap interval.

    Attributes:
        mean: the statistic on the full sample.
        lo: lower bound (``(1 - level) / 2`` percentile).
        hi: upper bound.
        n: items used (after dropping NaN).
        level: coverage, e.g. 0.95.
    """

    mean: float
    lo: float
    hi: float
    n: int
    level: float = 0.95


@dataclass(frozen=True)
class PairedTest:
    """Outcome of :func:`paired_test` between methods ``a`` and ``b`` on the same items.

    Attributes:
        mean_diff: mean of ``a - b``.
        ci: bootstrap interval of the mean difference.
        p_bootstrap: two-sided paired-bootstrap p-value.
        p_wilcoxon: two-sided Wilcoxon signed-rank p-value (1.0 when all differences are 0).
        n: pairs used.
    """

    mean_diff: float
    ci: CI
    p_bootstrap: float
    p_wilcoxon: float
    n: int

    @property
    def p(self) -> float:
        """The more conservative of the two p-values (what the tables use)."""
        return max(self.p_bootstrap, self.p_wilcoxon)

    def significant(self, alpha: float = ALPHA) -> bool:
        """True when both tests reject equality at level ``alpha``."""
        return self.p < alpha


def _clean(values: Sequence[float | None]) -> np.ndarray:
    x = np.asarray([np.nan if v is None else v for v in values], dtype=np.float64).ravel()
    return x[np.isfinite(x)]


def bootstrap_means(x: np.ndarray, n_resamples: int = N_RESAMPLES, seed: int = SEED) -> np.ndarray:
    """Means of ``n_resamples`` resamples (with replacement) of ``x``; indices from ``default_rng(seed)``.

    The draw is ``rng.integers(0, n, size=(n_resamples, n))``, so a reference written with
    the same generator and call reproduces it exactly.
    """
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.shape[0], size=(n_resamples, x.shape[0]))
    return x[idx].mean(axis=1)


def bootstrap_ci(values: Sequence[float | None], n_resamples: int = N_RESAMPLES, seed: int = SEED,
                 level: float = 0.95) -> CI | None:
    """Percentile bootstrap interval of the mean of ``values`` (NaN/None dropped).

    Args:
        values: per-item values.
        n_resamples: bootstrap resamples.
        seed: seed of ``numpy.random.default_rng``.
        level: coverage.

    Returns:
        The interval, or None when no finite value is left.
    """
    x = _clean(values)
    if x.size == 0:
        return None
    means = bootstrap_means(x, n_resamples, seed)
    q = 100 * (1 - level) / 2
    lo, hi = np.percentile(means, [q, 100 - q])
    return CI(float(x.mean()), float(lo), float(hi), int(x.size), level)


def bootstrap_ci_seeds(per_seed: Sequence[Sequence[float | None]], n_resamples: int = N_RESAMPLES, seed: int = SEED,
                       level: float = 0.95) -> CI | None:
    """Two-level bootstrap over seeds and items: the interval of the mean of per-seed means.

    One seed falls back to :func:`bootstrap_ci`. With several, each resample draws seeds
    with replacement and then items within each drawn seed; the statistic is the mean of
    the drawn seeds' means.

    Args:
        per_seed: per-item values of each seed (runs of one method on one clip).

    Returns:
        The interval around the mean of the seeds' means, or None without data.
    """
    groups = [g for g in (_clean(v) for v in per_seed) if g.size]
    if not groups:
        return None
    if len(groups) == 1:
        return bootstrap_ci(groups[0], n_resamples, seed, level)
    rng = np.random.default_rng(seed)
    k = len(groups)
    pick = rng.integers(0, k, size=(n_resamples, k))
    inner = np.empty((k, n_resamples))
    for j, g in enumerate(groups):
        idx = rng.integers(0, g.size, size=(n_resamples, g.size))
        inner[j] = g[idx].mean(axis=1)
    stats = inner[pick, np.arange(n_resamples)[:, None]].mean(axis=1)
    q = 100 * (1 - level) / 2
    lo, hi = np.percentile(stats, [q, 100 - q])
    mean = float(np.mean([g.mean() for g in groups]))
    return CI(mean, float(lo), float(hi), int(sum(g.size for g in groups)), level)


def paired_test(a: Sequence[float | None], b: Sequence[float | None], n_resamples: int = N_RESAMPLES,
                seed: int = SEED) -> PairedTest | None:
    """Paired bootstrap and Wilcoxon signed-rank test of ``mean(a - b) == 0``.

    Args:
        a: per-item values of method A.
        b: per-item values of method B on the same items (same length, same order).
        n_resamples: bootstrap resamples.
        seed: seed of the bootstrap.

    Returns:
        The test, or None when fewer than 2 complete pairs remain.

    Raises:
        ValueError: when ``a`` and ``b`` differ in length (the items are not the same).
    """
    xa = np.asarray([np.nan if v is None else v for v in a], dtype=np.float64).ravel()
    xb = np.asarray([np.nan if v is None else v for v in b], dtype=np.float64).ravel()
    if xa.shape != xb.shape:
        raise ValueError(f"paired test needs the same items: {xa.size} vs {xb.size} values")
    ok = np.isfinite(xa) & np.isfinite(xb)
    d = xa[ok] - xb[ok]
    if d.size < 2:
        return None
    mean = float(d.mean())
    means = bootstrap_means(d, n_resamples, seed)
    lo, hi = np.percentile(means, [2.5, 97.5])
    p_boot = float((1 + np.count_nonzero(np.abs(means - mean) >= abs(mean))) / (n_resamples + 1))
    if np.all(d == 0):
        p_w = 1.0
    else:
        p_w = float(wilcoxon(d, zero_method="wilcox", alternative="two-sided").pvalue)
    return PairedTest(mean, CI(mean, float(lo), float(hi), int(d.size)), p_boot, p_w, int(d.size))


def mean_over_seeds(per_seed: Sequence[Sequence[float | None]]) -> list[float] | None:
    """Item-wise mean over seeds (NaN where every seed is NaN); None if the lengths differ.

    Used to pair two methods run with several seeds: each item's value is its mean over
    the method's seeds.
    """
    arrs = [np.asarray([np.nan if v is None else v for v in s], dtype=np.float64) for s in per_seed]
    if not arrs or len({a.size for a in arrs}) != 1:
        return None
    stack = np.stack(arrs)
    with np.errstate(all="ignore"):
        cnt = np.isfinite(stack).sum(axis=0)
        tot = np.where(np.isfinite(stack), stack, 0.0).sum(axis=0)
        m = np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)
    return [float(v) for v in m]
