"""Particles against the grid: the same cloud scene run by the particle solver (non-adaptive and
adaptive) and by the grid baseline, over several noise seeds (the seed shifts the ground-heating
pattern, eq. 5, identically in both solvers).

Every run is analysed by the same code (bench.statistics): particles are deposited on the grid the
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

from typing import Annotated, Optional

import numpy as np
import pandas as pd
import typer

from bench import runs
from bench.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, click, refusals, scene_arg, study_context)
from bench.statistics import CLOUD_MEANS, CLOUDY_COVER, DIAGNOSTIC_COLUMNS, PROFILE_COLUMNS, grid_for_scene
from bench.studies.context import StudyContext
from bench.studies.registry import ReportSection, Study, register
from bench.studies.scales import scale_scene
from pbf_cuda.scene import Scene, SceneError, list_scenes, load_scene

MODES = ("non-adaptive", "adaptive", "grid")
# The energy and heat budget of both solvers (Simulation.stats(), GridSimulation.stats(); docs/physics.md, Budgets).
BUDGET_COLUMNS = ("mass_centre_height", "kinetic_energy", "mean_temperature", "heat_source_total",
                  "heat_latent_total", "heat_adiabatic_total", "heat_smoothing_total", "heat_numerical_total",
                  "heat_relaxation_total", "water_relaxation_total", "water_rain_total")
SOLVER_OF_MODE = {"non-adaptive": "particles", "adaptive": "particles", "grid": "grid"}
SOLVER_COLUMNS = ("n_particles", "level_0", "level_1", "level_2", "level_3", "density_error_mean",
                  "density_error_max", "density_excess_mean", "density_deficit_mean", "max_speed", "cfl", "substeps",
                  "divergence_rel", *BUDGET_COLUMNS)
MIN_SEEDS = 5


def scene_pair(name: str) -> tuple[Scene, Scene]:
    """(non-adaptive, adaptive) versions of a cloud scene.

    NAME_adaptive is used when it ships; otherwise adaptivity is switched on with level-0 particles
    twice the spacing (a level-3 particle then matches the non-adaptive size, as in the paper)."""
    base_name = name[: -len("_adaptive")] if name.endswith("_adaptive") and name[:-9] in list_scenes() else name
    base = load_scene(base_name)
    if base.atmosphere is None:
        raise ValueError(f"compare needs a cloud scene (one with an [atmosphere] section); '{name}' has none. "
                         f"Cloud scenes: {', '.join(n for n in list_scenes() if load_scene(n).thermodynamics)}")
    if base.adaptive.enabled:
        base = base.replace(**{"adaptive.enabled": False,
                               "particles.spacing": base.particles.spacing / 2 ** (base.adaptive.max_level / 3)})
    if f"{base_name}_adaptive" in list_scenes():
        adaptive = load_scene(f"{base_name}_adaptive")
    else:
        try:
            adaptive = base.replace(**{"adaptive.enabled": True, "adaptive.max_level": 3,
                                       "particles.spacing": 2.0 * base.particles.spacing})
        except SceneError as exc:
            raise ValueError(f"cannot make an adaptive twin of '{name}' by doubling its spacing ({exc}); "
                             f"write a scene file {base_name}_adaptive.toml") from None
    return base, adaptive


SMOKE_BOX = {"domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 4.0,
             "time.steps": 120, "time.snapshot_every": 20}
"""The smoke scale's compare box (both modes, level-0 spacing 100 m for the adaptive twin too): the cloud
scene's physics in a 1.2 x 1.6 x 1.2 km box of 2,304 particles, 480 s at dt = 4 s (at 8 s the adaptive
run's refined particles hold a 64% density error, at 4 s about 1%).  Scaled to 3,000
particles in the 3.2 km domain (222 m spacing) no particle run forms a cloud within the smoke run; in
this box the first cloud appears near t = 320 s (measured on the 2-core CPU, docs/harness.md "Scales")."""

ANIMATION_FRAMES = 8
"""Stored states of the seed-0 non-adaptive run (the report's animation of the clouds developing)."""


def compare_specs(ctx: StudyContext, scene_name: str, seeds: int) -> list[tuple[str, int, runs.RunSpec]]:
    """(mode, seed, spec) for every mode and seed."""
    if seeds < MIN_SEEDS:
        raise ValueError(f"seeds = {seeds}: compare needs at least {MIN_SEEDS} seeds")
    box = getattr(ctx.scale, "compare_box", None)
    if box:
        base, adaptive = (s.replace(**box) for s in scene_pair(scene_name))
    else:
        base, adaptive = (scale_scene(s, ctx.scale.particles, ctx.scale.step_fraction) for s in scene_pair(scene_name))
    shape, _ = grid_for_scene(base)                  # one cell per non-adaptive spacing, for all three
    out = []
    for seed in range(seeds):
        out.append(("non-adaptive", seed, runs.RunSpec("particles", base, backend=ctx.backend, seed=seed,
                                                        diagnostics_resolution=shape,
                                                        keep_snapshots=ANIMATION_FRAMES if seed == 0 else 3)))
        out.append(("adaptive", seed, runs.RunSpec("particles", adaptive, backend=ctx.backend, seed=seed,
                                                    diagnostics_resolution=shape)))
        out.append(("grid", seed, runs.RunSpec("grid", base, seed=seed, resolution=shape)))
    return out


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


register(Study("compare", order=30, run=lambda ctx, scene: run_compare(ctx, scene), sections=("adaptive", "compare"),
                report=(ReportSection("adaptive", "Adaptive against non-adaptive", "bench.report.build:_adaptive", 40),
                        ReportSection("compare", "Particles against the grid baseline", "bench.report.build:_compare_and_cycling", 50),),
                outputs=("compare_timeseries.csv", "compare_profiles.csv", "compare_runs.csv", "particles_vs_grid.csv"),
                scale={"seeds": {"smoke": 5, "cpu": 5, "gpu": 5},        # noise seeds per mode
                       # the smoke scale's small box that forms clouds (None: scale the scene as the others)
                       "compare_box": {"smoke": SMOKE_BOX, "cpu": None, "gpu": None}},
                command=compare_command))
