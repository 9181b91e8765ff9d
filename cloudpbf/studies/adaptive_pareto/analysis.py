"""The adaptive-pareto study's analysis: each run's signature (time series and final profile), errors of the
seed means against the reference, the uniform front, speed-ups at equal error with their resampled intervals,
and the verdict (cloudpbf.studies.adaptive_pareto).  Times are ms per step, spacings m."""
from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpbf import runs
from cloudpbf.pareto import pareto_front
from cloudpbf.statistics import relative_l2
from cloudpbf.studies.adaptive_pareto.design import (BOOTSTRAP_REPLICATES, DEFAULT_MAX_LEVEL, GOAL_SPEEDUP,
                                                  MIN_STABLE_SEEDS, SCENES, SERIES, Config)
from cloudpbf.studies.plans import scene_file_suffix


def _relative_l2(values, reference) -> float:
    """The relative L2 error over the samples finite in both (statistics.relative_l2)."""
    return relative_l2(values, reference, skip_nonfinite=True)


def signature(result: runs.RunResult) -> dict | None:
    """Time series (on the snapshot times) and the final cloud-fraction profile of one run."""
    stats, prof = result.stats(), result.profiles()
    if not result.stable or not len(stats):
        return None
    sig = {"time": stats["time_s"].to_numpy(float)}
    for key, column in SERIES:
        sig[key] = stats[column].to_numpy(float) if column in stats else np.full(len(stats), np.nan)
    if len(prof):
        last = prof[prof["time_s"] == prof["time_s"].max()] if "time_s" in prof else prof
        final = last.groupby("z", sort=True)["cloud_fraction"].mean()
        sig["z"], sig["profile"] = final.index.to_numpy(float), final.to_numpy(float)
    return sig


def aligned_signatures(sigs: list[dict | None]) -> dict | None:
    """The signatures (None ones left out) on the first one's times and heights, one row per signature:
    {"time", "cover": (n, T), ..., and "z", "profile": (n, Z) where every one has a profile}; None without any."""
    sigs = [s for s in sigs if s is not None]
    if not sigs:
        return None
    t = sigs[0]["time"]
    out = {"time": t}
    for key, _ in SERIES:
        out[key] = np.array([_interp_nan(t, s["time"], s[key]) for s in sigs])
    if all("z" in s for s in sigs):
        z = sigs[0]["z"]
        out["z"] = z
        out["profile"] = np.array([np.interp(z, s["z"], s["profile"]) for s in sigs])
    return out


def mean_of_rows(aligned: dict, rows=slice(None)) -> dict:
    """Seed mean of the `rows` of :func:`aligned_signatures`; base/top averaged where defined."""
    out = {"time": aligned["time"]}
    with warnings.catch_warnings():   # a time without cloud in any seed: NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        for key, _ in SERIES:
            out[key] = np.nanmean(aligned[key][rows], axis=0)
    if "z" in aligned:
        out["z"], out["profile"] = aligned["z"], aligned["profile"][rows].mean(axis=0)
    return out


def mean_signature(sigs: list[dict]) -> dict | None:
    """Seed mean of signatures (on the first one's times); base/top averaged where defined."""
    aligned = aligned_signatures(sigs)
    return None if aligned is None else mean_of_rows(aligned)


def _interp_nan(t, ts, values):
    """Linear interpolation that keeps NaN (no cloud) where the nearest sample is NaN."""
    idx = np.clip(np.searchsorted(ts, t), 0, len(ts) - 1)
    out = np.interp(t, ts, np.nan_to_num(values))
    out[~np.isfinite(values[idx])] = np.nan
    return out


def errors(sig: dict | None, ref: dict | None) -> dict:
    keys = [k for k, _ in SERIES] + ["profile"]
    if sig is None or ref is None:
        return {f"e_{k}": math.nan for k in keys} | {"error": math.nan}
    out = {}
    for key, _ in SERIES:
        out[f"e_{key}"] = _relative_l2(_interp_nan(ref["time"], sig["time"], sig[key]), ref[key])
    out["e_profile"] = (_relative_l2(np.interp(ref["z"], sig["z"], sig["profile"]), ref["profile"])
                        if "z" in sig and "z" in ref else math.nan)
    out["error"] = float(np.mean([out["e_cover"], out["e_volume"], out["e_lwp"]]))
    return out


