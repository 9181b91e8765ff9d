"""The time-to-solution study's analysis: each setting's seed-mean errors against the reference, its cost (wall
time per simulated second), the cheapest setting within each error budget, the seeds resampled for intervals,
and the verdict (cloudpbf.studies.time_to_solution).  Errors are relative L2 norms (dimensionless), costs s per
simulated s."""
from __future__ import annotations

import contextlib
import math
import warnings

import numpy as np
import pandas as pd

from cloudpbf.pareto import pareto_mask

SERIES = (("cover", "cloud_cover"), ("volume", "cloudy_volume"), ("lwp", "lwp_mean"))
BOOTSTRAP_REPLICATES = 1000
GOAL_SPEEDUP = 2.0
"""The issue's target: at least 2x less wall time per simulated second than today's defaults at their error."""
BUDGET_FACTORS = (("default", 1.0), ("half", 0.5), ("double", 2.0))
"""The error budgets of the verdict, as multiples of the defaults' own error."""


def arrays(per_run: pd.DataFrame, series: pd.DataFrame, names: list[str], seeds: list[int]):
    """(S, W): S[setting, seed, series, time] and W[setting, seed] (NaN where a run is incomplete)."""
    times = np.sort(series["time_s"].unique()) if len(series) else np.zeros(0)
    S = np.full((len(names), len(seeds), len(SERIES), len(times)), np.nan)
    W = np.full((len(names), len(seeds)), np.nan)
    index = {n: i for i, n in enumerate(names)}
    seat = {s: j for j, s in enumerate(seeds)}
    ok = {(r.setting, int(r.seed)) for r in per_run.itertuples() if _truthy(r.complete)}
    for r in per_run.itertuples():
        if (r.setting, int(r.seed)) in ok:
            W[index[r.setting], seat[int(r.seed)]] = float(r.wall_per_sim_s)
    for (name, seed), g in series.groupby(["setting", "seed"]):
        if (name, int(seed)) in ok and name in index:
            g = g.sort_values("time_s")
            for k, (key, _) in enumerate(SERIES):
                S[index[name], seat[int(seed)], k] = np.interp(times, g["time_s"].to_numpy(float),
                                                               g[key].to_numpy(float))
    return S, W


