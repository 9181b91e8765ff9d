"""Seed statistics of the report: 95% confidence intervals, the Welch t-test (scipy.stats) and fitted orders
of convergence with resolution (scipy.optimize).

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
from scipy.optimize import curve_fit, minimize_scalar

__all__ = ["Interval", "mean_ci", "format_ci", "welch", "difference_ci", "ratio_ci", "describes_no_difference",
           "median_spread", "LEVEL", "ConvergenceFit", "convergence_order", "convergence_orders", "ORDER_LEVEL"]

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


# ---- order of convergence with resolution ----------------------------------------------------------------
ORDER_LEVEL = 0.90
"""Confidence level of the intervals on a fitted order of convergence."""
ORDER_BOUNDS = (0.05, 8.0)
"""The orders p searched; a fit that ends on either bound is reported as not determined."""
BOOTSTRAP_DRAWS = 400
"""Resamplings of the seeds behind a bootstrap interval."""
MIN_BOOTSTRAP_SEEDS = 3
"""The fewest seeds at every resolution for a bootstrap interval (two seeds give three distinct draws)."""
MIN_DETERMINED = 0.5
"""The smallest fraction of bootstrap draws that must determine an order for their interval to be reported."""


@dataclass(frozen=True)
class ConvergenceFit:
    """S(h) = limit + coefficient * h^order fitted to a statistic S against the resolution h (m): the order p
    (dimensionless), the limit S_inf (units of S) and the coefficient C (units of S per m^p), each NaN where the
    order is not determined (``reason`` says why).  order_lo/hi and limit_lo/hi: the ORDER_LEVEL interval, NaN
    where there is none; ``interval`` names how it was made ("bootstrap, N seeds, K/B draws": K of B resamplings
    determined an order; "fit covariance, t with D dof"; or "none: why").
    resolutions: distinct h used; seeds: seeds behind each point (1: single runs or means only)."""
    order: float
    limit: float
    coefficient: float
    order_lo: float
    order_hi: float
    limit_lo: float
    limit_hi: float
    resolutions: int
    seeds: int
    interval: str
    reason: str = ""

    @property
    def determined(self) -> bool:
        return not self.reason


def _undetermined(reason: str, resolutions: int, seeds: int) -> ConvergenceFit:
    nan = math.nan
    return ConvergenceFit(nan, nan, nan, nan, nan, nan, nan, resolutions, seeds, "none", reason)


def _profile_fit(h: np.ndarray, s: np.ndarray) -> tuple[float, float, float, str]:
    """(p, S_inf, C, reason; reason "" where p is determined, else a short why: flat, not monotone, p on one of
    ORDER_BOUNDS because the changes do not shrink as a power of h) of the least-squares fit of S_inf + C h^p to points sorted coarse to fine (h in m).
    For a fixed p the model is linear in (S_inf, C), so the residual is profiled over p (bounded Brent on log p);
    the series must change monotonically with h, since S_inf + C h^p can do nothing else (Richardson's
    assumption).  With three points the fit is exact: Richardson's p from (S1 - S2) / (S2 - S3)."""
    d = np.diff(s)
    scale = max(float(np.max(np.abs(s))), np.finfo(float).tiny)
    if np.all(np.abs(d) <= 1e-12 * scale):
        return math.nan, math.nan, math.nan, "flat: no change with h"
    if not (np.all(d > 0) or np.all(d < 0)):
        return math.nan, math.nan, math.nan, "not monotone in h (differences change sign)"
    x = h / h.min()                                      # the fit in h / h_min keeps the design well conditioned

    def solve(log_p: float) -> tuple[float, np.ndarray]:
        design = np.column_stack([np.ones_like(x), x ** math.exp(log_p)])
        coef, *_ = np.linalg.lstsq(design, s, rcond=None)
        return float(np.sum((design @ coef - s) ** 2)), coef

    lo, hi = (math.log(b) for b in ORDER_BOUNDS)
    best = minimize_scalar(lambda q: solve(q)[0], bounds=(lo, hi), method="bounded", options={"xatol": 1e-7})
    log_p = float(best.x)
    if min(log_p - lo, hi - log_p) < 1e-3:
        return math.nan, math.nan, math.nan, "p at its bound: changes not a power of h"
    p = math.exp(log_p)
    _, (limit, c) = solve(log_p)
    return p, float(limit), float(c) / float(h.min()) ** p, ""