def series_frame(keys: list[tuple[str, int]], sigs: list[dict | None]) -> pd.DataFrame:
    """The runs' signatures as one long table (``adaptive_pareto_series.csv``): config, seed, series (cover,
    volume, lwp, base, top: over time_s; profile: over z), coordinate (s or m) and value; none for a run
    without a signature (unstable, or no snapshot).  :func:`signatures_from_series` reads it back, so that
    ``--from-data`` can redo every error and the seed resampling without the runs."""
    frames = []
    for (config, seed), sig in zip(keys, sigs):
        if sig is None:
            continue
        parts = [(key, sig["time"], sig[key]) for key, _ in SERIES]
        if "z" in sig:
            parts.append(("profile", sig["z"], sig["profile"]))
        for key, x, v in parts:
            frames.append(pd.DataFrame({"config": config, "seed": int(seed), "series": key,
                                        "coordinate": np.asarray(x, float), "value": np.asarray(v, float)}))
    columns = ["config", "seed", "series", "coordinate", "value"]
    return pd.concat(frames, ignore_index=True)[columns] if frames else pd.DataFrame(columns=columns)


def signatures_from_series(frame: pd.DataFrame) -> dict[tuple[str, int], dict]:
    """(config, seed) -> signature, from :func:`series_frame`'s table (the inverse of that function); ValueError
    naming the missing columns of a table that is not one."""
    missing = [c for c in ("config", "seed", "series", "coordinate", "value") if c not in frame.columns]
    if missing:
        raise ValueError(f"missing column(s) {', '.join(missing)}")
    out = {}
    for (config, seed), run in frame.groupby(["config", "seed"], sort=False):
        by = {k: g.sort_values("coordinate") for k, g in run.groupby("series", sort=False)}
        if "cover" not in by:
            continue
        sig = {"time": by["cover"]["coordinate"].to_numpy(float)}
        for key, _ in SERIES:
            sig[key] = (by[key]["value"].to_numpy(float) if key in by else np.full(len(sig["time"]), np.nan))
        if "profile" in by:
            sig["z"], sig["profile"] = by["profile"]["coordinate"].to_numpy(float), by["profile"]["value"].to_numpy(float)
        out[(str(config), int(seed))] = sig
    return out


def seed_groups(per_run: pd.DataFrame, sigs: dict[tuple[str, int], dict]) -> dict[str, dict[int, tuple]]:
    """config -> {seed: (signature or None, ms per step)} from the per-run rows and the runs' signatures; an
    unstable run has no signature (it enters no mean)."""
    out: dict[str, dict[int, tuple]] = {}
    for row in per_run.itertuples():
        stable = _truthy(row.stable)
        key = (str(row.config), int(row.seed))
        out.setdefault(str(row.config), {})[int(row.seed)] = (sigs.get(key) if stable else None,
                                                              float(row.ms_per_step) if stable else math.nan)
    return out


def _ms_per_step(result: runs.RunResult, steps: int) -> float:
    return 1e3 * float(result.step_wall_s) / steps if result.stable and steps else math.nan


def _pbf_ms(result: runs.RunResult) -> float:
    t = result.timings()
    return t["pbf"]["total_ms"] / t["pbf"]["count"] if "pbf" in t and t["pbf"]["count"] else math.nan


def _mean_particles(result: runs.RunResult) -> float:
    stats = result.stats()
    if "n_particles" in stats and len(stats):
        return float(stats["n_particles"].mean())
    return float(result.max_particles)


def uniform_front(uniform: pd.DataFrame) -> pd.DataFrame:
    """The uniform configurations no other uniform one beats in both ms/step and error, by error."""
    return pareto_front(uniform, "ms_per_step", "error").sort_values("error")


def _loglog_within(x: float, xs, ys) -> float:
    """y at `x`, interpolated in log x and log y between the points (xs, ys); NaN with fewer than two points or
    outside their range of x."""
    if len(xs) < 2 or not np.isfinite(x) or x <= 0:
        return math.nan
    lx, ly = np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float))
    if not lx.min() <= math.log(x) <= lx.max():
        return math.nan
    order = np.argsort(lx)
    return float(np.exp(np.interp(math.log(x), lx[order], ly[order])))