def relative_errors(series: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(n, 3) relative L2 norms over time of `series` (n, 3, T) against `reference` (3, T); NaN where the
    reference's series is all zero or a value is missing."""
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = np.linalg.norm(reference, axis=-1)
        out = np.linalg.norm(series - reference, axis=-1) / norm
    out[:, ~(norm > 0)] = np.nan
    return out


def errors_of(S: np.ndarray, ref: int, draw=None, ref_draw=None) -> np.ndarray:
    """(n_settings, 3) errors of the seed-mean series (seeds `draw`) against the reference's (`ref_draw`)."""
    draw = np.arange(S.shape[1]) if draw is None else draw
    ref_draw = draw if ref_draw is None else ref_draw
    with _quiet():
        return relative_errors(np.nanmean(S[:, draw], axis=1), np.nanmean(S[ref, ref_draw], axis=0))


@contextlib.contextmanager
def _quiet():
    """Means of all-NaN slices (settings without a stable seed) are NaN, silently."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def cheapest(error: np.ndarray, cost: np.ndarray, ok: np.ndarray, budget: float) -> int | None:
    """Index of the cheapest setting with ok, finite cost and error <= budget (ties: the smaller error)."""
    cand = [i for i in np.flatnonzero(ok) if np.isfinite(cost[i]) and np.isfinite(error[i]) and error[i] <= budget]
    return min(cand, key=lambda i: (cost[i], error[i])) if cand else None


def evaluate(S, W, qualified, ref: int, default: int, draw=None) -> dict:
    """Errors, costs, the defaults' error, and the cheapest setting at each budget for one draw of seeds."""
    e3 = errors_of(S, ref, draw)
    error = e3.mean(axis=1)
    with _quiet():
        cost = np.nanmean(W[:, draw] if draw is not None else W, axis=1)
    e0 = error[default]
    picks = {name: cheapest(error, cost, qualified, f * e0) if np.isfinite(e0) else None for name, f in BUDGET_FACTORS}
    pick = picks["default"]
    speedup = cost[default] / cost[pick] if pick is not None and cost[pick] > 0 else math.nan
    return {"e3": e3, "error": error, "cost": cost, "picks": picks, "speedup": speedup}


def noise_floor(S, ref: int) -> float:
    """The error of the mean of half the reference's seeds against the other half's, over sqrt(2)."""
    seeds = np.flatnonzero(np.isfinite(S[ref, :, 0, :]).all(axis=-1)) if S.shape[-1] else []
    if len(seeds) < 2:
        return math.nan
    half = len(seeds) // 2
    e = errors_of(S, ref, draw=seeds[:half], ref_draw=seeds[half:2 * half])[ref]
    return float(np.mean(e) / math.sqrt(2.0))


def analyse(per_run: pd.DataFrame, series: pd.DataFrame, meta: pd.DataFrame, verdict_extra: dict,
            replicates: int = BOOTSTRAP_REPLICATES, rng_seed: int = 0) -> tuple[pd.DataFrame, dict]:
    """(per-setting frame, verdict) from the runs, their series and the settings' frame `meta` (one row per
    setting: setting, group, default, spacing_m, dt, cfl, iterations, divergence_iterations, adaptive)."""
    names = list(meta["setting"])
    seeds = sorted(int(s) for s in per_run["seed"].unique())
    S, W = arrays(per_run, series, names, seeds)
    groups = list(meta["group"])
    ref = groups.index("reference")
    default = [bool(_truthy(v)) for v in meta["default"]].index(True)
    complete = per_run.groupby("setting")["complete"].apply(lambda c: int(sum(_truthy(v) for v in c)))
    stable_seeds = np.array([int(complete.get(n, 0)) for n in names])
    qualified = (stable_seeds == len(seeds)) & (np.array(groups) != "reference")
    point = evaluate(S, W, qualified, ref, default)
    qualified &= np.isfinite(point["error"]) & np.isfinite(point["cost"])
    point = evaluate(S, W, qualified, ref, default)
    frame = meta.copy()
    frame["stable_seeds"], frame["seeds"] = stable_seeds, len(seeds)
    for k, (key, _) in enumerate(SERIES):
        frame[f"e_{key}"] = point["e3"][:, k]
    frame["error"], frame["wall_per_sim_s"] = point["error"], point["cost"]
    with _quiet():      # the spread over seeds of the error of one seed against the reference's mean
        reference = np.nanmean(S[ref], axis=0)
        per_seed = np.stack([relative_errors(S[:, j], reference).mean(axis=1) for j in range(len(seeds))], axis=1)
        frame["error_seed_spread"] = np.nanstd(per_seed, axis=1, ddof=1) if len(seeds) > 1 else np.nan
    frame["qualified"] = qualified
    frame["front"] = pareto_mask(np.where(qualified, point["cost"], np.nan),
                                 np.where(qualified, point["error"], np.nan))
    boot = {"speedup": [], "errors": [], "costs": [], "picks": []}
    rng = np.random.default_rng(rng_seed)
    for _ in range(int(replicates) if len(seeds) > 1 else 0):
        draw = rng.integers(0, len(seeds), len(seeds))
        r = evaluate(S, W, qualified, ref, default, draw)
        for key, value in (("speedup", r["speedup"]), ("errors", r["error"]), ("costs", r["cost"]),
                           ("picks", r["picks"]["default"])):
            boot[key].append(value)
    if boot["errors"]:
        with _quiet():
            for col, key in (("error", "errors"), ("wall_per_sim_s", "costs")):
                lo, hi = np.nanpercentile(np.array(boot[key]), [5, 95], axis=0)
                frame[f"{col}_p05"], frame[f"{col}_p95"] = lo, hi
        frame["cheapest_share"] = [float(np.mean([p == i for p in boot["picks"]])) for i in range(len(names))]
    verdict = build_verdict(frame, point, default, boot, verdict_extra, noise_floor(S, ref), len(seeds))
    return frame, verdict


def build_verdict(frame: pd.DataFrame, point: dict, default: int, boot: dict, extra: dict, floor: float,
                  n_seeds: int) -> dict:
    rows = frame.to_dict("records")
    clean = lambda v: None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v  # noqa: E731
    brief = lambda i: None if i is None else {k: clean(rows[i].get(k)) for k in (  # noqa: E731
        "setting", "group", "spacing_m", "dt", "cfl", "iterations", "divergence_iterations", "adaptive", "error",
        "wall_per_sim_s", "error_p05", "error_p95", "wall_per_sim_s_p05", "wall_per_sim_s_p95")}
    e0, c0 = point["error"][default], point["cost"][default]
    budgets = []
    for name, f in BUDGET_FACTORS:
        i = point["picks"][name]
        budgets.append({"budget": name, "factor": f, "error_budget": clean(float(f * e0)), "cheapest": brief(i),
                        "speedup_vs_default": clean(float(c0 / point["cost"][i])) if i is not None else None})
    s = clean(float(point["speedup"])) if rows[default]["qualified"] else None   # defaults stable in every seed
    speeds = np.array([v for v in boot["speedup"] if np.isfinite(v)]) if s is not None else np.zeros(0)
    interval = [float(np.percentile(speeds, 5)), float(np.percentile(speeds, 95))] if len(speeds) else None
    p_goal = float(np.mean(speeds >= GOAL_SPEEDUP)) if len(speeds) else None
    front = frame[frame["front"]].sort_values("wall_per_sim_s")
    excluded = [{"setting": r["setting"], "stable_seeds": int(r["stable_seeds"]), "seeds": n_seeds}
                for r in rows if not r["qualified"] and r["group"] != "reference"]
    scene = extra.get("scene", "?")
    if s is None or budgets[0]["cheapest"] is None:
        text = (f"{scene}: no verdict: the defaults ({rows[default]['setting']}) are stable in "
                f"{rows[default]['stable_seeds']} of {n_seeds} seeds with error {clean(float(e0))} (a verdict needs "
                "every seed and a measurable error).")
    else:
        pick = budgets[0]["cheapest"]
        text = (f"{scene}: at the defaults' own error {e0:.3f} ({rows[default]['setting']}, "
                f"{c0 * 1e3:.3g} ms per simulated second), ")
        if pick["setting"] == rows[default]["setting"]:
            text += "no setting is cheaper than the defaults at an equal or lower error: 1x"
        else:
            text += (f"the cheapest setting is {pick['setting']} (error {pick['error']:.3f}, "
                     f"{pick['wall_per_sim_s'] * 1e3:.3g} ms per simulated second): {s:.2f}x less wall time per "
                     f"simulated second")
        if interval:
            text += (f" (5-95% over {len(speeds)} resamples of {n_seeds} seeds: {interval[0]:.2f}-{interval[1]:.2f}x; "
                     f">= {GOAL_SPEEDUP:g}x in {100 * p_goal:.0f}%)")
        text += f"; seed-noise floor of the error {floor:.3f}." if math.isfinite(floor) else "."
    within = max(e0, floor) if math.isfinite(floor) else e0
    j = cheapest(point["error"], point["cost"], frame["qualified"].to_numpy(bool), within) if s is not None else None
    noise = {"error_budget": clean(float(within)), "cheapest": brief(j),
             "speedup_vs_default": clean(float(c0 / point["cost"][j])) if j is not None else None}
    if j is not None and within > e0:
        text += (f" Within the noise floor the cheapest is {rows[j]['setting']} (error {point['error'][j]:.3f}): "
                 f"{noise['speedup_vs_default']:.2f}x.")
    return {"within_noise": noise, **extra, "metric": "error = mean relative L2 of the seed-mean cover, cloudy volume and mean LWP series "
                               "against the reference's; cost = solver wall time per simulated second",
            "default": brief(default), "budgets": budgets, "speedup_at_default_error": s,
            "speedup_interval": interval, "p_speedup_at_least_goal": p_goal, "goal_speedup": GOAL_SPEEDUP,
            "front": [brief(int(i)) for i in front.index], "excluded": excluded, "noise_floor": clean(floor),
            "seeds": n_seeds, "replicates": len(boot["speedup"]), "verdict": text}


def _truthy(value) -> bool:         # a CSV's True / "True" / 1; NaN is not
    return (value.strip().lower() in ("true", "1", "yes") if isinstance(value, str)
            else bool(value) and not (isinstance(value, float) and math.isnan(value)))
