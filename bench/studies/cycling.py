"""Paper example 2: clouds that disappear and reappear (docs/cycling.md), counted in both solvers.

Runs the `cycling` scene with the particle solver (non-adaptive and adaptive, the `cycling_adaptive`
twin) and with the grid baseline, for >= 3 noise seeds each, and counts the full cycles of the
cloud cover (fraction of columns with cloud, bench.statistics, the same deposit grid for all three)
with one rule (:func:`count_cycles`).  Outputs in OUT/data:

* cycling_cycles.csv: one row per solver, mode and seed: solver, mode, seed, cycles, peak_cover,
  min_cover, device, commit (and stable, steps, run_dir)
* cycling_timeseries.csv: solver, mode, seed, time_s, step, cloud_cover, lwp_mean, cloud_top,
  total_water (of the deposit grid), the water budget's running sums rain_total and
  water_relaxation_total (kg, docs/cycling.md C4), heat_latent_total (K, particles only), device, commit

Scales: ``gpu`` runs the scene files as they ship (930k particles, 4200 s).  Every other scale runs
the CPU cycle: the same physics in a 1200 x 1600 x 1200 m box at 100 m spacing (about 2,300
particles, a 12 x 16 x 12 grid), dt = 8 s and 2400 s, a few minutes on two cores (CPU_OVERRIDES).

    cloudpbf cycling --scale cpu --seeds 3
"""
from __future__ import annotations

import sys

from typing import Annotated

import numpy as np
import pandas as pd
import typer

from bench import runs
from bench.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
from bench.studies.registry import Study, register
from bench.statistics import grid_for_scene
from bench.studies.compare import SOLVER_OF_MODE, scene_pair
from bench.studies.context import StudyContext
from pbf_cuda.scene import Scene

MODES = ("non-adaptive", "adaptive", "grid")
MIN_SEEDS = 3
DISAPPEAR = 0.2      # a cycle: cover below DISAPPEAR x peak ...
REAPPEAR = 0.5       # ... then back above REAPPEAR x peak
MIN_PEAK = 0.05      # a run whose cover never reaches this has no cycles (one flickering column is no cloud field)
COLUMNS = ("solver", "mode", "seed", "cycles", "peak_cover", "min_cover", "device", "commit")
SERIES_COLUMNS = ("cloud_cover", "lwp_mean", "cloud_top", "total_water", "rain_total", "water_relaxation_total",
                  "heat_latent_total")
# The particle solver's name of a budget column -> the grid's (both kg: rho0 = 1 kg/m^3 in the cloud scenes)
RENAMED = {"water_rain_total": "rain_total"}
# The CPU cycle (docs/cycling.md): a small box with the shipped scene's physics; the time step is
# four times the scene's (the forcing is integrated exactly, and N dt stays below 0.1).
# tau = 600 s at this resolution (300 s, the scene file's, is chosen for the 33 m GPU scale; docs/cycling.md)
CPU_OVERRIDES = {"domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 8.0,
                 "time.steps": 300, "atmosphere.relaxation_time": 600.0}
CPU_SNAPSHOT_EVERY = 5
GPU_SNAPSHOT_EVERY = 25


def count_cycles(cover, disappear: float = DISAPPEAR, reappear: float = REAPPEAR, min_peak: float = MIN_PEAK) -> dict:
    """Full disappear/reappear cycles of a cloud-cover series (fractions in [0, 1], in time order).

    peak = the series' largest value.  The count starts once the cover first reaches reappear x peak;
    a cycle is then a fall below disappear x peak followed by a climb back to reappear x peak or more.
    A series whose peak is below `min_peak` counts no cycles (at CPU scale one column is 0.7% of the sky).
    Returns cycles, peak_cover, min_cover (the smallest value after the start; 0 for a cloudless series)."""
    c = np.asarray(cover, dtype=np.float64)
    if not (0.0 <= disappear < reappear <= 1.0):
        raise ValueError(f"disappear = {disappear}, reappear = {reappear}: need 0 <= disappear < reappear <= 1")
    if c.size == 0 or not np.isfinite(c).all():
        raise ValueError("cover: expected a non-empty series of finite values")
    peak = float(c.max())
    if peak <= 0.0:
        return {"cycles": 0, "peak_cover": 0.0, "min_cover": 0.0}
    start = int(np.argmax(c >= reappear * peak))
    cycles, down = 0, False
    for value in (c[start:] if peak >= min_peak else ()):
        if not down and value < disappear * peak:
            down = True
        elif down and value >= reappear * peak:
            down = False
            cycles += 1
    return {"cycles": cycles, "peak_cover": peak, "min_cover": float(c[start:].min())}