def time_at_error(front: pd.DataFrame, error: float) -> float:
    """ms/step of the uniform front at `error`, log-log interpolated; NaN outside the front's error range."""
    return _loglog_within(error, front["error"].to_numpy(float), front["ms_per_step"].to_numpy(float))


def pbf_cost_at_count(uniform: pd.DataFrame, particles: float) -> float:
    """PBF ms per particle of uniform runs at a particle count, interpolated in log(count)."""
    u = uniform.dropna(subset=["pbf_ms_per_particle", "particles"]).sort_values("particles")
    if len(u) < 2:
        return math.nan
    return float(np.interp(math.log(particles), np.log(u["particles"].to_numpy(float)),
                           u["pbf_ms_per_particle"].to_numpy(float)))


def uniform_time_at_count(uniform: pd.DataFrame, particles: float) -> float:
    """ms/step of a uniform run with `particles` particles, log-log interpolated between the uniform runs; NaN
    outside their range of counts."""
    u = uniform.dropna(subset=["ms_per_step", "particles"])
    return _loglog_within(particles, u["particles"].to_numpy(float), u["ms_per_step"].to_numpy(float))


def speedup_factors(t_at_error: float, t_at_count: float, ms_per_step: float) -> dict:
    """A variant's speed-up at equal error split in two factors whose product it is::

        speedup = t_u(e) / t_a = [t_u(e) / t_u(N_a)] * [t_u(N_a) / t_a]
                =  speedup_from_particles  /  step_cost_ratio

    with t_u(e) the uniform front's time at the variant's error, t_u(N_a) a uniform run's time at the variant's
    mean particle count and t_a the variant's own: what placing the particles adaptively buys (the speed-up if
    an adaptive particle-step cost what a uniform one does), and what the adaptive step costs beyond a
    uniform step of its size (neighbour lists over mixed levels, splitting, merging, the smoothing limiter)."""
    ok = np.isfinite(t_at_count) and t_at_count > 0
    return {"uniform_ms_at_equal_particles": _none_if_nan(t_at_count),
            "speedup_from_particles": _none_if_nan(t_at_error / t_at_count) if ok else None,
            "step_cost_ratio": _none_if_nan(ms_per_step / t_at_count) if ok else None}


