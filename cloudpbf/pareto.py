"""The Pareto front of cost against error, defined once (the sweep study marks it, the report draws it).

A point is on the front when no other point dominates it: none has cost <= and error <= with one of the
two strictly smaller.  Equal points do not dominate each other, so duplicates of a front point are all
on the front.  Points with a NaN cost or error are never on it.
"""
from __future__ import annotations

import numpy as np

__all__ = ["pareto_mask", "pareto_front"]


def pareto_mask(cost: np.ndarray, error: np.ndarray) -> np.ndarray:
    """True where no other point has cost <= and error <= with one strictly smaller (NaN: False)."""
    cost = np.asarray(cost, dtype=float)
    error = np.asarray(error, dtype=float)
    ok = np.isfinite(cost) & np.isfinite(error)
    out = np.zeros(len(cost), dtype=bool)
    for i in np.flatnonzero(ok):
        better_eq = ok & (cost <= cost[i]) & (error <= error[i])
        strictly = (cost < cost[i]) | (error < error[i])
        out[i] = not np.any(better_eq & strictly)
    return out


def pareto_front(df, cost: str = "wall_s", error: str = "error_self"):
    """The rows of DataFrame `df` on the front of columns `cost` and `error`, sorted by cost (then error)."""
    mask = pareto_mask(df[cost].to_numpy(float), df[error].to_numpy(float))
    return df[mask].sort_values([cost, error], kind="stable")
