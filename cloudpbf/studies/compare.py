"""Particles against the grid: the same cloud scene run by the particle solver (non-adaptive and
adaptive) and by the grid baseline, over several noise seeds (the seed shifts the ground-heating
pattern, eq. 5, identically in both solvers).

Every run is analysed by the same code (cloudpbf.statistics): particles are deposited on the grid the
grid baseline uses (one cell per non-adaptive particle spacing), so cover, base/top, objects and
budgets are measured alike.  Outputs in OUT/data:

* compare_timeseries.csv: solver, mode, seed, time_s, step, the diagnostics (DIAGNOSTIC_COLUMNS),
  then solver-specific columns (n_particles, density_error_mean, max_speed, ...), device, commit
* compare_profiles.csv: solver, mode, seed, time_s, step, z, cloud_fraction, temperature, vapor,
  cloud, device, commit
* compare_runs.csv: one row per run: solver, mode, seed, stable, reason, step, max_particles,
  cells, step_wall_s, device, commit, run_dir
"""
from __future__ import annotations

import math
from typing import Annotated, Optional

import numpy as np
import pandas as pd
import typer

from cloudpbf.report import glance_plots as gp
from cloudpbf.report import plots
from cloudpbf.report.catalogue import GlanceCard
from cloudpbf.report.common import (Inputs, Section, _mean_sd, _measured_total, _missing, _paper_table, _provenance,
                                 _table, step_time_ratios)
from cloudpbf.report.glance import Card, data_link, missing_card, section_link
from cloudpbf.report.inference import (LEVEL, convergence_orders, describes_no_difference, difference_ci, format_ci,
                                      mean_ci, welch)
from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, click, refusals, scene_arg, study_context)
from cloudpbf.statistics import CLOUD_MEANS, CLOUDY_COVER, DIAGNOSTIC_COLUMNS, PROFILE_COLUMNS, onset_time
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.plans import (ANIMATION_FRAMES, MIN_SEEDS, SOLVER_OF_MODE, compare_specs,  # noqa: F401
                                  scene_pair, SMOKE_CLOUD_BOX)
from cloudpbf.studies.registry import ReportSection, Study, register
from pbf_cuda.scene import Scene

MODES = ("non-adaptive", "adaptive", "grid")
# The energy and heat budget of both solvers (Simulation.stats(), GridSimulation.stats(); docs/physics.md, Budgets).
BUDGET_COLUMNS = ("mass_centre_height", "kinetic_energy", "mean_temperature", "heat_source_total",
                  "heat_latent_total", "heat_adiabatic_total", "heat_smoothing_total", "heat_numerical_total",
                  "heat_relaxation_total", "water_relaxation_total", "water_rain_total")
SOLVER_COLUMNS = ("n_particles", "level_0", "level_1", "level_2", "level_3", "density_error_mean",
                  "density_error_max", "density_excess_mean", "density_deficit_mean", "max_speed", "cfl", "substeps",
                  "divergence_rel", *BUDGET_COLUMNS)


SMOKE_BOX = {**SMOKE_CLOUD_BOX, "particles.spacing": 100.0}
"""The smoke scale's compare box (both modes, level-0 spacing 100 m for the adaptive twin too): the cloud
scene's physics in a 1.2 x 1.6 x 1.2 km box of 2,304 particles, 480 s at dt = 4 s (at 8 s the adaptive
run's refined particles hold a 64% density error, at 4 s about 1%).  Scaled to 3,000
particles in the 3.2 km domain (222 m spacing) no particle run forms a cloud within the smoke run; in
this box the first cloud appears near t = 320 s (measured on the 2-core CPU, docs/harness.md "Scales")."""

def _labelled(frame: pd.DataFrame, mode: str, seed: int, ctx: StudyContext, device: str) -> pd.DataFrame:
    frame = frame.copy()
    for i, (key, value) in enumerate((("solver", SOLVER_OF_MODE[mode]), ("mode", mode), ("seed", seed))):
        frame.insert(i, key, value)
    frame["device"] = device
    frame["commit"] = ctx.commit
    return frame