def bootstrap_speedups(groups: dict[str, dict[int, tuple]], kinds: dict[str, str], qualified: set[str],
                       replicates: int = BOOTSTRAP_REPLICATES, seed: int = 0) -> dict:
    """Each qualifying adaptive variant's speed-up at equal error over `replicates` resamples of the seeds.

    A resample draws the study's seeds with replacement, one draw for all configurations (every configuration
    ran the same seeds, so they stay paired), and repeats the whole analysis on it: the reference's seed mean,
    each qualifying configuration's seed mean, its error and ms per step, the uniform front and the speed-ups.
    The spread of a variant's speed-up over the resamples is what the finite number of seeds leaves unknown,
    the reference's seeds included; picking the best of many variants on the same seeds is not corrected for
    (``best_share`` says how often each one wins).

    Returns ``{"speedups": {config: array of speed-ups, NaN where the variant's error is outside the front},
    "best": array of the best variant's name per resample ("" where none is scored), "replicates": n}``."""
    rng = np.random.default_rng(seed)
    seeds = sorted({s for runs_ in groups.values() for s in runs_})
    ref_name = next((c for c, k in kinds.items() if k == "reference"), None)
    uniform = [c for c in groups if kinds.get(c) == "uniform" and c in qualified]
    adaptive = [c for c in groups if kinds.get(c) == "adaptive" and c in qualified]
    speedups = {c: np.full(replicates, np.nan) for c in adaptive}
    best = np.full(replicates, "", dtype=object)
    if ref_name is None or not seeds or not adaptive:
        return {"speedups": speedups, "best": best, "replicates": int(replicates)}

    # each configuration's runs aligned once (as mean_signature aligns them), so that a resample's seed mean is a
    # mean over rows
    aligned = {}
    for config in [ref_name] + uniform + adaptive:
        runs_ = groups[config]
        order = sorted(runs_)
        stable = [s for s in order if runs_[s][0] is not None]
        aligned[config] = ({s: i for i, s in enumerate(order)}, np.array([runs_[s][1] for s in order], float),
                           {s: i for i, s in enumerate(stable)}, aligned_signatures([runs_[s][0] for s in stable]))

    def resampled(config, draw):
        index, ms, row_of, stacks = aligned[config]
        picked = [index[s] for s in draw if s in index]
        rows = [row_of[s] for s in draw if s in row_of]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean_ms = float(np.nanmean(ms[picked])) if picked else math.nan
        return (mean_of_rows(stacks, rows) if rows else None), mean_ms

    for b in range(replicates):
        draw = rng.choice(seeds, size=len(seeds), replace=True)
        reference, _ = resampled(ref_name, draw)
        rows = {}
        for config in uniform + adaptive:
            sig, ms = resampled(config, draw)
            rows[config] = (errors(sig, reference)["error"], ms)
        u = pd.DataFrame([{"config": c, "error": rows[c][0], "ms_per_step": rows[c][1]} for c in uniform])
        u = u[np.isfinite(u["error"]) & np.isfinite(u["ms_per_step"])] if len(u) else u
        front = uniform_front(u) if len(u) else u
        top, top_s = "", -math.inf
        for config in adaptive:
            error, ms = rows[config]
            t = time_at_error(front, error)
            s = t / ms if np.isfinite(t) and np.isfinite(ms) and ms > 0 else math.nan
            speedups[config][b] = s
            if np.isfinite(s) and s > top_s:
                top, top_s = config, s
        best[b] = top
    return {"speedups": speedups, "best": best, "replicates": int(replicates)}


def speedup_interval(samples: np.ndarray, goal: float = GOAL_SPEEDUP) -> dict:
    """The 5th and 95th percentiles of a variant's resampled speed-ups (over the resamples where it has one),
    the share of resamples where it has one, and the share where it reaches `goal`."""
    samples = np.asarray(samples, float)
    ok = np.isfinite(samples)
    if not ok.any():
        return {"speedup_interval": None, "speedup_defined_share": 0.0, "p_speedup_at_least_goal": 0.0}
    lo, hi = np.percentile(samples[ok], [5.0, 95.0])
    return {"speedup_interval": [float(lo), float(hi)], "speedup_defined_share": float(ok.mean()),
            "p_speedup_at_least_goal": float(np.mean(ok & (samples >= goal)))}


