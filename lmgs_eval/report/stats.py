"""Confidence intervals and tests over the per-item values kept in result records.

Every metric of the toolkit is a mean of per-frame (or per-window) values, and records keep
those values (``metrics.<key>.per_item``), so intervals and tests are computed from the
results store alone, never by re-running anything.

Consecutive frames of a video are not independent draws: a mouth that is wrong in one frame
is wrong in the next few. Resampling frames one by one then underestimates the variance of a
mean, and p-values come out too small. Every frame-level interval and test here therefore
resamples **circular blocks** of consecutive frames (Politis & Romano 1992), with the block
length chosen from the data (:func:`block_length`):

* :func:`bootstrap_ci`: circular-block percentile bootstrap of the mean,

  .. math:: \\bar x^{*}_b = \\frac1n \\sum_{j<\\lceil n/\\ell\\rceil} \\sum_{t<\\ell} x_{(S_{bj}+t) \\bmod n},
            \\quad S_{bj} \\sim U\\{0..n-1\\},\\qquad \\mathrm{CI}_{95} = [q_{2.5}(\\bar x^*), q_{97.5}(\\bar x^*)]

  (the last block cut so that a resample has ``n`` items; ``\\ell = 1`` is Efron's bootstrap).
* :func:`bootstrap_ci_seeds`: two levels when there are several seeds (resample seeds, then
  blocks of frames within each drawn seed), so the interval covers training and frame noise.
* :func:`paired_test`: two methods scored on the same frames: block bootstrap of the mean
  difference :math:`d_t = a_t - b_t`, the block length chosen from the series :math:`d`, with a
  two-sided p from the null-centred distribution,
  :math:`p = (1 + \\#\\{|\\bar d^*_b - \\bar d| \\ge |\\bar d|\\}) / (B + 1)`.
* :func:`seed_test`: two trained methods with several seeds each: Welch's t-test on the
  per-seed means. The seed is the unit of replication of a trained method; a frame-level test
  of seed-averaged frames says nothing about whether another draw of the seeds would agree.

The block length (:func:`block_length`) is the rule of Politis & White (2004) with the
correction of Patton, Politis & White (2009) for the circular block bootstrap:

.. math:: \\hat\\ell = \\Big(\\frac{2\\hat G^2}{\\hat D}\\Big)^{1/3} n^{1/3},\\quad
          \\hat G = \\sum_{|k|\\le M} \\lambda(k/M)\\,|k|\\,\\hat R(k),\\quad
          \\hat D = \\tfrac43 \\Big(\\sum_{|k|\\le M} \\lambda(k/M)\\,\\hat R(k)\\Big)^2

with :math:`\\hat R` the sample autocovariance, :math:`\\lambda` the flat-top window (1 up to
1/2, then linear to 0 at 1), :math:`M = 2\\hat m` where :math:`\\hat m` is the first lag after
which :math:`K_n = \\max(5, \\lceil\\sqrt{\\log_{10} n}\\rceil)` autocorrelations in a row are
below :math:`2\\sqrt{\\log_{10} n / n}`, and :math:`\\hat\\ell` rounded up and kept within
:math:`[1, \\min(3\\sqrt n, n/3)]`. Independent data give :math:`\\ell = 1`; an AR(1) series with
coefficient :math:`\\phi` gives about :math:`(6\\phi^2/(1-\\phi^2)^2)^{1/3} n^{1/3}`.

NaN items (frames where no face was found) are dropped; in a paired test a pair is dropped
when either side is NaN (the series is then shorter, its order kept). All functions are
deterministic for a given ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import ttest_ind

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
        block: block length of the resampling (1: items resampled one by one).
    """

    mean: float
    lo: float
    hi: float
    n: int
    level: float = 0.95
    block: int = 1