def run_compare(ctx: StudyContext, scene_name: str = "growing", seeds: int | None = None) -> dict[str, pd.DataFrame]:
    """Run (or read) every mode x seed and write the three compare CSVs."""
    plan = compare_specs(ctx, scene_name, seeds or ctx.scale.seeds)
    results = ctx.run_parallel([spec for _, _, spec in plan], "compare")
    series, profiles, table = [], [], []
    head = ["solver", "mode", "seed", "time_s", "step"]
    for (mode, seed, spec), res in zip(plan, results):
        stats = res.stats()
        if len(stats):
            cols = ["time_s", "step", *DIAGNOSTIC_COLUMNS, *(c for c in SOLVER_COLUMNS if c in stats.columns)]
            series.append(_labelled(stats[cols], mode, seed, ctx, res.device))
        prof = res.profiles()
        if len(prof):
            profiles.append(_labelled(prof[["time_s", "step", *PROFILE_COLUMNS]], mode, seed, ctx, res.device))
        table.append({"solver": spec.solver, "mode": mode, "seed": seed, "stable": res.stable, "reason": res.reason,
                      "step": res.step, "max_particles": res.max_particles, "cells": res.cells,
                      "step_wall_s": res.step_wall_s, "scene": spec.scene.name, "device": res.device,
                      "commit": ctx.commit, "run_dir": str(res.path)})
    out = {
        "compare_timeseries": pd.concat(series, ignore_index=True) if series else pd.DataFrame(columns=head),
        "compare_profiles": pd.concat(profiles, ignore_index=True) if profiles else pd.DataFrame(columns=head),
        "compare_runs": pd.DataFrame(table),
    }
    out["particles_vs_grid"] = particles_vs_grid(out["compare_timeseries"], profiles=out["compare_profiles"],
                                                 scene=plan[0][2].scene)
    for name, frame in out.items():
        runs.write_csv(frame, ctx.data / f"{name}.csv")
    return out


def mixed_layer_lcl(profiles: pd.DataFrame, series: pd.DataFrame, mode: str, scene: Scene) -> pd.Series:
    """time_s -> the lifting condensation level (m) of `mode`'s mixed-layer air: the seed-mean layers below
    half that time's seed-mean cloud base (the sub-cloud layer, clear of the entrainment at its top), their
    mean dry static temperature T + Gamma_d z and total water v + w (equal-mass layers), through
    Scene.lifting_condensation_level.  NaN where there is no cloud base yet."""
    a = scene.atmosphere
    prof = profiles[profiles["mode"] == mode].groupby(["time_s", "z"])[["temperature", "vapor", "cloud"]].mean()
    base = series[series["mode"] == mode].groupby("time_s")["cloud_base"].mean()
    out = {}
    for t, layers in prof.groupby(level="time_s"):
        z = layers.index.get_level_values("z").to_numpy(float)
        b = base.get(t, float("nan"))
        below = z < 0.5 * b if b == b else np.zeros(len(z), bool)
        if not below.any():
            out[t] = float("nan")
            continue
        rows = layers[below]
        t_s = float(np.mean(rows["temperature"].to_numpy(float) + a.dry_lapse_rate * z[below]))
        q = float(np.mean(rows["vapor"].to_numpy(float) + rows["cloud"].to_numpy(float)))
        out[t] = float(scene.lifting_condensation_level(t_s, q))
    return pd.Series(out, dtype=float)