def analyse(entries: list[tuple[Config, int, runs.RunSpec]], results: list[runs.RunResult], scene_name: str,
            device: str, commit: str, min_stable_seeds: int | None = MIN_STABLE_SEEDS,
            replicates: int = BOOTSTRAP_REPLICATES, sigs: list[dict | None] | None = None
            ) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """(per-run rows, per-configuration rows, verdict); `replicates` resamples of the seeds give each variant's
    speed-up interval (0: none).  `sigs`: the results' signatures, where the caller has them already."""
    sigs = [signature(r) for r in results] if sigs is None else sigs
    by_config: dict[Config, list[int]] = {}
    for i, (config, _, _) in enumerate(entries):
        by_config.setdefault(config, []).append(i)
    ref_config = next(c for c in by_config if c.kind == "reference")
    reference = mean_signature([sigs[i] for i in by_config[ref_config]])

    run_rows, config_rows = [], []
    for config, idx in by_config.items():
        mean_sig = mean_signature([sigs[i] for i in idx])
        err = errors(mean_sig, reference)
        per_seed = [errors(sigs[i], reference)["error"] for i in idx]
        ms = [_ms_per_step(results[i], entries[i][2].total_steps) for i in idx]
        pbf = [_pbf_ms(results[i]) for i in idx]
        parts = [_mean_particles(results[i]) for i in idx]
        stable = [bool(results[i].stable) for i in idx]
        with np.errstate(all="ignore"):
            row = {"config": config.name, "kind": config.kind, "criterion": config.criterion,
                   "spacing_m": config.spacing_m, "max_level": config.max_level,
                   "threshold_scale": config.threshold_scale, "adapt_every": config.adapt_every,
                   "pair_kernel": config.pair_kernel, "seeds": len(idx), "stable_seeds": int(sum(stable)),
                   "particles": float(np.nanmean(parts)), "ms_per_step": float(np.nanmean(ms)),
                   "ms_per_step_spread": float(np.nanstd(ms)), "pbf_ms": float(np.nanmean(pbf)),
                   **err, "error_seed_spread": (float(np.nanstd(per_seed)) if np.isfinite(per_seed).sum() >= 2
                                                else math.nan)}
        row["pbf_ms_per_particle"] = row["pbf_ms"] / row["particles"] if row["particles"] else math.nan
        config_rows.append(row)
        for i, e_seed in zip(idx, per_seed):
            res = results[i]
            run_rows.append({"config": config.name, "kind": config.kind, "criterion": config.criterion,
                             "spacing_m": config.spacing_m, "max_level": config.max_level,
                             "threshold_scale": config.threshold_scale, "adapt_every": config.adapt_every,
                             "pair_kernel": config.pair_kernel, "seed": entries[i][1], "stable": bool(res.stable),
                             "reason": res.reason, "particles": _mean_particles(res),
                             "max_particles": res.max_particles,
                             "ms_per_step": _ms_per_step(res, entries[i][2].total_steps), "pbf_ms": _pbf_ms(res),
                             "error_this_seed": e_seed, **{f"config_{k}": v for k, v in err.items()},
                             "device": res.device, "commit": commit, "run_dir": str(res.path)})
    per_run, per_config = pd.DataFrame(run_rows), pd.DataFrame(config_rows)
    groups = seed_groups(per_run, {(config.name, seed): sigs[i] for i, (config, seed, _) in enumerate(entries)})
    verdict = build_verdict(per_run, per_config, scene_name, device, commit, min_stable_seeds, groups=groups,
                            replicates=replicates)
    add_verdict_columns(per_config, verdict)
    return per_run, per_config, verdict


def add_verdict_columns(per_config: pd.DataFrame, verdict: dict) -> None:
    """Each adaptive configuration's speed-up (and, where the seeds were resampled, its 5-95% interval) as
    columns of the per-configuration table; pops the verdict's private ``_speedups``."""
    per_config["speedup_at_equal_error"] = per_config["config"].map(verdict.pop("_speedups"))
    intervals = {v["name"]: v.get("speedup_interval") for v in verdict["variants"] + verdict["excluded"]}
    for k, column in enumerate(("speedup_p05", "speedup_p95")):
        per_config[column] = per_config["config"].map(
            lambda c: (intervals.get(c) or [math.nan, math.nan])[k])


def required_stable_seeds(per_config: pd.DataFrame, min_stable_seeds: int | None = MIN_STABLE_SEEDS) -> int:
    """The stable seeds a configuration needs: `min_stable_seeds`, or (None) every seed the study ran."""
    if min_stable_seeds is not None:
        if int(min_stable_seeds) < 1:
            raise ValueError(f"min_stable_seeds = {min_stable_seeds}: at least 1")
        return int(min_stable_seeds)
    return int(per_config["seeds"].max()) if len(per_config) else 1


def _qualification(per_run: pd.DataFrame | None, per_config: pd.DataFrame, required: int) -> dict[str, list[str]]:
    """config name -> the reasons it is left out of the verdict (empty: it qualifies)."""
    out = {}
    for row in per_config.itertuples():
        reasons = []
        stable, seeds = int(row.stable_seeds), int(row.seeds)
        if stable < required:
            reasons.append(f"stable in {stable} of {seeds} seeds (the verdict needs {required})")
            if per_run is not None and "stable" in per_run:
                bad = per_run[(per_run["config"] == row.config) & ~per_run["stable"].map(_truthy)]
                for r in bad.itertuples():
                    why = getattr(r, "reason", None)
                    why = why if isinstance(why, str) and why else "unstable"
                    reasons.append(f"seed {int(r.seed)}: {why}")
        elif not (np.isfinite(row.error) and np.isfinite(row.ms_per_step)):
            reasons.append("no measurable error or time (no cloud in the seed mean, or no timed step)")
        out[row.config] = reasons
    return out


