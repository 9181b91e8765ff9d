"""Sections of step timings: Table 1 against the paper, the per-phase cost, scaling, the benchmark history and
the CPU peer."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from . import plots
from .common import (PHASES, Inputs, Section, _command, _measured_total, _missing, _paper_table, _provenance, _scale_of,
                     _table, _variant)

from bench.studies.table1 import MATCH_TOLERANCE  # noqa: E402  (a speed-up against the paper needs matching counts)

PAPER_NEEDS_GPU = ("The comparison with the paper's Table 1 needs the gpu scale (the paper's 500k-930k particles: "
                   "cloudpbf table1 --scale gpu); at this scale the rows are throughput only.")


def step_time_text(row: dict) -> str:
    """'3.83 ms per step (median over 495 timed steps, 5-95%: 3.71-4.02)' where the row carries the per-step
    spread (step_ms_median, step_ms_p05, step_ms_p95, timed_steps), else the mean over the timed steps and a
    plain note that the spread was not recorded."""
    med, lo, hi = (pd.to_numeric(row.get(k), errors="coerce") for k in ("step_ms_median", "step_ms_p05", "step_ms_p95"))
    steps = pd.to_numeric(row.get("timed_steps", row.get("steps")), errors="coerce")
    over = f" over {int(steps)} timed steps" if np.isfinite(steps) else " over the timed steps"
    if np.isfinite(med) and np.isfinite(lo) and np.isfinite(hi):
        return f"{med:.3g} ms per step (median{over}, 5-95%: {lo:.3g}-{hi:.3g})"
    total = pd.to_numeric(row.get("total_ms"), errors="coerce")
    return f"{total:.3g} ms per step (mean{over}; per-step spread not recorded in this data)"


def paper_comparison(measured: pd.DataFrame, env: dict | None) -> pd.DataFrame:
    """One row per Table 1 row: particle counts (ours, the paper's), ms per step, throughput in particle-steps per
    second (ours, the paper's), and ``speedup_vs_paper`` (the paper's ms / ours) only where the counts match
    (gpu scale, within MATCH_TOLERANCE); elsewhere ``throughput_vs_paper`` (gpu scale) or nothing."""
    measured = measured.copy()
    measured["total_ms"] = _measured_total(measured)
    paper = _paper_table().set_index(["example", "mode"])
    scale = _scale_of(env, measured)
    rows = []
    for r in measured.to_dict("records"):
        key = (r["example"], r["mode"])
        n = pd.to_numeric(r.get("max_particles"), errors="coerce")
        t = pd.to_numeric(r.get("total_ms"), errors="coerce")
        n_p = paper["max_particles"].get(key, math.nan) if "max_particles" in paper else math.nan
        t_p = paper["total_ms"].get(key, math.nan)
        p05, p95 = (pd.to_numeric(r.get(k), errors="coerce") for k in ("step_ms_p05", "step_ms_p95"))
        rate = n * 1e3 / t if t and t > 0 else math.nan
        rate_p = n_p * 1e3 / t_p if t_p and t_p > 0 else math.nan
        matched = scale == "gpu" and np.isfinite(n) and np.isfinite(n_p) and abs(n / n_p - 1) <= MATCH_TOLERANCE
        variant = _variant(r)
        rows.append({**r, "row": f"{r['example']} {r['mode']}" + (f" ({variant})" if variant else ""),
                     "variant": variant, "paper_particles": n_p, "paper_ms": t_p, "particle_steps_per_s": rate,
                     "paper_particle_steps_per_s": rate_p, "counts_match": bool(matched),
                     "speedup_vs_paper": t_p / t if matched and t > 0 else math.nan,
                     "speedup_lo": t_p / p95 if matched and p95 > 0 else math.nan,
                     "speedup_hi": t_p / p05 if matched and p05 > 0 else math.nan,
                     "throughput_vs_paper": rate / rate_p if scale == "gpu" and not matched and rate_p > 0
                     else math.nan, "scale": scale})
    return pd.DataFrame(rows)


def _table1(inp: Inputs, sec: Section, env: dict | None) -> None:
    measured, _ = inp.csv("table1")
    if measured is None:
        _missing(sec, "table1.csv", "table1", inp.out)
        return
    rows = paper_comparison(measured, env)
    scale = rows["scale"].iloc[0]
    gpu = scale == "gpu"
    if not gpu:
        sec.add("note", f"Scale '{scale}': {PAPER_NEEDS_GPU}", level="warn")
    elif not rows["counts_match"].all():
        sec.add("note", "Rows whose particle count differs from the paper's by more than "
                        f"{100 * MATCH_TOLERANCE:g}% ({', '.join(rows.loc[~rows['counts_match'], 'row'])}) are "
                        "compared by throughput (particle-steps per second), not as a speed-up.", level="info")
    table = pd.DataFrame({
        "example": rows["example"], "mode": rows["row"].str.split(" ", n=1).str[1], "particles": rows["max_particles"],
        "total ms": rows["total_ms"], "particle-steps/s": rows["particle_steps_per_s"]})
    if gpu:
        table["particles (paper)"] = rows["paper_particles"]
        table["total ms (paper)"] = rows["paper_ms"]
        table["particle-steps/s (paper)"] = rows["paper_particle_steps_per_s"]
        table["speed-up vs paper (same counts)"] = rows["speedup_vs_paper"]
        table["throughput vs paper (other counts)"] = rows["throughput_vs_paper"]
    for p in PHASES:
        if f"{p}_ms" in rows.columns and rows[f"{p}_ms"].notna().any():
            table[f"{p} ms"] = rows[f"{p}_ms"]
    if {"step_ms_median", "step_ms_p05", "step_ms_p95"} <= set(rows.columns):
        table["step ms median [5-95%]"] = [step_time_text(r).split(" (")[0] + f" [{r['step_ms_p05']:.3g}, "
                                           f"{r['step_ms_p95']:.3g}]" for r in rows.to_dict("records")]
    table = table.loc[:, [c for c in table.columns if not table[c].isna().all()]]
    sec.add("table", _table(table), caption=(
        "Milliseconds per step (each phase's time over the timed steps; pbf holds the neighbour search and the "
        "constraint iterations) and throughput = particles (the run's largest count) x steps per second. "
        + ("Beside them the paper's Table 1 (GeForce GTX 780 Ti): a speed-up only where the particle counts match, "
           "else the ratio of throughputs. " if gpu else "")
        + "A row 'adaptive (name)' is the adaptive study's best variant (cloudpbf adaptive-pareto)."))
    paper = _paper_table()
    missing_rows = set(paper["example"] + "/" + paper["mode"]) - set(measured["example"] + "/" + measured["mode"])
    if missing_rows:
        sec.add("note", "rows not measured in this study: " + ", ".join(sorted(missing_rows)), level="missing",
                command=_command("table1", inp.out))
    sec.provenance = _provenance(measured, env=env)


def _phases(inp: Inputs, sec: Section, env: dict | None) -> None:
    measured, _ = inp.csv("table1")
    if measured is None:
        _missing(sec, "table1.csv (per-phase timings)", "table1", inp.out)
        return
    paper = _paper_table()
    sec.add("image", plots.phase_bars(measured, paper), caption=(
        "Stacked ms per step of the Table 1 phases (pbf includes neighbour search and constraint iterations). "
        "Phases a run does not have (splitting and merging without adaptivity) are absent, not zero."))
    shares = measured[["example", "mode"]].copy()
    total = _measured_total(measured)
    for p in PHASES:
        if f"{p}_ms" in measured.columns and measured[f"{p}_ms"].notna().any():
            shares[f"{p} %"] = 100.0 * pd.to_numeric(measured[f"{p}_ms"], errors="coerce") / total
    sec.add("table", _table(shares, "{:.1f}"), caption="share of each phase in the measured step time (%)")
    cost, cost_path = inp.csv("adaptive_cost")
    if cost is None:
        _missing(sec, "adaptive_cost.csv (splitting and merging at ~500k adaptive particles, GPU)", "adaptive_cost",
                 inp.out)
    else:
        cols = [c for c in ("scene", "spacing_m", "mean_particles", "max_particles", "splitting_ms", "merging_ms",
                            "merge_passes_ms", "compaction_ms", "pbf_ms", "split_target_ms", "merge_target_ms",
                            "meets_targets", "device", "commit") if c in cost.columns]
        sec.add("table", _table(cost[cols]), caption=(
            f"Splitting and merging at the size of the targets, from {cost_path.name}: ms per step over the whole "
            "run (merge_passes and compaction are parts of merging; pbf is the same run's constraint solve). "
            "meets_targets is left empty off the GPU or below 400k particles."))
    sec.provenance = _provenance(measured, env=env)


def _scaling(inp: Inputs, sec: Section, env: dict | None) -> None:
    frames = []
    for study, solver, unit, plot in (("pbf_scaling", "particle solver", "particle", plots.pbf_scaling_plot),
                                      ("grid_scaling", "grid baseline", "cell", plots.grid_scaling_plot)):
        frame, path = inp.csv(study)
        frames.append(frame)
        if frame is None:
            _missing(sec, f"{study}.csv ({solver} step time against {unit} count)", study, inp.out)
            continue
        name = "PBF" if study == "pbf_scaling" else solver
        sec.add("image", plot(frame), caption=f"{name} step (log-log) from {path.name}")
        extra = frame.copy()
        if "step_ms" in extra and f"{unit}s" in extra:
            extra[f"ns per {unit}"] = 1e6 * extra["step_ms"] / extra[f"{unit}s"]
        sec.add("table", _table(extra))
    sec.provenance = _provenance(*frames, env=env)


def _benchmark_history(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, path = inp.csv("benchmark_history")
    if df is None:
        _missing(sec, "benchmark_history.csv (the solver's step across commits, from the asv results in "
                      "benchmarks/results)", "benchmark_history", inp.out)
        return
    sec.add("text", "Each point is one commit's median of asv samples (docs/benchmarks.md), error bars its 99% "
                    "interval. A change is flagged when the ratio to the machine's previous recorded commit passes "
                    "the history's factor and the two intervals do not overlap.")
    for machine in sorted(df["machine"].unique()):
        sec.add("image", plots.benchmark_history_plot(df, machine), caption=f"{machine}, from {path.name}")
    changed = df[df["change"].fillna("") != ""]
    if len(changed):
        shown = changed[["machine", "commit", "backend", "scene", "particles", "time_ms", "ratio", "change"]].rename(
            columns={"time_ms": "ms per step", "ratio": "ratio to the previous commit"})
        sec.add("table", _table(shown, float_format="{:.3g}"), caption="changes between consecutive recorded commits")
    else:
        sec.add("note", "no change beyond the factor between consecutive recorded commits", level="ok")


def _peers(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, path = inp.csv("cpu_peer")
    if df is None:
        _missing(sec, "cpu_peer.csv (SPlisHSPlasH's PBF dam break against cloudpbf's: cloudpbf peers)", "peers", inp.out)
        return
    sec.add("text", "SPlisHSPlasH's DamBreakModel with PBF (4 iterations, dt 0.002 s) and cloudpbf's dam break on the "
                    "same box, water cube and spacing, timed alternately in one run; per run the faster repeat of each "
                    "and cloudpbf's ratio to SPlisHSPlasH of the faster repeats and of the means. A shared host's "
                    "speed drifts between runs: compare within a row. Fluid particle-steps per second: more is "
                    "faster.")
    from bench.studies.peers import best_rates
    wide = best_rates(df)
    wide["threads"] = wide["threads"].map(lambda t: "GPU" if int(t) == 0 else str(int(t)))
    commits = ", ".join(sorted(df["commit"].astype(str).unique()))
    sec.add("table", _table(wide, float_format="{:.3g}"), caption=f"from {path.name}, commit {commits}")