def particles_vs_grid(series: pd.DataFrame, mode: str = "non-adaptive", profiles: pd.DataFrame | None = None,
                      scene: Scene | None = None) -> pd.DataFrame:
    """Time means over the cloudy period of the seed-mean cloud statistics of `mode`'s particles and of the
    grid: one row per metric (cloud_base, cloud_top in m; cover, a fraction; lwp in kg/m^2) with
    rel_diff = (particles - grid) / grid.  The cloudy period is the snapshot times at which the seed-mean
    cover of both is above CLOUDY_COVER (grid times matched to the particles' nearest ones).  With the
    profiles and the scene, a last row mixed_layer_lcl: each solver's :func:`mixed_layer_lcl` (m), where its
    cloud base should sit."""
    columns = ["metric", "particles", "grid", "rel_diff", "cloudy_from_s", "cloudy_to_s", "times", "device", "commit"]
    need = {"mode", "time_s", *(c for _, c in CLOUD_MEANS)}
    if series is None or series.empty or not need <= set(series.columns):
        return pd.DataFrame(columns=columns)
    means = {m: series[series["mode"] == m].groupby("time_s")[[c for _, c in CLOUD_MEANS]].mean()
             for m in (mode, "grid")}
    part, grid = means[mode], means["grid"]
    if part.empty or grid.empty:
        return pd.DataFrame(columns=columns)
    grid = grid.reindex(part.index, method="nearest")
    cloudy = (part["cloud_cover"] > CLOUDY_COVER) & (grid["cloud_cover"] > CLOUDY_COVER)
    if not cloudy.any():
        return pd.DataFrame(columns=columns)
    times = part.index[cloudy]
    device = " / ".join(sorted(series.loc[series["mode"].isin([mode, "grid"]), "device"].dropna().astype(str).unique())) \
        if "device" in series else ""
    commit = str(series["commit"].dropna().iloc[0]) if "commit" in series and series["commit"].notna().any() else ""
    def row(metric: str, p: float, g: float) -> dict:
        return {"metric": metric, "particles": p, "grid": g, "rel_diff": (p - g) / g if g else float("nan"),
                "cloudy_from_s": float(times.min()), "cloudy_to_s": float(times.max()), "times": int(cloudy.sum()),
                "device": device, "commit": commit}

    rows = [row(metric, float(part.loc[cloudy, column].mean()), float(grid.loc[cloudy, column].mean()))
            for metric, column in CLOUD_MEANS]
    if profiles is not None and scene is not None and not profiles.empty:
        lcl = {m: mixed_layer_lcl(profiles, series, m, scene) for m in (mode, "grid")}
        rows.append(row("mixed_layer_lcl", float(lcl[mode].reindex(times).mean()),
                        float(lcl["grid"].reindex(grid.index[cloudy], method="nearest").mean())))
    return pd.DataFrame(rows, columns=columns)


def compare_command(
    scene: Annotated[str, typer.Argument(help="a cloud scene (its NAME_adaptive twin is used when it ships)")] = "growing",
    seeds: Annotated[Optional[int], typer.Option(min=5, max=1000, help="noise seeds per mode (>= 5)")] = None,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
) -> None:
    """Particles (non-adaptive and adaptive) against the grid baseline over >= 5 seeds."""
    scene_arg(scene)
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        try:
            with refusals():
                frames = run_compare(ctx, scene, seeds)
        except ValueError as exc:
            raise click.UsageError(str(exc)) from None
    typer.echo(frames["compare_runs"][["solver", "mode", "seed", "stable", "step", "step_wall_s"]].to_string(index=False))
    if len(frames["particles_vs_grid"]):
        typer.echo(frames["particles_vs_grid"][["metric", "particles", "grid", "rel_diff"]].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'compare_timeseries.csv'}, compare_profiles.csv, compare_runs.csv, "
               "particles_vs_grid.csv")


# ---- report: adaptive against non-adaptive, particles against the grid, the verdict card ---------
PARTICLE_COUNT_COLUMNS = ("n_particles", "particles", "max_particles")