def _truthy(value) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes")
    return bool(value) and not (isinstance(value, float) and math.isnan(value))


def _none_if_nan(x):
    return None if x is None or not np.isfinite(x) else float(x)


def build_verdict(per_run: pd.DataFrame | None, per_config: pd.DataFrame, scene_name: str, device: str, commit: str,
                  min_stable_seeds: int | None = MIN_STABLE_SEEDS, groups: dict | None = None,
                  replicates: int = BOOTSTRAP_REPLICATES) -> dict:
    """The verdict from the per-configuration rows (``adaptive_pareto_configs.csv``) and the per-run rows
    (``adaptive_pareto.csv``: failure reasons and the reference seeds' errors, for the noise floor).

    Only configurations stable in at least :func:`required_stable_seeds` seeds, with a finite error and time,
    enter the uniform front and compete for ``best``; the others are listed under ``excluded``.  With `groups`
    (:func:`seed_groups`: every run's signature and time) and `replicates` > 0, the seeds are resampled
    (:func:`bootstrap_speedups`) and each qualifying variant gets its speed-up's 5-95% interval, the share of
    resamples where it reaches :data:`GOAL_SPEEDUP` and the share where it is the best variant.  The result has
    a private ``_speedups`` (config -> speed-up of every adaptive configuration with an error, for the CSV)."""
    required = required_stable_seeds(per_config, min_stable_seeds)
    reasons = _qualification(per_run, per_config, required)
    ok = per_config["config"].map(lambda c: not reasons[c])
    uniform = per_config[(per_config.kind == "uniform") & ok]
    front = uniform_front(uniform) if len(uniform) else uniform
    variants, excluded, speedups = [], [], {}
    for row in per_config[per_config.kind != "reference"].itertuples():
        pair_kernel = getattr(row, "pair_kernel", "")    # "" (read back as NaN): the scene's own, eq. 19
        entry = {"name": row.config, "criterion": row.criterion if isinstance(row.criterion, str) else "",
                 "spacing_m": float(row.spacing_m),
                 # CSVs written before these columns existed: every variant then had max_level 3, thresholds x1
                 "max_level": int(getattr(row, "max_level", DEFAULT_MAX_LEVEL if row.kind == "adaptive" else 0)),
                 "threshold_scale": float(getattr(row, "threshold_scale", 1.0)),
                 "adapt_every": int(getattr(row, "adapt_every", 0) or 0),   # 0: the scene's own (older CSVs)
                 "pair_kernel": pair_kernel if isinstance(pair_kernel, str) else "",
                 "stable_seeds": int(row.stable_seeds), "seeds": int(row.seeds),
                 "error": _none_if_nan(row.error), "ms_per_step": _none_if_nan(row.ms_per_step)}
        if row.kind == "adaptive":
            t_uniform = time_at_error(front, row.error)
            speedup = t_uniform / row.ms_per_step if np.isfinite(t_uniform) else math.nan
            speedups[row.config] = _none_if_nan(speedup)
            base = pbf_cost_at_count(uniform, row.particles) if row.particles else math.nan
            entry |= {"speedup_at_equal_error": _none_if_nan(speedup),
                      "uniform_ms_at_equal_error": _none_if_nan(t_uniform),
                      # one stable seed has no spread (older CSVs wrote 0 for it)
                      "error_seed_spread": _none_if_nan(row.error_seed_spread) if row.stable_seeds >= 2 else None,
                      "particles": float(row.particles),
                      "cost_ratio_per_particle": _none_if_nan(row.pbf_ms_per_particle / base)
                      if np.isfinite(base) and base else None,
                      **speedup_factors(t_uniform, uniform_time_at_count(uniform, row.particles), row.ms_per_step)}
        if reasons[row.config]:
            excluded.append({"name": row.config, "kind": row.kind, **{k: v for k, v in entry.items() if k != "name"},
                             "reasons": reasons[row.config]})
        elif row.kind == "adaptive":
            variants.append(entry)
    resampling = None
    if groups and replicates > 0:
        kinds = dict(zip(per_config["config"].astype(str), per_config["kind"].astype(str)))
        boot = bootstrap_speedups(groups, kinds, {c for c, why in reasons.items() if not why}, int(replicates))
        for entry in variants:
            entry |= speedup_interval(boot["speedups"][entry["name"]])
            entry["best_share"] = float(np.mean(boot["best"] == entry["name"]))
        resampling = {"replicates": boot["replicates"], "seeds": int(per_config["seeds"].max()),
                      "goal_speedup": GOAL_SPEEDUP, "no_best_share": float(np.mean(boot["best"] == ""))}
    costs = [v["cost_ratio_per_particle"] for v in variants if v["cost_ratio_per_particle"] is not None]
    verdict = {"scene": scene_name, "cost_ratio_per_particle": float(np.median(costs)) if costs else None,
               "min_stable_seeds": required, "variants": variants, "excluded": excluded,
               "noise_floor": _noise_floor(per_run),
               "reference_stable_seeds": _reference_seeds(per_config),
               "uniform_front": front[["config", "error", "ms_per_step"]].to_dict("records"),
               "resampling": resampling, "device": device, "commit": commit}
    verdict["best"], verdict["verdict"] = _verdict_text(variants, excluded, front, verdict["noise_floor"],
                                                        scene_name, required, resampling)
    verdict["_speedups"] = speedups
    return verdict