@dataclass(frozen=True)
class PairedTest:
    """The outcome of a test of ``mean(a) == mean(b)``: :func:`paired_test` or :func:`seed_test`.

    Attributes:
        mean_diff: mean of ``a`` minus mean of ``b``.
        p: two-sided p-value.
        n: frames (``unit="frames"``) or seeds of the smaller side (``unit="seeds"``).
        unit: ``"frames"`` (circular block bootstrap) or ``"seeds"`` (Welch's t on seed means).
        n_a: seeds of ``a`` (seed-level tests).
        n_b: seeds of ``b``.
        ci: bootstrap interval of the mean difference, with its block length (frame-level tests only).
    """

    mean_diff: float
    p: float
    n: int
    unit: str = "frames"
    n_a: int = 0
    n_b: int = 0
    ci: CI | None = None

    @property
    def block(self) -> int:
        """Block length of the frame-level bootstrap (1 for a seed-level test)."""
        return self.ci.block if self.ci is not None else 1

    def significant(self, alpha: float = ALPHA) -> bool:
        """True when the test rejects equality at level ``alpha``."""
        return self.p < alpha

    @property
    def how(self) -> str:
        """Which test this was, for a table's note."""
        if self.unit == "seeds":
            return f"Welch t on seed means, {self.n_a} vs {self.n_b} seeds"
        return f"circular block bootstrap over {self.n} frames, block {self.block}"


def _clean(values: Sequence[float | None]) -> np.ndarray:
    x = np.asarray([np.nan if v is None else v for v in values], dtype=np.float64).ravel()
    return x[np.isfinite(x)]


def block_length(x: np.ndarray) -> int:
    """The circular-block-bootstrap block length of series ``x`` (Politis & White 2004; see the module doc).

    Args:
        x: a finite 1-D series in time order.

    Returns:
        An integer in ``[1, max(1, min(3 sqrt(n), n / 3))]``; 1 for fewer than 8 items or a constant series.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    n = x.size
    if n < 8:
        return 1
    e = x - x.mean()
    acv0 = float(e @ e) / n
    if acv0 <= 0.0:
        return 1
    kn = max(5, math.ceil(math.sqrt(math.log10(n))))
    m_max = math.ceil(math.sqrt(n)) + kn
    m_max = min(m_max, n - 1)
    acv = np.array([float(e[k:] @ e[:n - k]) / n for k in range(m_max + 1)])
    rho = np.abs(acv / acv0)
    crit = 2.0 * math.sqrt(math.log10(n) / n)
    m_hat = None
    for m in range(0, m_max - kn + 1):
        if np.all(rho[m + 1:m + 1 + kn] < crit):
            m_hat = m
            break
    big_m = min(2 * max(m_hat, 1), m_max) if m_hat is not None else m_max
    k = np.arange(1, big_m + 1)
    t = k / big_m
    lam = np.where(t <= 0.5, 1.0, 2.0 * (1.0 - t))
    g = 2.0 * float(np.sum(lam * k * acv[1:big_m + 1]))
    lr = acv0 + 2.0 * float(np.sum(lam * acv[1:big_m + 1]))
    b_max = max(1, math.ceil(min(3.0 * math.sqrt(n), n / 3.0)))
    if lr <= 0.0 or g == 0.0:
        return 1
    b = (2.0 * g * g / (4.0 / 3.0 * lr * lr)) ** (1.0 / 3.0) * n ** (1.0 / 3.0)
    return int(min(max(1, math.ceil(b)), b_max))


def block_indices(n: int, block: int, n_resamples: int, rng: np.random.Generator) -> np.ndarray:
    """``(n_resamples, n)`` indices of circular-block resamples of ``0..n-1``.

    ``block == 1`` is the ordinary bootstrap draw ``rng.integers(0, n, size=(n_resamples, n))``.
    """
    if block <= 1:
        return rng.integers(0, n, size=(n_resamples, n))
    k = -(-n // block)
    starts = rng.integers(0, n, size=(n_resamples, k))
    idx = (starts[:, :, None] + np.arange(block)) % n
    return idx.reshape(n_resamples, k * block)[:, :n]


def bootstrap_means(x: np.ndarray, n_resamples: int = N_RESAMPLES, seed: int = SEED, block: int = 1) -> np.ndarray:
    """Means of ``n_resamples`` circular-block resamples of ``x`` (:func:`block_indices`, ``default_rng(seed)``)."""
    rng = np.random.default_rng(seed)
    return x[block_indices(x.shape[0], block, n_resamples, rng)].mean(axis=1)


def bootstrap_ci(values: Sequence[float | None], n_resamples: int = N_RESAMPLES, seed: int = SEED,
                 level: float = 0.95, block: int | None = None) -> CI | None:
    """Percentile circular-block bootstrap interval of the mean of ``values`` (NaN/None dropped).

    Args:
        values: per-item values in time order.
        n_resamples: bootstrap resamples.
        seed: seed of ``numpy.random.default_rng``.
        level: coverage.
        block: block length; None chooses it from the data (:func:`block_length`).

    Returns:
        The interval, or None when no finite value is left.
    """
    x = _clean(values)
    if x.size == 0:
        return None
    b = block_length(x) if block is None else int(block)
    means = bootstrap_means(x, n_resamples, seed, b)
    q = 100 * (1 - level) / 2
    lo, hi = np.percentile(means, [q, 100 - q])
    return CI(float(x.mean()), float(lo), float(hi), int(x.size), level, b)


def bootstrap_ci_seeds(per_seed: Sequence[Sequence[float | None]], n_resamples: int = N_RESAMPLES, seed: int = SEED,
                       level: float = 0.95) -> CI | None:
    """Two-level bootstrap over seeds and frames: the interval of the mean of per-seed means.

    One seed falls back to :func:`bootstrap_ci`. With several, each resample draws seeds
    with replacement and then circular blocks of frames within each drawn seed (each seed's
    block length from its own series); the statistic is the mean of the drawn seeds' means.

    Args:
        per_seed: per-item values of each seed (runs of one method on one clip).

    Returns:
        The interval around the mean of the seeds' means (``block``: the longest block used),
        or None without data.
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
    blocks = [block_length(g) for g in groups]
    for j, g in enumerate(groups):
        inner[j] = g[block_indices(g.size, blocks[j], n_resamples, rng)].mean(axis=1)
    stats = inner[pick, np.arange(n_resamples)[:, None]].mean(axis=1)
    q = 100 * (1 - level) / 2
    lo, hi = np.percentile(stats, [q, 100 - q])
    mean = float(np.mean([g.mean() for g in groups]))
    return CI(mean, float(lo), float(hi), int(sum(g.size for g in groups)), level, max(blocks))