def _adaptive(inp: Inputs, sec: Section, env: dict | None) -> None:
    ts, _ = inp.csv("compare_timeseries")
    table1, _ = inp.csv("table1")
    particles = None
    if ts is not None and "solver" in ts.columns:
        particles = ts[ts["solver"] == "particles"]
        if particles.empty or particles["mode"].nunique() < 2:
            particles = None
    if particles is None and table1 is None:
        _missing(sec, "adaptive and non-adaptive particle runs (compare_timeseries.csv, table1.csv)", "compare", inp)
        return
    if table1 is not None:
        measured = table1.copy()
        measured["total_ms"] = _measured_total(measured)
        ratio = step_time_ratios(measured)
        paper = step_time_ratios(_paper_table())
        counts = measured.pivot_table(index="example", columns="mode", values="max_particles", aggfunc="max")
        rows = []
        for example in sorted(set(ratio) | set(counts.index)):
            rows.append({"example": example,
                         "particles non-adaptive": counts.get("non-adaptive", pd.Series()).get(example, math.nan),
                         "particles adaptive": counts.get("adaptive", pd.Series()).get(example, math.nan),
                         "step-time ratio non-adaptive / adaptive": ratio.get(example, math.nan),
                         "the paper's ratio": paper.get(example, math.nan)})
        sec.add("table", _table(pd.DataFrame(rows)), caption=(
            "Step time of each Table 1 example's non-adaptive row over its adaptive row. The two runs hold different "
            "particle counts, so the ratio is not a speed-up: the speed-up at equal error is the adaptive-pareto "
            "study's ('Adaptive mode at equal error') or the sweep's ('Run time against error'). The paper's ratios: "
            + ", ".join(f"{k} {v:.2f}" for k, v in paper.items()) + "."))
    else:
        _missing(sec, "table1.csv (adaptive and non-adaptive step times)", "table1", inp)
    if particles is not None:
        count_col = next((c for c in PARTICLE_COUNT_COLUMNS if c in particles.columns), None)
        panels = ([(count_col, "particles (count)")] if count_col else []) + [
            ("cloud_cover", "cloud cover (fraction of columns)"), ("lwp_mean", "mean liquid water path (kg/m$^2$)")]
        shown = particles
        if "total_water" in particles.columns:
            shown = particles.assign(total_water_change=plots.relative_change(particles, "total_water"))
            panels.append(("total_water_change", "total water (vapor + cloud), relative change since t = 0"))
        sec.add("image", plots.timeseries_plot(shown, panels), caption=(
            "Particle runs, non-adaptive and adaptive: mean over seeds, band = min..max over seeds. Total water "
            "is shown as its relative change from each run's start (conserved without sources: it stays near 0)."))
        rows = []
        for mode, g in particles.groupby("mode", sort=True):
            last = g.sort_values("time_s").groupby("seed").tail(1)
            onset = [_onset(gs) for _, gs in g.groupby("seed")]
            row = {"mode": mode, "seeds": g["seed"].nunique(), "onset s": _mean_sd(pd.Series(onset)),
                   "final cover": _mean_sd(last["cloud_cover"]), "final LWP kg/m2": _mean_sd(last.get("lwp_mean"))}
            if count_col:
                row["final particles"] = _mean_sd(last[count_col])
                row["max particles"] = f"{pd.to_numeric(g[count_col]).max():.0f}"
            rows.append(row)
        sec.add("table", _table(pd.DataFrame(rows)), caption="mean [95% confidence interval, t over seeds]")
        tests = adaptive_tests(particles, inp.csv("compare_runs")[0])
        if tests is not None:
            sec.add("table", _table(tests), caption=(
                "Adaptive against non-adaptive, seed by seed: Welch's t-test (unequal variances, scipy.stats."
                "ttest_ind) of each quantity; p < 0.05: the difference is larger than the seed spread explains. "
                "Wall time is the time inside step() of each run (compare_runs.csv)."))
    else:
        _missing(sec, "compare_timeseries.csv with both particle modes (cloud statistics over time)", "compare", inp)
    sec.provenance = _provenance(table1, ts, env=env)


def _per_seed(particles: pd.DataFrame, runs_df: pd.DataFrame | None, mode: str) -> dict:
    """quantity label -> per-seed values of one particle mode (the last time of each seed's series)."""
    g = particles[particles["mode"] == mode]
    last = g.sort_values("time_s").groupby("seed").tail(1)
    out = {"onset time (s)": [_onset(gs) for _, gs in g.groupby("seed")],
           "final cloud cover (fraction)": last["cloud_cover"]}
    if "lwp_mean" in last.columns:
        out["final mean LWP (kg/m2)"] = last["lwp_mean"]
    if runs_df is not None and {"solver", "mode", "step_wall_s"} <= set(runs_df.columns):
        r = runs_df[(runs_df["solver"] == "particles") & (runs_df["mode"] == mode)]
        out["wall time in step() (s)"] = r["step_wall_s"]
    return out