def convergence_order(resolution, values, seeds=None, level: float = ORDER_LEVEL, draws: int = BOOTSTRAP_DRAWS,
                      rng: int | np.random.Generator | None = 0) -> ConvergenceFit:
    """Fit S(h) = S_inf + C h^p (Richardson extrapolation's model; h the resolution in m, finer is smaller) to the
    values of one statistic.

    resolution, values: one entry per run; seeds: each run's seed (None: the runs are single ones, or means).
    The fit is to the mean over seeds at each h (at least three distinct h; a least-squares fit profiled over p,
    exact with three).  Interval: with at least MIN_BOOTSTRAP_SEEDS seeds at every h, a percentile bootstrap over seeds (seed ids
    drawn with replacement and kept across h, since one seed's heating pattern is the same at every h), reported
    where at least MIN_DETERMINED of the draws determine an order; otherwise, with more than three h, the fit's
    covariance of the seed means (a t interval with n - 3 degrees of freedom); with three h, none.  A series that is
    flat, not monotone, or whose differences do not shrink as a power of h gives an order "not determined" with
    the reason, never an error."""
    frame = pd.DataFrame({"h": pd.to_numeric(pd.Series(list(resolution)), errors="coerce"),
                          "s": pd.to_numeric(pd.Series(list(values)), errors="coerce")})
    frame["seed"] = list(seeds) if seeds is not None else 0
    frame = frame[np.isfinite(frame["h"]) & np.isfinite(frame["s"]) & (frame["h"] > 0)]
    table = frame.pivot_table(index="h", columns="seed", values="s", aggfunc="mean").sort_index(ascending=False)
    n_h, n_seeds = len(table), int(table.notna().sum(axis=1).min()) if len(table) else 0
    if n_h < 3:
        return _undetermined(f"{n_h} resolution(s), 3 needed", n_h, n_seeds)
    h = table.index.to_numpy(float)
    mean = table.mean(axis=1).to_numpy(float)
    p, limit, c, reason = _profile_fit(h, mean)
    if reason:
        return _undetermined(reason, n_h, n_seeds)
    nan = math.nan
    tail = (1.0 - level) / 2.0
    if n_seeds >= MIN_BOOTSTRAP_SEEDS:
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        columns = table.to_numpy(float)
        fits = []
        for _ in range(draws):
            pick = gen.integers(0, columns.shape[1], columns.shape[1])
            fit = _profile_fit(h, np.nanmean(columns[:, pick], axis=1))
            if not fit[3]:
                fits.append(fit[:2])
        share = len(fits) / draws
        how = f"bootstrap, {columns.shape[1]} seeds, {len(fits)}/{draws} draws"
        if share < MIN_DETERMINED:
            return ConvergenceFit(p, limit, c, nan, nan, nan, nan, n_h, n_seeds, "none: " + how)
        orders, limits = np.asarray(fits).T
        (p_lo, p_hi), (s_lo, s_hi) = (np.quantile(a, [tail, 1.0 - tail]) for a in (orders, limits))
        return ConvergenceFit(p, limit, c, float(p_lo), float(p_hi), float(s_lo), float(s_hi), n_h, n_seeds, how)
    if n_h == 3:
        return ConvergenceFit(p, limit, c, nan, nan, nan, nan, n_h, n_seeds,
                              "none: 3 resolutions fit exactly")
    x = h / h.min()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            _, cov = curve_fit(lambda x_, s0, c0, p0: s0 + c0 * x_ ** p0, x, mean,
                               p0=(limit, c * float(h.min()) ** p, p))
        except (RuntimeError, ValueError):
            cov = np.full((3, 3), np.inf)
    se_s, se_p = (math.sqrt(v) if np.isfinite(v) and v >= 0 else nan for v in np.diag(cov)[[0, 2]])
    t = float(stats.t.ppf(1.0 - tail, n_h - 3))
    how = f"fit covariance, t with {n_h - 3} dof"
    if not (np.isfinite(se_p) and np.isfinite(se_s)):
        return ConvergenceFit(p, limit, c, nan, nan, nan, nan, n_h, n_seeds, "none: singular fit covariance")
    return ConvergenceFit(p, limit, c, p - t * se_p, p + t * se_p, limit - t * se_s, limit + t * se_s, n_h, n_seeds,
                          how)


def convergence_orders(frame: pd.DataFrame, statistics, by: str = "solver", resolution: str = "resolution_m",
                       seed: str = "seed", **kwargs) -> pd.DataFrame:
    """One :func:`convergence_order` per group of `by` and statistic column: columns by, statistic, order,
    order_lo, order_hi, limit, limit_lo, limit_hi, resolutions, seeds, interval, reason.  Rows whose `seed` is
    "mean" (a CSV's mean rows beside its per-seed ones) are dropped when per-seed rows exist."""
    rows = []
    data = frame
    if seed in frame.columns:
        per_seed = pd.to_numeric(frame[seed], errors="coerce")
        data = frame[per_seed.notna()].assign(**{seed: per_seed[per_seed.notna()]}) if per_seed.notna().any() \
            else frame.assign(**{seed: 0})
    for key, group in data.groupby(by, sort=True):
        for column in statistics:
            if column not in group.columns:
                continue
            fit = convergence_order(group[resolution], group[column],
                                    group[seed] if seed in group.columns else None, **kwargs)
            rows.append({by: key, "statistic": column, "order": fit.order, "order_lo": fit.order_lo,
                         "order_hi": fit.order_hi, "limit": fit.limit, "limit_lo": fit.limit_lo,
                         "limit_hi": fit.limit_hi, "resolutions": fit.resolutions, "seeds": fit.seeds,
                         "interval": fit.interval, "reason": fit.reason})
    return pd.DataFrame(rows, columns=[by, "statistic", "order", "order_lo", "order_hi", "limit", "limit_lo",
                                       "limit_hi", "resolutions", "seeds", "interval", "reason"])