def paired_test(a: Sequence[float | None], b: Sequence[float | None], n_resamples: int = N_RESAMPLES,
                seed: int = SEED, block: int | None = None) -> PairedTest | None:
    """Circular-block paired bootstrap test of ``mean(a - b) == 0`` over the same frames.

    Args:
        a: per-frame values of method A, in time order.
        b: per-frame values of method B on the same frames (same length, same order).
        n_resamples: bootstrap resamples.
        seed: seed of the bootstrap.
        block: block length; None chooses it from the differences (:func:`block_length`).

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
    bl = block_length(d) if block is None else int(block)
    if np.all(d == 0):
        return PairedTest(0.0, 1.0, int(d.size), "frames", ci=CI(0.0, 0.0, 0.0, int(d.size), 0.95, bl))
    means = bootstrap_means(d, n_resamples, seed, bl)
    lo, hi = np.percentile(means, [2.5, 97.5])
    p = float((1 + np.count_nonzero(np.abs(means - mean) >= abs(mean))) / (n_resamples + 1))
    return PairedTest(mean, p, int(d.size), "frames", ci=CI(mean, float(lo), float(hi), int(d.size), 0.95, bl))


def seed_test(a: Sequence[float | None], b: Sequence[float | None]) -> PairedTest | None:
    """Welch's two-sided t-test of equal means on per-seed values (``scipy.stats.ttest_ind``, unequal variances).

    Args:
        a: one value per seed of method A (its mean over the clip's frames).
        b: the same for method B (the seeds of two methods are not paired).

    Returns:
        The test, or None unless both sides have at least 2 finite values. Two sides without
        any spread are different exactly when their means differ (p 0 or 1).
    """
    xa, xb = _clean(a), _clean(b)
    if xa.size < 2 or xb.size < 2:
        return None
    diff = float(xa.mean() - xb.mean())
    if xa.std() == 0.0 and xb.std() == 0.0:
        p = 1.0 if diff == 0.0 else 0.0
    else:
        p = float(ttest_ind(xa, xb, equal_var=False).pvalue)
    return PairedTest(diff, p, int(min(xa.size, xb.size)), "seeds", n_a=int(xa.size), n_b=int(xb.size))


def mean_over_seeds(per_seed: Sequence[Sequence[float | None]]) -> list[float] | None:
    """Item-wise mean over seeds (NaN where every seed is NaN); None if the lengths differ.

    Used to pair two methods when one of them has a single seed: each frame's value is its
    mean over the other method's seeds.
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