def adaptive_tests(particles: pd.DataFrame, runs_df: pd.DataFrame | None = None) -> pd.DataFrame | None:
    """One row per quantity: both modes' mean [95% CI] over seeds, the difference and Welch's p-value;
    None without both modes."""
    if particles is None or not {"non-adaptive", "adaptive"} <= set(particles["mode"]):
        return None
    fixed, adapt = _per_seed(particles, runs_df, "non-adaptive"), _per_seed(particles, runs_df, "adaptive")
    rows = []
    for name in fixed:
        if name not in adapt:
            continue
        a, b = mean_ci(fixed[name]), mean_ci(adapt[name])
        t, p = welch(adapt[name], fixed[name])    # t > 0: adaptive larger
        rows.append({"quantity": name, "non-adaptive": format_ci(a), "adaptive": format_ci(b),
                     "seeds": f"{a.n} / {b.n}", "adaptive - non-adaptive": b.mean - a.mean, "Welch t": t,
                     "p": p, "significant (5%)": "–" if math.isnan(p) else ("yes" if p < 0.05 else "no")})
    return pd.DataFrame(rows) if rows else None


def _onset(g: pd.DataFrame) -> float:
    return onset_time(g)


SUMMARY_COLUMNS = (("cloud_cover", "cover"), ("lwp_mean", "LWP kg/m2"), ("cloud_base", "base m"),
                   ("cloud_top", "top m"), ("base_p10", "base p10 m"), ("top_p90", "top p90 m"),
                   ("n_objects", "objects"))


def _compare(inp: Inputs, sec: Section, env: dict | None) -> None:
    ts, _ = inp.csv("compare_timeseries")
    prof, _ = inp.csv("compare_profiles")
    if ts is None and prof is None:
        _missing(sec, "compare_timeseries.csv and compare_profiles.csv", "compare", inp)
        return
    if prof is not None:
        sec.add("image", plots.profiles_plot(prof), caption=(
            "Horizontal-mean vertical profiles at the last common time, particles deposited on a grid with the SPH "
            "kernel, the grid baseline on its own grid; both through the same statistics code."))
    else:
        _missing(sec, "compare_profiles.csv", "compare", inp)
    if ts is not None:
        panels = list(plots.TIMESERIES_PANELS)
        if "base_p10" in ts.columns and "top_p90" in ts.columns:
            panels += [("base_p10", "cloud base, 10th percentile of columns (m)"),
                       ("top_p90", "cloud top, 90th percentile of columns (m)")]
        sec.add("image", plots.timeseries_plot(ts, panels), caption=(
            "Cloud statistics against time: line = mean over seeds, band = min..max over seeds."))
        budget = [c for c in ("heat_source_total", "heat_latent_total", "heat_adiabatic_total",
                              "heat_smoothing_total", "heat_numerical_total", "mass_centre_height",
                              "kinetic_energy") if c in ts.columns]
        if budget:
            labels = {"heat_source_total": "warming from the ground heating, eq. 5 (K)",
                      "heat_latent_total": "warming from latent heat, eq. 11 (K)",
                      "heat_adiabatic_total": "warming from the adiabatic term, eq. 7 (K)",
                      "heat_smoothing_total": "warming from smoothing, eq. 12-17 (K)",
                      "heat_numerical_total": "warming from the grid's advection scheme (K)",
                      "mass_centre_height": "mass-centre height (m)", "kinetic_energy": "kinetic energy (J)"}
            sec.add("image", plots.timeseries_plot(ts, [(c, labels[c]) for c in budget]), caption=(
                "Heat budget of every run, particles and grid alike (mass-weighted mean warming from each "
                "process, summed from t = 0; they add up to the change of the mean temperature; "
                "docs/validation.md), mass-centre height and kinetic energy: line = mean over seeds, band = "
                "min..max. In a closed, incompressible atmosphere the adiabatic term and the mass centre stay "
                "near zero and smoothing adds no heat; the grid has no smoothing and reports what its "
                "advection creates instead."))
        rows = []
        keys = [k for k in ("solver", "mode") if k in ts.columns]
        for key, g in ts.groupby(keys, sort=True):
            key = key if isinstance(key, tuple) else (key,)
            last = g.sort_values("time_s").groupby("seed").tail(1) if "seed" in g else g.tail(1)
            onset = [_onset(gs) for _, gs in g.groupby("seed")] if "seed" in g else [_onset(g)]
            row = dict(zip(keys, key))
            row["seeds"] = g["seed"].nunique() if "seed" in g else 1
            row["onset s"] = _mean_sd(pd.Series(onset))
            for col, label in SUMMARY_COLUMNS:
                if col in last.columns:
                    row[f"final {label}"] = _mean_sd(last[col])
            rows.append(row)
        sec.add("table", _table(pd.DataFrame(rows)), caption=(
            "At each run's last time; mean [95% confidence interval, t over seeds] (onset: first time with cover > 0; "
            "'–' where no cloud formed)."))
        agreement, _ = inp.csv("particles_vs_grid")
        if agreement is not None and len(agreement):
            sec.add("table", _table(agreement[["metric", "particles", "grid", "rel_diff", "cloudy_from_s",
                                               "cloudy_to_s"]]), caption=(
                "Particles (non-adaptive) against the grid: time means over the cloudy period (both seed-mean covers "
                "above 1%) of the seed-mean cloud base and top (m), cover and mean LWP (kg/m2), and each solver's "
                "mixed-layer LCL (m: the lifting condensation level of the mean air below half its cloud base); "
                "rel_diff = (particles - grid) / grid."))
        if "seed" in ts.columns and ts.groupby(keys)["seed"].nunique().min() < 5:
            sec.add("note", "fewer than 5 seeds in at least one group: the spread is not well sampled.", level="warn")
    else:
        _missing(sec, "compare_timeseries.csv", "compare", inp)
    sec.provenance = _provenance(ts, prof, env=env)


