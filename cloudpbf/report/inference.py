"""Seed statistics of the report: 95% confidence intervals and the Welch t-test (scipy.stats).

Runs of one configuration that differ only in their seed are independent samples of the same
quantity (cloud cover, onset time, wall time, ...).  The report gives their mean with a two-sided
95% t-interval, ``mean ± t_{0.975, n-1} s / sqrt(n)`` (s the sample standard deviation), and compares
two configurations (adaptive against non-adaptive) with Welch's unequal-variance t-test.  Both
assume roughly normal seed spread; with 5 seeds they are the standard small-sample choice, and the
report prints n beside every interval so a reader can judge.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

__all__ = ["Interval", "mean_ci", "format_ci", "welch", "difference_ci", "ratio_ci", "describes_no_difference",
           "median_spread", "LEVEL"]

LEVEL = 0.95
"""Confidence level of every interval in the report."""


@dataclass(frozen=True)
class Interval:
    """Mean of n samples and its two-sided t-interval (lo, hi); lo = hi = mean when n == 1 or the
    samples are all equal; NaN when n == 0."""
    mean: float
    lo: float
    hi: float
    n: int

    @property
    def half_width(self) -> float:
        return 0.5 * (self.hi - self.lo)


def _finite(values) -> np.ndarray:
    a = pd.to_numeric(pd.Series(values), errors="coerce").to_numpy(dtype=float)
    return a[np.isfinite(a)]


def mean_ci(values, level: float = LEVEL) -> Interval:
    """Mean and `level` t-interval of the finite values (NaN and non-numbers dropped)."""
    a = _finite(values)
    n = len(a)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = float(a.mean())
    if n == 1:
        return Interval(mean, mean, mean, 1)
    sem = float(a.std(ddof=1)) / math.sqrt(n)
    if sem == 0.0:
        return Interval(mean, mean, mean, n)
    lo, hi = stats.t.interval(level, n - 1, loc=mean, scale=sem)
    return Interval(mean, float(lo), float(hi), n)


def format_ci(values, digits: int = 3) -> str:
    """'mean [lo, hi]' (95% t-interval, n samples), the value alone for n == 1, '–' for none."""
    ci = values if isinstance(values, Interval) else mean_ci(values)
    if ci.n == 0:
        return "–"
    if ci.n == 1 or ci.lo == ci.hi:
        return f"{ci.mean:.{digits}g}" + (f" (n={ci.n})" if ci.n > 1 else "")
    return f"{ci.mean:.{digits}g} [{ci.lo:.{digits}g}, {ci.hi:.{digits}g}]"


def welch(a, b) -> tuple[float, float]:
    """(t, two-sided p) of Welch's t-test between the finite values of a and b; (NaN, NaN) when either
    has fewer than two values or both are constant (no spread to test against)."""
    x, y = _finite(a), _finite(b)
    if len(x) < 2 or len(y) < 2:
        return math.nan, math.nan
    if x.std(ddof=1) == 0.0 and y.std(ddof=1) == 0.0:
        return math.nan, math.nan
    with warnings.catch_warnings():     # near-identical samples: scipy warns, the p-value is still right
        warnings.simplefilter("ignore", RuntimeWarning)
        res = stats.ttest_ind(x, y, equal_var=False)
    return float(res.statistic), float(res.pvalue)


def difference_ci(a, b, level: float = LEVEL) -> Interval:
    """mean(a) - mean(b) and its Welch `level` interval (unequal variances, Welch-Satterthwaite degrees of
    freedom); the interval is NaN where either side has fewer than two finite values."""
    x, y = _finite(a), _finite(b)
    if not len(x) or not len(y):
        return Interval(math.nan, math.nan, math.nan, 0)
    diff = float(x.mean() - y.mean())
    if len(x) < 2 or len(y) < 2:
        return Interval(diff, math.nan, math.nan, min(len(x), len(y)))
    va, vb = x.var(ddof=1) / len(x), y.var(ddof=1) / len(y)
    if va + vb == 0.0:
        return Interval(diff, diff, diff, min(len(x), len(y)))
    dof = (va + vb) ** 2 / (va ** 2 / (len(x) - 1) + vb ** 2 / (len(y) - 1))
    half = float(stats.t.ppf(0.5 + level / 2, dof)) * math.sqrt(va + vb)
    return Interval(diff, diff - half, diff + half, min(len(x), len(y)))


def ratio_ci(ratios, level: float = LEVEL) -> Interval:
    """The geometric mean of positive ratios (speed-ups) and its `level` t-interval, taken on their logarithms
    (a ratio of 2 and one of 1/2 average to 1); NaN bounds for fewer than two ratios."""
    r = _finite(ratios)
    r = r[r > 0]
    if not len(r):
        return Interval(math.nan, math.nan, math.nan, 0)
    logs = mean_ci(np.log(r), level)
    if logs.n < 2:
        return Interval(math.exp(logs.mean), math.nan, math.nan, logs.n)
    return Interval(math.exp(logs.mean), math.exp(logs.lo), math.exp(logs.hi), logs.n)


def describes_no_difference(interval: Interval, null: float = 1.0) -> bool:
    """True where the interval holds `null` (1 for a ratio, 0 for a difference) or is unknown: the data then
    measured no difference."""
    if not (math.isfinite(interval.lo) and math.isfinite(interval.hi)):
        return True
    return interval.lo <= null <= interval.hi


def median_spread(values) -> tuple[float, float, float, int]:
    """(median, 5th percentile, 95th percentile, n) of the finite values (NaN for none)."""
    a = _finite(values)
    if not len(a):
        return math.nan, math.nan, math.nan, 0
    lo, med, hi = np.percentile(a, [5, 50, 95])
    return float(med), float(lo), float(hi), len(a)