def _noise_floor(per_run: pd.DataFrame | None) -> float:
    """Mean error of a single reference seed against the reference mean (NaN without reference rows)."""
    if per_run is None or "error_this_seed" not in per_run:
        return math.nan
    ref = per_run.loc[per_run["kind"] == "reference", "error_this_seed"].to_numpy(float)
    return float(np.nanmean(ref)) if np.isfinite(ref).any() else math.nan


def _reference_seeds(per_config: pd.DataFrame) -> str | None:
    ref = per_config[per_config.kind == "reference"]
    return f"{int(ref['stable_seeds'].iloc[0])} of {int(ref['seeds'].iloc[0])}" if len(ref) else None


def _verdict_text(variants: list[dict], excluded: list[dict], front: pd.DataFrame, noise_floor: float,
                  scene_name: str, required: int, resampling: dict | None = None):
    left_out = [e for e in excluded if e["kind"] == "adaptive"]
    left_uniform = [e for e in excluded if e["kind"] == "uniform"]
    note = ""
    if left_out or left_uniform:
        note = " Left out (stable in fewer than {} seeds, or no error): {}.".format(
            required, ", ".join(f"{e['name']} ({e['stable_seeds']}/{e['seeds']} stable)"
                                for e in left_uniform + left_out))
    scored = [v for v in variants if v["speedup_at_equal_error"] is not None]
    if scored:
        best = max(scored, key=lambda v: v["speedup_at_equal_error"])
        s = best["speedup_at_equal_error"]
        word = "faster" if s >= 1 else "slower"
        text = (f"{scene_name}: the best adaptive variant, {best['name']} (stable in {best['stable_seeds']} of "
                f"{best['seeds']} seeds), is {s if s >= 1 else 1 / s:.2f}x {word} than uniform particles at its "
                f"error {best['error']:.3f} (seed-noise floor {noise_floor:.3f}).")
        if best.get("speedup_from_particles") is not None:
            text += (f" Its {best['particles']:,.0f} particles would give {best['speedup_from_particles']:.2f}x if "
                     f"they cost what uniform particles do (a uniform run of that size takes "
                     f"{best['uniform_ms_at_equal_particles']:.2f} ms per step); its step costs "
                     f"{best['step_cost_ratio']:.2f}x that.")
        if resampling and best.get("speedup_interval"):
            lo, hi = best["speedup_interval"]
            text += (f" Over {resampling['replicates']} resamples of its {resampling['seeds']} seeds the speed-up "
                     f"lies between {lo:.2f}x and {hi:.2f}x (5-95%), reaches {resampling['goal_speedup']:g}x in "
                     f"{100 * best['p_speedup_at_least_goal']:.0f}% of them, and this variant is the best in "
                     f"{100 * best['best_share']:.0f}%.")
        return best, text + note
    if not variants:
        what = "adaptive variant" if left_out else "adaptive run"
        return None, (f"{scene_name}: no best variant: no {what} is stable in at least {required} seeds with a "
                      f"measurable error." + note)
    if len(front) < 2:
        return None, (f"{scene_name}: no best variant: fewer than two uniform configurations are stable in at "
                      f"least {required} seeds with a measurable error, so there is no uniform front to compare "
                      f"with." + note)
    lo, hi = front["error"].min(), front["error"].max()
    errs = ", ".join(f"{v['name']} {v['error']:.3f}" for v in variants)
    return None, (f"{scene_name}: no best variant: no adaptive variant lies within the uniform front's error range "
                  f"[{lo:.3f}, {hi:.3f}] (adaptive errors: {errs}; seed-noise floor {noise_floor:.3f})." + note)