CYCLING_PANELS = (("cloud_cover", "cloud cover (fraction of columns)"), ("lwp_mean", "mean liquid water path (kg/m2)"),
                  ("cloud_top", "cloud top (m)"), ("rain_total", "rain removed since t = 0 (kg, eq. C3)"),
                  ("water_relaxation_total", "vapor added by the relaxation since t = 0 (kg, eq. C2)"))


def _cycling(inp: Inputs, sec: Section) -> None:
    """Paper example 2 (docs/cycling.md), shown in the compare section when `cloudpbf cycling` ran."""
    ts, _ = inp.csv("cycling_timeseries")
    cycles, path = inp.csv("cycling_cycles")
    if ts is None and cycles is None:
        return
    sec.add("text", "Example 2: clouds that disappear and reappear (cloudpbf cycling, docs/cycling.md): "
                    "time-of-day ground heating, relaxation toward the initial profiles and rain.")
    if ts is not None:
        sec.add("image", plots.timeseries_plot(ts, CYCLING_PANELS), caption=(
            "The cycling scene: cover, liquid water path, cloud top and the water budget's sinks and sources "
            "(docs/cycling.md C4: total water = initial + relaxation - rain) against time for the three solvers; "
            "line = mean over seeds, band = min..max over seeds."))
    if cycles is not None:
        rows = []
        for (solver, mode), g in cycles.groupby(["solver", "mode"], sort=True):
            rows.append({"solver": solver, "mode": mode, "seeds": g["seed"].nunique(),
                         "full cycles": _mean_sd(g["cycles"]), "fewest cycles": int(g["cycles"].min()),
                         "peak cover": _mean_sd(g["peak_cover"]), "min cover": _mean_sd(g["min_cover"])})
        sec.add("table", _table(pd.DataFrame(rows)), caption=(
            f"Full cycles per run from {path.name}: after the cover first reaches half its peak, a fall below "
            "20% of the peak followed by a climb back above 50%; mean [95% confidence interval, t over seeds]."))
    budgets, bpath = inp.csv("cycling_budgets")
    if budgets is not None and len(budgets):
        shown = budgets.copy()
        shown["closure"] = shown["closure"].map(lambda x: f"{x:.1e}")
        keep = ["mode", "seed", "cycle", "start_s", "peak_s", "min_s", "end_s", "peak_cover", "rain", "relaxation",
                "d_total_water", "closure", "latent_heat"]
        sec.add("table", _table(shown[[c for c in keep if c in shown.columns]].round(3)), caption=(
            f"The water budget over each full cycle ({bpath.name}, docs/cycling.md C4), kg: rain removed, "
            "vapor added by the relaxation (negative: removed), the change of the solver's own total water, and "
            "closure = (change - (relaxation - rain)) / mean total water; latent heat released, K (eq. 11)."))
    modes, tags = ("non-adaptive", "adaptive", "grid"), ("peak", "min")
    grid = [[inp.render(f"cycling_{mode}_{tag}")[0] for tag in tags] for mode in modes]
    shown = [(mode, row) for mode, row in zip(modes, grid) if any(p is not None for p in row)]
    if shown:
        sec.add("image", plots.image_grid([row for _, row in shown], [mode for mode, _ in shown],
                                          ["first cover peak", "clearest moment after that peak"]), caption=(
            "Example 2 in the style of the paper's Fig. 5c/d: each solver's seed-0 run at its first cover "
            "peak (left) and at the clearest moment that follows (right), side by side "
            "(cloudpbf.studies.cycling.cycle_states; the times are those of the water-budget table). Particles "
            "with w > 1e-5 kg/kg are drawn, the grid's cloud water as a volume."))


