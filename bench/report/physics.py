"""Sections of the physics: adaptive against non-adaptive particles, particles against the grid (with the
convergence and cycling parts), shallow cumulus."""
from __future__ import annotations

import math

import pandas as pd

from . import plots
from .common import (Inputs, Section, step_time_ratios, _mean_sd, _measured_total, _missing, _paper_table,
                     _provenance, _table)
from .inference import format_ci, mean_ci, welch
from .pictures import _render_blocks

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
        _missing(sec, "adaptive and non-adaptive particle runs (compare_timeseries.csv, table1.csv)", "compare",
                 inp.out)
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
        _missing(sec, "table1.csv (adaptive and non-adaptive step times)", "table1", inp.out)
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
        _missing(sec, "compare_timeseries.csv with both particle modes (cloud statistics over time)", "compare",
                 inp.out)
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
    from bench.statistics import onset_time
    return onset_time(g)


SUMMARY_COLUMNS = (("cloud_cover", "cover"), ("lwp_mean", "LWP kg/m2"), ("cloud_base", "base m"),
                   ("cloud_top", "top m"), ("base_p10", "base p10 m"), ("top_p90", "top p90 m"),
                   ("n_objects", "objects"))


def _compare(inp: Inputs, sec: Section, env: dict | None) -> None:
    ts, _ = inp.csv("compare_timeseries")
    prof, _ = inp.csv("compare_profiles")
    if ts is None and prof is None:
        _missing(sec, "compare_timeseries.csv and compare_profiles.csv", "compare", inp.out)
        return
    if prof is not None:
        sec.add("image", plots.profiles_plot(prof), caption=(
            "Horizontal-mean vertical profiles at the last common time, particles deposited on a grid with the SPH "
            "kernel, the grid baseline on its own grid; both through the same statistics code."))
    else:
        _missing(sec, "compare_profiles.csv", "compare", inp.out)
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
        _missing(sec, "compare_timeseries.csv", "compare", inp.out)
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
            "(bench.studies.cycling.cycle_states; the times are those of the water-budget table). Particles "
            "with w > 1e-5 kg/kg are drawn, the grid's cloud water as a volume."))


def _convergence(inp: Inputs, sec: Section) -> None:
    """Both solvers against resolution in the scene's own domain (convergence.csv; docs/validation.md,
    "Convergence of both solvers with resolution")."""
    conv, path = inp.csv("convergence")
    if conv is None:
        return
    figure = plots.convergence_plot(conv)
    if figure is None:
        return
    sec.add("image", figure, caption=(
        f"Convergence in the full domain ({path.name}, {_provenance(conv)}): each solver's cloud statistics "
        "(time means over the cloudy period, seed 0) against its resolution, particle spacing or grid cell size "
        "(finer to the right); where the lines approach each other, the solvers converge toward one answer."))


def _compare_and_cycling(inp: Inputs, sec: Section, env: dict | None) -> None:
    _compare(inp, sec, env)
    _convergence(inp, sec)
    _cycling(inp, sec)


def _shallow_cumulus(inp: Inputs, sec: Section, env: dict | None) -> None:
    """The shallow_cumulus study (bench.studies.shallow_cumulus): statistics beside the LES cases, renders."""
    summary, path = inp.csv("shallow_cumulus")
    if summary is None:
        _missing(sec, "the shallow-cumulus study (shallow_cumulus.csv)", "shallow_cumulus", inp.out)
        return
    sec.add("text", "growing under a capping inversion (scene shallow_cumulus, docs/validation.md "
                    "\"Shallow cumulus\"): per seed, statistics over the last half of the run. "
            + _provenance(summary, env=env))
    cols = {"seed": "seed", "particles": "particles", "cover_mean": "cover (mean)", "cover_max": "cover (max)",
            "in_shallow_range": "snapshots in 0.1-0.4", "cf_peak": "cloud-fraction peak",
            "z_cf_peak_m": "peak height (m)", "cover_to_peak": "cover / peak", "cloud_base_m": "base (m)",
            "cloud_top_m": "top (m)", "lwp_g_m2": "LWP (g/m²)", "clouds_end": "clouds at the end"}
    shown = summary[[c for c in cols if c in summary.columns]].rename(columns=cols)
    sec.add("table", _table(shown), caption=f"{path.name}: one row per seed and their mean.")
    les, lpath = inp.csv("shallow_cumulus_les")
    if les is not None:
        keep = ["case", "metric", "lo", "hi", "scene_mean", "scene_seed_min", "scene_seed_max", "inside", "note",
                "source"]
        sec.add("table", _table(les[[c for c in keep if c in les.columns]]), caption=(
            f"{lpath.name}: the published cases' numbers (from the papers' text) beside the scene's seed mean "
            "and seed range; inside: the mean lies in the case's range."))
    grid, gpath = inp.csv("shallow_cumulus_grid")
    if grid is not None:
        seeds = [str(x) for x in grid["seed"] if str(x) != "mean"]
        particles = summary[summary["seed"].astype(str).isin(seeds)]
        keep = [c for c in cols if c not in ("seed", "particles") and c in grid.columns and c in particles.columns]
        rows = [{"solver": f"particles (seeds {', '.join(seeds)})", **particles[keep].mean(numeric_only=True)},
                {"solver": f"grid, {int(grid['cells'].iloc[0])}³ cells (seeds {', '.join(seeds)})",
                 **grid[grid["seed"].astype(str) != "mean"][keep].mean(numeric_only=True)}]
        sec.add("table", _table(pd.DataFrame(rows).rename(columns=cols)), caption=(
            f"The grid baseline on the same scene and seeds ({gpath.name}, cloudpbf run shallow_cumulus --solver grid, "
            f"{_provenance(grid)}), analysed as the particle runs are: seed means."))
    series, _ = inp.csv("shallow_cumulus_series")
    profile, _ = inp.csv("shallow_cumulus_profile")
    if series is not None and profile is not None:
        covers = les[les["metric"] == "cover_mean"] if les is not None else pd.DataFrame()
        bands = [(str(r.case), float(r.lo), float(r.hi)) for r in covers.itertuples()]
        sec.add("image", plots.shallow_cumulus_plot(series, profile, bands),
                caption="Cover against time (shaded: the LES cases' cover ranges) and the time-mean cloud-fraction "
                        "profile.")
    _render_blocks(inp, sec, [
        ("shallow_cumulus_volume", "seed 0 at the end: the cloud water deposited on the analysis grid, volume "
                                   "rendered"),
        ("shallow_cumulus_particles", "the same state as particles with w > 1e-5 kg/kg, opacity rising with w"),
    ])


