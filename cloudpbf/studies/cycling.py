"""Paper example 2: clouds that disappear and reappear (docs/cycling.md), counted in both solvers.

Runs the `cycling` scene with the particle solver (non-adaptive and adaptive, the `cycling_adaptive`
twin) and with the grid baseline, for >= 3 noise seeds each, and counts the full cycles of the
cloud cover (fraction of columns with cloud, cloudpbf.statistics, the same deposit grid for all three)
with one rule (:func:`count_cycles`).  Outputs in OUT/data:

* cycling_cycles.csv: one row per solver, mode and seed: solver, mode, seed, cycles, peak_cover,
  min_cover, device, commit (and stable, steps, run_dir)
* cycling_budgets.csv: the water budget of every full cycle of every run (:func:`cycle_budgets`):
  its window (start_s, peak_s, end_s), peak cover, the rain, relaxation and total-water change (kg)
  and their closure, the latent heat released (K, particles)
* cycling_timeseries.csv: solver, mode, seed, time_s, step, cloud_cover, lwp_mean, cloud_top,
  total_water (of the deposit grid), budget_total_water (the solver's own total, which C4 closes
  against), the water budget's running sums rain_total and
  water_relaxation_total (kg, docs/cycling.md C4), heat_latent_total (K, particles only), device, commit

Scales: ``gpu`` runs the scene files as they ship (930k particles, 4200 s).  Every other scale runs
the CPU cycle: the same physics in a 1200 x 1600 x 1200 m box at 100 m spacing (about 2,300
particles, a 12 x 16 x 12 grid), dt = 8 s and 2400 s, a few minutes on two cores (CPU_OVERRIDES).

    cloudpbf cycling --scale cpu --seeds 3
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, run_command, study_context)
from cloudpbf.render import compact_particles, render_or_note, render_particles, render_volume
from cloudpbf.store.result import RunResult
from cloudpbf.studies.registry import Study, register
from cloudpbf.statistics import grid_for_scene
from cloudpbf.studies.plans import SOLVER_OF_MODE, scene_pair
from cloudpbf.studies.context import StudyContext
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
# tau = 600 s at this resolution (300 s, the scene file's, is chosen for the 33 m GPU scale; docs/cycling.md).
# At 100 m spacing the density solve lifts the whole column off the heated floor unless its net vertical
# shift is removed (pbf.remove_shift_drift; docs/physics.md, Shift drift): without it the adaptive twin's later
# days lose a third of their heat and it counts no cycle (docs/cycling.md, Measured at CPU scale).
# adaptive.every = 1: the adaptive twin splits and merges every 8 s of model time, as at GPU scale (every fourth
# step of 2 s; with every fourth step of 8 s here, the CPU twin cycled in 1 seed of 0-2, docs/cycling.md)
# The CPU cycle's smoothing and XSPH are stated per step of its own 8 s (time.reference_dt), as it was tuned: with
# the 2 s scenes' rates at its 8 s steps (4x the mixing per step) the adaptive twin of seed 0 had no clouds after
# the night.
CPU_OVERRIDES = {"domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 8.0,
                 "time.reference_dt": 8.0, "time.steps": 300, "atmosphere.relaxation_time": 600.0, "pbf.remove_shift_drift": True,
                 "adaptive.every": 1}
CPU_SNAPSHOT_EVERY = 5
GPU_SNAPSHOT_EVERY = 25
# seed 0 stores every diagnostic state (cycle_states picks the peak and minimum): 84 states of about 50 MB
# for a particle run at GPU scale (about 4 GB on disk), a few MB at CPU scale
RENDER_SNAPSHOTS = 10_000
CLOUD_RENDER_THRESHOLD = 1e-6  # kg/kg: a cloudy particle in the compact render states


def _cycle_ends(c: np.ndarray, disappear: float, reappear: float, min_peak: float) -> tuple[int, list]:
    """The one rule of a full cycle, on a validated cover array c: (start, [(low_at, back_at), ...]).

    peak = c.max(); counting starts at `start`, the first index where c reaches reappear x peak; each full
    cycle ends with a fall below disappear x peak (first at low_at) and a climb back to reappear x peak
    (first at back_at).  A series whose peak is below `min_peak` (or 0) has no cycles."""
    peak = float(c.max())
    start = int(np.argmax(c >= reappear * peak))
    ends, low_at = [], None
    if peak <= 0.0 or peak < min_peak:
        return start, ends
    for i in range(start, c.size):
        if low_at is None and c[i] < disappear * peak:
            low_at = i
        elif low_at is not None and c[i] >= reappear * peak:
            ends.append((low_at, i))
            low_at = None
    return start, ends


def _cover_array(cover, disappear: float, reappear: float) -> np.ndarray:
    c = np.asarray(cover, dtype=np.float64)
    if not (0.0 <= disappear < reappear <= 1.0):
        raise ValueError(f"disappear = {disappear}, reappear = {reappear}: need 0 <= disappear < reappear <= 1")
    if c.size == 0 or not np.isfinite(c).all():
        raise ValueError("cover: expected a non-empty series of finite values")
    return c


def count_cycles(cover, disappear: float = DISAPPEAR, reappear: float = REAPPEAR, min_peak: float = MIN_PEAK) -> dict:
    """Full disappear/reappear cycles of a cloud-cover series (fractions in [0, 1], in time order).

    peak = the series' largest value.  The count starts once the cover first reaches reappear x peak;
    a cycle is then a fall below disappear x peak followed by a climb back to reappear x peak or more.
    A series whose peak is below `min_peak` counts no cycles (at CPU scale one column is 0.7% of the sky).
    Returns cycles, peak_cover, min_cover (the smallest value after the start; 0 for a cloudless series)."""
    c = _cover_array(cover, disappear, reappear)
    peak = float(c.max())
    if peak <= 0.0:
        return {"cycles": 0, "peak_cover": 0.0, "min_cover": 0.0}
    start, ends = _cycle_ends(c, disappear, reappear, min_peak)
    return {"cycles": len(ends), "peak_cover": peak, "min_cover": float(c[start:].min())}


def cycle_windows(cover, times, disappear: float = DISAPPEAR, reappear: float = REAPPEAR,
                  min_peak: float = MIN_PEAK) -> list[dict]:
    """The full cycles of a cover series as time windows, by the rule of :func:`count_cycles`.

    A cycle runs from the moment the cover has vanished (first below disappear x peak; or the series'
    first time) through its clouds' rise and peak, their decay below disappear x peak, to the moment
    the next generation's cover is back at reappear x peak.  Returns one dict per full cycle: start_s,
    peak_s, min_s (the clearest moment after the peak), end_s (s), peak_cover, min_cover."""
    c = _cover_array(cover, disappear, reappear)
    t = np.asarray(times, dtype=np.float64)
    if c.shape != t.shape:
        raise ValueError(f"cover has {c.size} values, times {t.size}")
    windows, start = [], 0
    for low_at, back_at in _cycle_ends(c, disappear, reappear, min_peak)[1]:
        top = start + int(np.argmax(c[start:low_at + 1]))
        low = top + int(np.argmin(c[top:back_at + 1]))
        windows.append({"start_s": float(t[start]), "peak_s": float(t[top]), "min_s": float(t[low]),
                        "end_s": float(t[back_at]), "peak_cover": float(c[top]), "min_cover": float(c[low])})
        start = low_at
    return windows


def cycle_budgets(series: pd.DataFrame) -> pd.DataFrame:
    """The water budget of every full cycle (docs/cycling.md C4) of every run in a cycling time series.

    For each solver, mode, seed and cycle (:func:`cycle_windows`) the changes over the window, in kg:
    total water (the solver's own total of vapor + cloud, ``budget_total_water``, else ``total_water``),
    rain (C3, removed), relaxation (C2, added; negative when the forcing dries the air), and closure = d total_water - (relaxation - rain) as a fraction of
    the window's mean total water (0 up to rounding when the run conserves water); for particle runs
    also the latent heat released (K, mass-weighted mean warming, eq. 11).  Rows in time order."""
    water = "budget_total_water" if "budget_total_water" in series.columns else "total_water"
    need = {"solver", "mode", "seed", "time_s", "cloud_cover", water, "rain_total", "water_relaxation_total"}
    missing = sorted(need - set(series.columns))
    if missing:
        raise ValueError(f"cycling time series lacks the column(s) {', '.join(missing)}")
    rows = []
    for (solver, mode, seed), run in series.groupby(["solver", "mode", "seed"], sort=False):
        run = run.sort_values("time_s")
        t = run["time_s"].to_numpy(np.float64)
        for k, w in enumerate(cycle_windows(run["cloud_cover"].to_numpy(), t)):
            a, b = run.iloc[int(np.searchsorted(t, w["start_s"]))], run.iloc[int(np.searchsorted(t, w["end_s"]))]
            window = run[(run["time_s"] >= w["start_s"]) & (run["time_s"] <= w["end_s"])]
            d = {key: float(b[col] - a[col]) for key, col in (("total_water", water), ("rain_total", "rain_total"),
                                                               ("water_relaxation_total", "water_relaxation_total"))}
            row = {"solver": solver, "mode": mode, "seed": seed, "cycle": k + 1, **w,
                   "d_total_water": d["total_water"], "rain": d["rain_total"],
                   "relaxation": d["water_relaxation_total"],
                   "closure": (d["total_water"] - (d["water_relaxation_total"] - d["rain_total"]))
                   / float(window[water].mean()),
                   "max_lwp": float(window["lwp_mean"].max()) if "lwp_mean" in window else float("nan"),
                   "latent_heat": (float(b["heat_latent_total"] - a["heat_latent_total"])
                                   if "heat_latent_total" in run and np.isfinite(b["heat_latent_total"])
                                   else float("nan"))}
            rows.append(row)
    return pd.DataFrame(rows, columns=["solver", "mode", "seed", "cycle", "start_s", "peak_s", "min_s", "end_s",
                                       "peak_cover", "min_cover", "d_total_water", "rain", "relaxation", "closure",
                                       "max_lwp", "latent_heat"])


def render_cycle_states(states_dir, out_dir, scene_name: str = "cycling", cpu: bool = False) -> list:
    """Render the compact states of :func:`cycle_states` (cycle_<mode>_<peak|min>.npz in `states_dir`):
    particles as cloud points (cloudpbf.render.render_particles), the grid's cloud field as a volume
    (render_volume).  Writes OUT/cycling_<mode>_<peak|min>.png; returns the paths written (none
    where pyvista cannot render: cloudpbf.render.render_or_note leaves a note instead).  ``cpu``: the states
    come from the CPU cycle (:func:`cpu_scene`), not the scene files."""
    base, adaptive = scene_pair(scene_name)
    if cpu:
        base, adaptive = cpu_scene(base), cpu_scene(adaptive)
    written = []
    for path in sorted(Path(states_dir).glob("cycle_*_*.npz")):
        mode, tag = path.stem[len("cycle_"):].rsplit("_", 1)
        with np.load(path) as z:
            state = {k: z[k] for k in z.files}
        when = f"{'cover peak' if tag == 'peak' else 'clearest moment after it'}, t = {float(state['time_s']):.0f} s"
        target = Path(out_dir) / f"cycling_{mode}_{tag}.png"
        if "position" in state:
            scene = adaptive if mode == "adaptive" else base
            title = f"{scene.name} ({mode} particles), {when}"
            done = render_or_note(render_particles, target, state, scene, title=title)
        else:
            title = f"{base.name} (grid), {when}"
            done = render_or_note(render_volume, target, state["cloud"], state["cell_size"], title=title)
        if done is not None:
            written.append(done)
    return written


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
        # seed 0 keeps every diagnostic state: the renders of a cycle's peak and clearest moment come from it
        keep = {"keep_snapshots": RENDER_SNAPSHOTS} if seed == 0 else {}
        out.append(("non-adaptive", seed, runs.RunSpec("particles", base, backend=ctx.backend, seed=seed,
                                                        snapshot_every=every, diagnostics_resolution=shape, **keep)))
        out.append(("adaptive", seed, runs.RunSpec("particles", adaptive, backend=ctx.backend, seed=seed,
                                                    snapshot_every=every, diagnostics_resolution=shape, **keep)))
        out.append(("grid", seed, runs.RunSpec("grid", base, seed=seed, resolution=shape, snapshot_every=every,
                                               **keep)))
    return out


def cycle_states(cycles: pd.DataFrame, budgets: pd.DataFrame, out_dir, seed: int = 0, cycle: int = 1,
                 clear_fraction: float = 0.1) -> list:
    """Compact states of each mode's run at its `cycle`-th cover peak and the clearest moment after it
    (the stored snapshots nearest peak_s and min_s of :func:`cycle_budgets`), for renders: particles keep
    every cloudy particle and `clear_fraction` of the clear ones (position, cloud, level); grid runs keep
    the cloud-water field.  Writes OUT/cycle_<mode>_<peak|min>.npz; returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for row in cycles[cycles["seed"] == seed].itertuples():
        window = budgets[(budgets["mode"] == row.mode) & (budgets["seed"] == seed) & (budgets["cycle"] == cycle)]
        if window.empty:
            continue
        res = RunResult.load(row.run_dir)
        stored = {}
        for path in res.snapshot_paths():
            with np.load(path) as z:
                stored[float(z["time_s"])] = path
        times = np.array(sorted(stored))
        for tag, when in (("peak", float(window["peak_s"].iloc[0])), ("min", float(window["min_s"].iloc[0]))):
            if not len(times):
                break
            path = stored[float(times[np.argmin(np.abs(times - when))])]
            with np.load(path) as z:
                state = {k: z[k] for k in z.files}
            if "position" in state:
                compact = compact_particles(state, CLOUD_RENDER_THRESHOLD, clear_fraction)
            else:
                compact = {"cloud": state["cloud"].astype(np.float32),
                           **{k: state[k] for k in ("cell_size", "origin") if k in state}}
            compact.update(time_s=state["time_s"], step=state["step"])
            target = out_dir / f"cycle_{row.mode}_{tag}.npz"
            np.savez_compressed(target, **compact)
            written.append(target)
    return written


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
            # the solver's own total water (particles: sum m (v + w), exact; grid: its field sum), the one
            # its budget terms close against (C4); total_water is the deposit grid's
            frame["budget_total_water"] = stats["solver_total_water" if "solver_total_water" in stats
                                                else "total_water"]
            for i, (key, value) in enumerate((("solver", solver), ("mode", mode), ("seed", seed))):
                frame.insert(i, key, value)
            frame["device"] = res.device
            frame["commit"] = ctx.commit
            series.append(frame)
    timeseries = (pd.concat(series, ignore_index=True) if series
                  else pd.DataFrame(columns=["solver", "mode", "seed", "time_s", "step", *SERIES_COLUMNS]))
    budgets = cycle_budgets(timeseries)
    devices = {(r["mode"], r["seed"]): r["device"] for r in rows}
    budgets["device"] = [devices.get((m, s)) for m, s in zip(budgets["mode"], budgets["seed"])]
    budgets["commit"] = ctx.commit
    out = {"cycling_cycles": pd.DataFrame(rows), "cycling_timeseries": timeseries, "cycling_budgets": budgets}
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
    typer.echo(f"wrote {ctx.data / 'cycling_cycles.csv'}, cycling_timeseries.csv, cycling_budgets.csv")


register(Study("cycling", order=35, sections=("compare",),
               outputs=("cycling_cycles.csv", "cycling_timeseries.csv", "cycling_budgets.csv"), command=cycling_command))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.cycling ARGS`` is ``cloudpbf cycling ARGS``."""
    return run_command(cycling_command, "cycling", argv)


if __name__ == "__main__":
    sys.exit(main())