def _convergence_means(conv: pd.DataFrame) -> pd.DataFrame:
    """The rows the convergence plot draws: the mean rows (seed "mean") where convergence.csv has per-seed rows
    beside them, else every row (a CSV of single runs)."""
    if "seed" not in conv.columns:
        return conv
    means = conv[conv["seed"].astype(str) == "mean"]
    return means if len(means) else conv


def _fmt_interval(value: float, lo: float, hi: float) -> str:
    if not math.isfinite(value):
        return "–"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"{value:.3g}"
    return f"{value:.3g} [{lo:.3g}, {hi:.3g}]"


def convergence_table(conv: pd.DataFrame) -> pd.DataFrame:
    """Per solver and statistic of convergence.csv: the fitted order p of S(h) = S_inf + C h^p with its 90%
    interval, S_inf with its interval, the resolutions (m) and seeds behind the fit, how the interval was made and
    why no order was determined where none was (cloudpbf.report.inference.convergence_orders)."""
    runs_ = conv[conv["parameter"].isin(["spacing", "cells"])] if "parameter" in conv.columns else conv
    if "stable" in runs_.columns:
        runs_ = runs_[runs_["stable"].map(plots._truthy)]
    columns = [c for c, _ in plots.CONVERGENCE_PANELS]
    fits = convergence_orders(runs_, columns, by="solver")
    labels = dict(plots.CONVERGENCE_PANELS)
    rows = []
    for fit in fits.itertuples():
        h = pd.to_numeric(runs_.loc[runs_["solver"] == fit.solver, "resolution_m"], errors="coerce").dropna()
        rows.append({"solver": fit.solver, "statistic": labels.get(fit.statistic, fit.statistic),
                     "order p [90%]": _fmt_interval(fit.order, fit.order_lo, fit.order_hi),
                     "S_inf [90%]": _fmt_interval(fit.limit, fit.limit_lo, fit.limit_hi),
                     "h (m)": f"{h.max():.3g}..{h.min():.3g} ({fit.resolutions})" if len(h) else "–",
                     "seeds": fit.seeds,
                     "interval": fit.interval, "no order because": fit.reason or "–"})
    return pd.DataFrame(rows)