def cpu_scene(scene: Scene) -> Scene:
    """The CPU cycle of a cycling scene: CPU_OVERRIDES, for the adaptive twin too.  Its level-0 spacing
    is the non-adaptive one (100 m), not twice it as at GPU scale: with 200 m (and with 126 m) level-0
    particles no cloud forms in this box (measured, docs/cycling.md)."""
    return scene.replace(**CPU_OVERRIDES)


def cycling_specs(ctx: StudyContext, seeds: int, scene_name: str = "cycling") -> list[tuple[str, int, runs.RunSpec]]:
    """(mode, seed, spec) for every mode and seed."""
    if seeds < MIN_SEEDS:
        raise ValueError(f"seeds = {seeds}: the cycling study needs at least {MIN_SEEDS} seeds")
    base, adaptive = scene_pair(scene_name)
    if ctx.scale.name == "gpu":
        every = GPU_SNAPSHOT_EVERY
    else:
        base, adaptive = cpu_scene(base), cpu_scene(adaptive)
        every = CPU_SNAPSHOT_EVERY
    shape, _ = grid_for_scene(base)            # one cell per non-adaptive spacing, for all three
    out = []
    for seed in range(seeds):
        out.append(("non-adaptive", seed, runs.RunSpec("particles", base, backend=ctx.backend, seed=seed,
                                                        snapshot_every=every, diagnostics_resolution=shape)))
        out.append(("adaptive", seed, runs.RunSpec("particles", adaptive, backend=ctx.backend, seed=seed,
                                                    snapshot_every=every, diagnostics_resolution=shape)))
        out.append(("grid", seed, runs.RunSpec("grid", base, seed=seed, resolution=shape, snapshot_every=every)))
    return out


def run_cycling(ctx: StudyContext, seeds: int = MIN_SEEDS, scene_name: str = "cycling") -> dict[str, pd.DataFrame]:
    """Run (or read) every mode x seed; write cycling_cycles.csv and cycling_timeseries.csv."""
    plan = cycling_specs(ctx, seeds, scene_name)
    results = ctx.run_parallel([spec for _, _, spec in plan], "cycling")
    rows, series = [], []
    for (mode, seed, spec), res in zip(plan, results):
        stats = res.stats()
        solver = SOLVER_OF_MODE[mode]
        counted = (count_cycles(stats["cloud_cover"]) if len(stats)
                   else {"cycles": 0, "peak_cover": float("nan"), "min_cover": float("nan")})
        rows.append({"solver": solver, "mode": mode, "seed": seed, **counted, "device": res.device,
                     "commit": ctx.commit, "stable": res.stable, "steps": res.step, "scene": spec.scene.name,
                     "run_dir": str(res.path)})
        if len(stats):
            stats = stats.rename(columns=RENAMED)
            frame = stats[["time_s", "step", *(c for c in SERIES_COLUMNS if c in stats.columns)]].copy()
            for i, (key, value) in enumerate((("solver", solver), ("mode", mode), ("seed", seed))):
                frame.insert(i, key, value)
            frame["device"] = res.device
            frame["commit"] = ctx.commit
            series.append(frame)
    out = {"cycling_cycles": pd.DataFrame(rows),
           "cycling_timeseries": (pd.concat(series, ignore_index=True) if series
                                  else pd.DataFrame(columns=["solver", "mode", "seed", "time_s", "step"]))}
    for name, frame in out.items():
        runs.write_csv(frame, ctx.data / f"{name}.csv")
    return out


def cycling_command(
    seeds: Annotated[int, typer.Option(min=3, max=1000, help="noise seeds per mode (>= 3)")] = 3,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
) -> None:
    """Paper example 2: count the clouds' disappear/reappear cycles in both solvers (docs/cycling.md)."""
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            frames = run_cycling(ctx, seeds)
    typer.echo(frames["cycling_cycles"][list(COLUMNS)].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'cycling_cycles.csv'}, cycling_timeseries.csv")


register(Study("cycling", order=35, sections=("compare",), outputs=("cycling_cycles.csv", "cycling_timeseries.csv"),
               command=cycling_command))


def main(argv=None) -> int:
    """``python -m bench.studies.cycling ARGS`` is ``cloudpbf cycling ARGS``."""
    from bench.cli import main as cli_main
    return cli_main(["cycling", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