def rebuild_verdict(data_dir, scene_name: str = "growing", min_stable_seeds: int | None = MIN_STABLE_SEEDS,
                    write: bool = True, replicates: int = BOOTSTRAP_REPLICATES) -> dict:
    """The verdict again from DATA's ``adaptive_pareto[_SCENE].csv`` and ``adaptive_pareto_configs[_SCENE].csv``,
    without running anything; device and commit stay those of the verdict already there (else the runs' CSV).
    Where ``adaptive_pareto_series[_SCENE].csv`` is there too (studies from 2026-11-26 on), the seeds are
    resampled as in the study.  Writes ``adaptive_verdict[_SCENE].json`` (and the configurations' speed-up
    columns) unless `write` is False."""
    if scene_name not in SCENES:
        raise ValueError(f"scene = {scene_name!r}: allowed {', '.join(SCENES)}")
    data_dir = Path(data_dir)
    suffix = scene_file_suffix(scene_name)
    runs_path = data_dir / f"adaptive_pareto{suffix}.csv"
    configs_path = data_dir / f"adaptive_pareto_configs{suffix}.csv"
    for path in (runs_path, configs_path):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (run `cloudpbf adaptive-pareto --scene {scene_name}` first)")
    per_run, per_config = _read_data_csv(runs_path), _read_data_csv(configs_path)
    verdict_path = data_dir / f"adaptive_verdict{suffix}.json"
    old = json.loads(verdict_path.read_text()) if verdict_path.is_file() else {}
    device = old.get("device") or _first(per_run, "device") or "unknown"
    commit = old.get("commit") or _first(per_run, "commit") or "unknown"
    series_path = data_dir / f"adaptive_pareto_series{suffix}.csv"
    groups = None
    if series_path.is_file():
        try:
            sigs = signatures_from_series(_read_data_csv(series_path))
        except ValueError as exc:
            raise ValueError(f"{series_path}: {exc}") from None
        lacking = [f"{r.config} seed {int(r.seed)}" for r in per_run.itertuples()
                   if _truthy(r.stable) and (str(r.config), int(r.seed)) not in sigs]
        if lacking:
            raise ValueError(f"{series_path}: no series for {len(lacking)} stable run(s) of {runs_path.name} "
                             f"({', '.join(lacking[:3])}{', ...' if len(lacking) > 3 else ''}); it belongs to "
                             "another study, or was cut short (delete it to rebuild the verdict without resampling)")
        groups = seed_groups(per_run, sigs)
    verdict = build_verdict(per_run, per_config, scene_name, device, commit, min_stable_seeds, groups=groups,
                            replicates=replicates)
    add_verdict_columns(per_config, verdict)
    if write:
        runs.atomic_write_json(verdict_path, verdict)
        runs.write_csv(per_config, configs_path)
    return verdict


def _read_data_csv(path: Path) -> pd.DataFrame:
    """One of the study's CSVs; ValueError naming the file when it cannot be parsed."""
    try:
        return pd.read_csv(path, float_precision="round_trip")
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{path}: not a readable CSV ({why})") from None


def _first(frame: pd.DataFrame, column: str) -> str | None:
    values = frame[column].dropna() if column in frame else []
    return str(values.iloc[0]) if len(values) else None