def _convergence(inp: Inputs, sec: Section) -> None:
    """Both solvers against resolution in the scene's own domain (convergence.csv; docs/validation.md,
    "Convergence of both solvers with resolution"), with each statistic's fitted order of convergence."""
    conv, path = inp.csv("convergence")
    if conv is None:
        return
    means = _convergence_means(conv)
    figure = plots.convergence_plot(means)
    if figure is None:
        return
    seeds = pd.to_numeric(conv["seed"], errors="coerce").nunique() if "seed" in conv.columns else 0
    which = f"mean over {seeds} seeds" if seeds > 1 else "seed 0"
    sec.add("image", figure, caption=(
        f"Convergence in the full domain ({path.name}, {_provenance(conv)}): each solver's cloud statistics "
        f"(time means over the cloudy period, {which}) against its resolution, particle spacing or grid cell size "
        "(finer to the right); where the lines approach each other, the solvers converge toward one answer."))
    table = convergence_table(conv)
    if len(table):
        sec.add("table", _table(table), caption=(
            "Order of convergence: S(h) = S_inf + C h^p fitted by least squares to each statistic's seed mean "
            "against the resolution h (Richardson's model; exact with three resolutions). A larger p converges "
            "faster; S_inf is the extrapolated h -> 0 value. Intervals (90%): a percentile bootstrap over seeds "
            "where per-seed rows exist, else the fit's covariance (t with n - 3 degrees of freedom). A series that "
            "is flat, not monotone in h, or whose changes do not shrink as a power of h has no order: its "
            "resolution effect is not separated from run-to-run noise, or does not follow one power of h (a p at the "
            "search bound, 0.05 or 8) (docs/validation.md)."))
        if not (table["order p [90%]"] != "–").any():
            sec.add("note", "no statistic of either solver has a determined order of convergence over these "
                            "resolutions (the table says why for each).", level="warn")


def _compare_and_cycling(inp: Inputs, sec: Section, env: dict | None) -> None:
    _compare(inp, sec, env)
    _convergence(inp, sec)
    _cycling(inp, sec)


def compare_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    card = Card("compare", "Particles against the grid")
    ts, _ = inp.csv("compare_timeseries")
    if ts is None or "solver" not in ts.columns or not {"particles", "grid"} <= set(ts["solver"]):
        return missing_card(card, inp, "no compare_timeseries.csv with both solvers", "compare")
    last = ts.sort_values("time_s").groupby(["solver", "mode", "seed"]).tail(1)
    grid = last[last["solver"] == "grid"]["cloud_cover"]
    labels, cis, parts, none = [], [], [], []
    for mode in ("non-adaptive", "adaptive"):
        part = last[(last["solver"] == "particles") & (last["mode"] == mode)]["cloud_cover"]
        if not len(part):
            continue
        diff = difference_ci(part, grid)
        no = describes_no_difference(diff, 0.0)
        none.append(no)
        labels.append(f"particles {mode}")
        cis.append(mean_ci(part))
        bounds = (f"[{diff.lo:+.2g}, {diff.hi:+.2g}]" if np.isfinite(diff.lo) else "(no interval)")
        parts.append(f"{mode} {diff.mean:+.2g} {bounds}" + (": no difference measured" if no else ""))
    labels.append("grid")
    cis.append(mean_ci(grid))
    card.answer = "Final cloud cover, particles minus grid: " + "; ".join(parts) + "."
    card.detail = ("Seed means [95% t-interval]: " + ", ".join(f"{lab} {format_ci(ci)}" for lab, ci in zip(labels, cis))
                   + f"; difference: Welch {100 * LEVEL:g}% interval.")
    card.level = "warn" if any(none) else "ok"
    card.figure = gp.intervals(labels, [c.mean for c in cis], [c.lo for c in cis], [c.hi for c in cis],
                               "final cloud cover (fraction)")
    card.links = section_link("compare", titles) + data_link(inp, "compare_timeseries.csv", "compare_runs.csv")
    return card


register(Study("compare", order=30, run=lambda ctx, scene: run_compare(ctx, scene), sections=("adaptive", "compare"),
                report=(ReportSection("adaptive", "Adaptive against non-adaptive", _adaptive, 40, "Adaptive"),
                        ReportSection("compare", "Particles against the grid baseline", _compare_and_cycling, 50,
                                      "Particles vs grid"),),
                glance=(GlanceCard(compare_card, 30),), produces={"compare": "cloudpbf compare growing --out {out}"},
                outputs=("compare_timeseries.csv", "compare_profiles.csv", "compare_runs.csv", "particles_vs_grid.csv"),
                scale={"seeds": {"smoke": 5, "cpu": 5, "gpu": 5},        # noise seeds per mode
                       # the smoke scale's small box that forms clouds (None: scale the scene as the others)
                       "compare_box": {"smoke": SMOKE_BOX, "cpu": None, "gpu": None}},
                command=compare_command))
