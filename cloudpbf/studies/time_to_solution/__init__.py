"""Time to solution at equal error: the cheapest settings of the particle solver that meet an error budget.

For one cloud scene (``growing`` by default; ``cumulus``, ``cycling``) the study runs, each over ``seeds`` noise
seeds and every one until the same simulated time T (the scene's ``time.steps`` x its dt; ``RunSpec.end_time``,
so that CFL-controlled runs cover the same period as fixed-step ones):

* the spacing x dt grid: the scale's spacings (at the GPU scale 68, 54, 43 and 34 m for ``growing``: the
  scene's own spacing times 2, 2^(2/3), 2^(1/3), 1, halving the particle count each step) x fixed steps (1, 2
  and 4 s), and the CFL-controlled step (``time.cfl`` 0.5, dt_max 8 s) at every spacing;
* one factor at a time around today's defaults (the scene's spacing and dt, 2 s): ``pbf.iterations`` 2,
  ``pbf.divergence_iterations`` 2, ``time.cfl`` 0.8, and the adaptive twin (``<scene>_adaptive``, its finest
  level at the default spacing); more iterations, smaller CFL numbers and dt 8 s are left out to bound the cost;
* the reference, never one of the compared settings: the finest spacing at the smallest step (0.5 s) with
  8 density iterations and the scene's 4 projection iterations (at a quarter of the default step, four
  times their iterations per simulated second).

Error of a setting (as in the adaptive study): its seed-mean series of cloud cover, cloudy volume and mean LWP,
each interpolated onto N times evenly spaced in (0, T], against the reference's seed mean, relative L2 over
the times; ``error`` is the mean of the three.  ``noise_floor`` is the error of half the reference's seeds
against the other half, divided by sqrt(2) (the seed noise of an n-seed mean against another).  Cost:
``wall_per_sim_s``, the solver's wall time per simulated second, the run loop's step time after the first
step (allocations) over the simulated time after it, seed mean.  A setting enters the verdict only when every
seed ran stably to T (``time.max_cfl``, the scene's, marks a step too large as unstable).

The verdict: for each error budget (the defaults' own error, half and twice it, and the larger of the defaults'
error and the noise floor, below which errors are indistinguishable) the cheapest qualifying setting within it;
the front (cloudpbf.pareto); the speed-up at the defaults' error (their cost over the cheapest's).  Intervals: the
seeds resampled :data:`BOOTSTRAP_REPLICATES` times (the whole analysis redone each time): 5-95% of every error,
cost and the speed-up, and the share of resamples reaching :data:`GOAL_SPEEDUP`.  Outputs (OUT/data, suffix
``_<scene>`` but for growing): ``time_to_solution.csv``, ``_runs.csv``, ``_series.csv`` (what ``--from-data``
reads) and ``_verdict.json``, with device and commit; ``--estimate`` prints the plan, ``--groups`` runs a part.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import click
import numpy as np
import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
from cloudpbf.studies.plans import scene_file_suffix
from cloudpbf.studies.registry import GlanceCard, ReportSection, Study, register
from cloudpbf.studies.time_to_solution.analysis import (BOOTSTRAP_REPLICATES, BUDGET_FACTORS, GOAL_SPEEDUP,  # noqa: F401
                                                     SERIES, analyse, build_verdict, cheapest)
from cloudpbf.studies.time_to_solution.report import time_to_solution_card, time_to_solution_section
from cloudpbf.studies.scales import scale_scene
from pbf_cuda.scene import Scene, load_scene

SCENES = ("growing", "cumulus", "cycling")
SMOKE_BOX = {"domain.size": [1200.0, 1600.0, 1200.0]}


@dataclass(frozen=True)
class Sizes:
    """What the study runs at one scale (spacings as multiples of the scale's default spacing)."""
    spacing_ratios: tuple = (2.0, 2 ** (2 / 3), 2 ** (1 / 3), 1.0)
    dts: tuple = (1.0, 2.0, 4.0)
    grid_cfls: tuple = (0.5,)               # CFL-controlled steps at every spacing of the grid
    cfls: tuple = (0.8,)                    # more CFL-controlled steps at the default spacing
    dt_max: float = 8.0
    iterations: tuple = (2,)
    divergence_iterations: tuple = (2,)
    adaptive: bool = True
    reference_dt: float = 0.5
    reference_iterations: int = 8
    reference_divergence_iterations: int = 4
    default_dt: float | None = None         # None: the scene's
    end_time: float | None = None           # None: the scene's time.steps x its dt
    times: int = 4                          # analysis times in (0, T] (each a deposit of every particle)
    box: dict | None = None                 # scene overrides (smoke: a small box) and its default spacing
    spacing: float | None = None
    analysis_grid: tuple = (32, 32, 32)

    def __str__(self) -> str:
        """The sizes in a line (the scale table and the docs' studies page show it)."""
        g = lambda v: ", ".join(f"{x:.3g}" for x in v) or "none"  # noqa: E731
        where = (f"box {self.box['domain.size']} m, spacing {self.spacing:g} m" if self.box
                 else "the scale's spacing of the scene")
        return (f"{where} x ({g(self.spacing_ratios)}); dt {g(sorted(set(self.dts) | {self.default_dt or 2.0}))} s; "
                f"CFL {g(self.grid_cfls)} at every spacing, {g(self.cfls)} at the default (dt_max {self.dt_max:g} s); "
                f"iterations {g(self.iterations)}; projection iterations {g(self.divergence_iterations)}; adaptive "
                f"twin {'yes' if self.adaptive else 'no'}; reference dt {self.reference_dt:g} s, "
                f"{self.reference_iterations} / {self.reference_divergence_iterations} iterations; "
                f"{self.times} analysis times to {f'{self.end_time:g} s' if self.end_time else 'the scene end'}")


SIZES = {"gpu": Sizes(), "cpu": Sizes(),  # smoke: a box whose first cloud comes near 480 s; no adaptive twin (too
         # coarse); CFL 0.3 with steps up to 16 s (at 0.5 the step stays at 8 s)
         "smoke": Sizes(spacing_ratios=(1.26, 1.0), dts=(8.0,), grid_cfls=(), cfls=(0.3,), iterations=(2,),
                        dt_max=16.0, divergence_iterations=(), adaptive=False, reference_dt=4.0, default_dt=8.0,
                        end_time=640.0, times=4, box=SMOKE_BOX, spacing=120.0, analysis_grid=(16, 16, 16))}


@dataclass(frozen=True)
class Setting:
    """One setting of the study (all its seeds share it)."""
    name: str
    group: str              # grid | iterations | divergence | cfl | adaptive | reference
    spacing_m: float        # uniform spacing (adaptive: the finest level's)
    dt: float               # the fixed step, or the first one where cfl > 0
    cfl: float = 0.0
    iterations: int = 0     # 0: the scene's
    divergence_iterations: int = 0
    adaptive: bool = False
    default: bool = False   # today's defaults: the scene's spacing, dt and iterations


def settings(base: Scene, sizes: Sizes) -> list[Setting]:
    """Every setting of the study, for `base` (the scene at its scale), without duplicates."""
    s0 = base.particles.spacing
    dt0 = sizes.default_dt or base.time.dt
    it0, div0 = base.pbf.iterations, base.pbf.divergence_iterations
    out: dict[str, Setting] = {}

    def add(group, spacing, dt, cfl=0.0, it=0, div=0, adaptive=False):
        it, div = (0 if it == it0 else it), (0 if div == div0 else div)
        name = f"{spacing:.3g}m-" + (f"cfl{cfl:g}" if cfl else f"dt{dt:g}")
        name += (f"-it{it}" if it else "") + (f"-div{div}" if div else "") + ("-adaptive" if adaptive else "")
        if group == "reference":
            name = "reference-" + name
        default = spacing == s0 and dt == dt0 and not (cfl or it or div or adaptive) and group != "reference"
        out.setdefault(name, Setting(name, group, float(spacing), float(dt), float(cfl), int(it), int(div),
                                     adaptive, default))

    spacings = [s0 * r for r in sizes.spacing_ratios]
    for s in spacings:
        for dt in sorted(set(sizes.dts) | {dt0}):
            add("grid", s, dt)
        for c in sizes.grid_cfls:
            add("grid", s, dt0, cfl=c)
    for it in sizes.iterations:
        add("iterations", s0, dt0, it=it)
    for div in sizes.divergence_iterations:
        add("divergence", s0, dt0, div=div)
    for c in sizes.cfls:
        add("cfl", s0, dt0, cfl=c)
    if sizes.adaptive:
        add("adaptive", s0, dt0, adaptive=True)
    add("reference", min(spacings), sizes.reference_dt, it=sizes.reference_iterations,
        div=sizes.reference_divergence_iterations)
    return list(out.values())


def scaled_scene(scene_name: str, scale_name: str, particles: int | None, sizes: Sizes,
                 adaptive: bool = False) -> Scene:
    """The scene (or its adaptive twin, at the same coarsening) as this scale runs it, at its default spacing."""
    base = load_scene(scene_name)
    if sizes.box is not None:
        scaled = base.replace(**sizes.box, **{"particles.spacing": float(sizes.spacing)})
    else:
        scaled = scale_scene(base, particles if scale_name != "gpu" else None)
    if not adaptive:
        return scaled
    twin = load_scene(f"{scene_name}_adaptive")
    ratio = twin.particles.spacing / base.particles.spacing            # level 0 over the uniform spacing
    keep = {k: v for k, v in (sizes.box or {}).items()}
    return twin.replace(**keep, **{"particles.spacing": scaled.particles.spacing * ratio,
                                   "atmosphere.heating_depth": scaled.atmosphere.heating_depth,
                                   "atmosphere.heating_rate": scaled.atmosphere.heating_rate})


def end_time(base: Scene, sizes: Sizes) -> float:      # the sizes' own, else the scene's time.steps x its dt
    return float(sizes.end_time or base.time.steps * base.time.dt)


def setting_scene(setting: Setting, scene_name: str, scale_name: str, particles: int | None, sizes: Sizes,
                  base: Scene) -> tuple[Scene, int]:
    """(scene, step cap) of a setting: spacing, step (fixed or CFL-controlled), iterations."""
    t_end = end_time(base, sizes)
    if setting.adaptive:
        scene = scaled_scene(scene_name, scale_name, particles, sizes, adaptive=True)
        scene = scene.replace(**{"particles.spacing": scene.particles.spacing * setting.spacing_m
                                 / base.particles.spacing})
    else:
        scene = base.with_spacing(setting.spacing_m)
    over = {"time.dt": setting.dt}
    if setting.iterations:
        over["pbf.iterations"] = setting.iterations
    if setting.divergence_iterations:
        over["pbf.divergence_iterations"] = setting.divergence_iterations
    if setting.cfl:
        dt_min = sizes.reference_dt / 4.0
        over.update({"time.cfl": setting.cfl, "time.dt_min": dt_min, "time.dt_max": sizes.dt_max,
                     "time.dt": min(max(setting.dt, dt_min), sizes.dt_max)})
        cap = math.ceil(t_end / dt_min)
    else:
        cap = None
    # rows every T / times at the fixed step, on the analysis times; a CFL-controlled run's steps cannot be planned
    # to land on them: its rows bracket each analysis time instead (RunSpec.diagnostic_times, set in plan())
    steps = cap or max(1, math.ceil(t_end / setting.dt * (1 - 1e-9)))
    over["time.snapshot_every"] = steps if setting.cfl else max(1, int(round(t_end / sizes.times / setting.dt)))
    over["time.steps"] = steps
    return scene.replace(**over), steps


GROUPS = ("grid", "iterations", "divergence", "cfl", "adaptive")   # of settings (with the reference)


def analysis_times(t_end: float, sizes: Sizes) -> np.ndarray:
    """The times, s, at which the series are compared: `sizes.times` of them, evenly spaced in (0, T]."""
    return np.linspace(0.0, t_end, int(sizes.times) + 1)[1:]


def plan(ctx, scene_name: str, seeds: int, sizes: Sizes | None = None,
         groups: tuple | None = None) -> tuple[list, list, Sizes, Scene]:
    """(settings, [(setting, seed, RunSpec)], sizes, base scene) of the study at ctx's scale; with `groups`
    only the settings of those groups, and always the defaults and the reference (a part of the study that
    a later run of all groups finds in the run cache)."""
    sizes = sizes or getattr(ctx.scale, "time_to_solution", None) or SIZES[ctx.scale.name]
    base = scaled_scene(scene_name, ctx.scale.name, ctx.scale.particles, sizes)
    if sizes.default_dt:
        base = base.replace(**{"time.dt": sizes.default_dt})
    study = [s for s in settings(base, sizes)
             if groups is None or s.group in groups or s.default or s.group == "reference"]
    t_end = end_time(base, sizes)
    times = tuple(float(t) for t in analysis_times(t_end, sizes))
    entries = []
    for setting in study:
        scene, steps = setting_scene(setting, scene_name, ctx.scale.name, ctx.scale.particles, sizes, base)
        for seed in range(seeds):
            spec = runs.RunSpec("particles", scene, backend=ctx.backend, seed=seed, steps=steps, keep_snapshots=0,
                                checkpoint_every=steps, diagnostics_resolution=sizes.analysis_grid,
                                warmup_steps=1, end_time=t_end, diagnostic_times=times if setting.cfl else ())
            entries.append((setting, seed, spec))
    return study, entries, sizes, base


# H100 cost model of the estimate: ~1 ms per step at 100k particles, ~4 at 800k (issue #53); a run's set-up
# (0.3 s + 1 us per particle) and its diagnostics rows (deposits on the host, ~1 us per particle each): guesses
MS_FIXED, MS_PER_PARTICLE, S_PER_RUN, S_PER_PARTICLE = 0.57, 4.3e-6, 0.3, 1e-6


def estimate(entries, sizes: Sizes, base: Scene) -> dict:
    """Runs, steps, particle-steps and a rough GPU time (s) of the plan (CFL steps taken as the default step
    times cfl / 0.67, the CFL number of the defaults at 34 m, within [dt_min, dt_max])."""
    t_end = end_time(base, sizes)
    steps = particle_steps = step_s = other_s = 0.0
    for setting, _, spec in entries:
        scene = spec.scene
        n = scene.estimated_particles() * (2 ** scene.adaptive.max_level / 2 if scene.adaptive.enabled else 1)
        guess = setting.dt * setting.cfl / 0.67 * setting.spacing_m / base.particles.spacing
        dt = setting.dt if not setting.cfl else min(sizes.dt_max, max(sizes.reference_dt / 4, guess))
        k, factor = t_end / dt, 1 + 0.1 * (scene.pbf.iterations - 4) + 0.05 * (scene.pbf.divergence_iterations - 4)
        steps, particle_steps = steps + k, particle_steps + k * n
        rows = min(k, spec.total_steps) / spec.diagnostic_every + 2
        step_s += k * (MS_FIXED + MS_PER_PARTICLE * n) * factor / 1e3
        other_s += S_PER_RUN + (1 + rows) * n * S_PER_PARTICLE
    return {"runs": len(entries), "steps": int(steps), "particle_steps": float(particle_steps), "simulated_s": t_end,
            "step_s_estimate": step_s, "other_s_estimate": other_s, "gpu_s_estimate": step_s + other_s}


def describe_estimate(est: dict) -> str:
    return (f"{est['runs']} runs, {est['steps']:,} steps, {est['particle_steps']:.3g} particle-steps, "
            f"{est['simulated_s']:g} s simulated each; on one H100 about {est['gpu_s_estimate'] / 60:.1f} min "
            f"({est['step_s_estimate'] / 60:.1f} in steps, {est['other_s_estimate'] / 60:.1f} in set-up and "
            f"diagnostics; a rough model)")


# ---- analysis --------------------------------------------------------------------------------------
def run_row(setting: Setting, seed: int, spec, result, t_end: float, device: str, commit: str) -> dict:
    """One run's row: completeness, wall time per simulated second, step statistics."""
    info = result.info
    time_s = info.get("time_s")
    complete = bool(result.stable) and time_s is not None and float(time_s) >= t_end * (1 - 1e-6)
    stats = result.stats() if result.stable else pd.DataFrame()
    first_dt = float(spec.scene.time.dt)          # the first step, fixed or CFL-controlled, is time.dt
    wall = (info.get("step_ms") or math.nan) * (info.get("timed_steps") or 0) / 1e3     # steps after the first
    wall_per_sim_s = wall / (float(time_s) - first_dt) if complete and float(time_s) > first_dt else math.nan
    reason = info.get("reason") or (None if complete else f"stopped at t = {time_s} s before {t_end:g} s")
    return {"setting": setting.name, "seed": int(seed), "stable": bool(result.stable), "complete": complete,
            "reason": reason, "steps": info.get("step"), "time_s": time_s, "wall_per_sim_s": wall_per_sim_s,
            "ms_per_step": info.get("step_ms"), "particles": info.get("max_particles"),
            "max_cfl": float(stats["cfl"].max()) if "cfl" in stats and len(stats) else math.nan,
            "device": info.get("device") or device, "commit": commit, "run_dir": str(result.path)}


def run_series(result, times: np.ndarray) -> dict | None:
    """The run's cover, volume and LWP series interpolated onto `times` (None: unstable or no rows)."""
    stats = result.stats() if result.stable else pd.DataFrame()
    if not len(stats):
        return None
    t = stats["time_s"].to_numpy(float)
    return {key: np.interp(times, t, stats[col].to_numpy(float)) if col in stats else np.full(len(times), np.nan)
            for key, col in SERIES}


def meta_frame(study: list[Setting]) -> pd.DataFrame:
    return pd.DataFrame([dataclasses.asdict(s) for s in study]).rename(columns={"name": "setting"})


def write_outputs(data: Path, scene_name: str, per_setting, per_run, series, verdict) -> None:
    sfx = scene_file_suffix(scene_name)
    runs.write_csv(per_setting, data / f"time_to_solution{sfx}.csv")
    runs.write_csv(per_run, data / f"time_to_solution_runs{sfx}.csv")
    runs.write_csv(series, data / f"time_to_solution_series{sfx}.csv")
    runs.atomic_write_json(data / f"time_to_solution_verdict{sfx}.json", verdict)


def run_time_to_solution(ctx, scene_name: str = "growing", seeds: int = 8, replicates: int = BOOTSTRAP_REPLICATES,
                         sizes: Sizes | None = None, groups: tuple | None = None) -> dict:
    """Run (or read) the study for one scene; write its CSVs and verdict into ctx.data."""
    if scene_name not in SCENES:
        raise ValueError(f"scene = {scene_name!r}: allowed {', '.join(SCENES)}")
    if not 2 <= int(seeds) <= 100:
        raise ValueError(f"seeds = {seeds}: allowed 2..100 (seed means and intervals need at least two)")
    study, entries, sizes, base = plan(ctx, scene_name, int(seeds), sizes, groups)
    est = estimate(entries, sizes, base)
    click.echo(f"time-to-solution {scene_name} ({ctx.scale.name}, {len(study)} settings x {seeds} seeds): "
               + describe_estimate(est), err=True)     # also with --quiet: the size of what is about to run
    results = ctx.run_parallel([e[2] for e in entries], f"time-to-solution {scene_name}")
    device = next((r.device for r in results if getattr(r, "device", None)), "unknown")
    t_end = end_time(base, sizes)
    times = analysis_times(t_end, sizes)
    rows, series = [], []
    for (setting, seed, spec), result in zip(entries, results):
        rows.append(run_row(setting, seed, spec, result, t_end, device, ctx.commit))
        sig = run_series(result, times) if rows[-1]["complete"] else None
        if sig is not None:
            series += [{"setting": setting.name, "seed": seed, "time_s": float(t),
                        **{k: float(sig[k][j]) for k, _ in SERIES}}
                       for j, t in enumerate(times)]
    per_run = pd.DataFrame(rows)
    series = pd.DataFrame(series, columns=["setting", "seed", "time_s"] + [k for k, _ in SERIES])
    extra = {"scene": scene_name, "scale": ctx.scale.name, "simulated_s": t_end, "device": device,
             "commit": ctx.commit, "estimate": est}
    per_setting, verdict = analyse(per_run, series, meta_frame(study), extra, replicates)
    per_setting["device"], per_setting["commit"] = device, ctx.commit
    write_outputs(ctx.data, scene_name, per_setting, per_run, series, verdict)
    return {"settings": per_setting, "runs": per_run, "series": series, "verdict": verdict}


def rebuild(data: Path, scene_name: str = "growing", replicates: int = BOOTSTRAP_REPLICATES) -> dict:
    """The verdict again from the study's CSVs in `data` (nothing run); device and commit those of the runs."""
    sfx = scene_file_suffix(scene_name)
    paths = {k: Path(data) / f"time_to_solution{k}{sfx}.csv" for k in ("", "_runs", "_series")}
    for p in paths.values():
        if not p.is_file():
            raise FileNotFoundError(f"{p}: missing (run `cloudpbf time-to-solution --scene {scene_name}` first)")
    old = Path(data) / f"time_to_solution_verdict{sfx}.json"
    extra = json.loads(old.read_text()) if old.is_file() else {"scene": scene_name}
    extra = {k: extra[k] for k in ("scene", "scale", "simulated_s", "device", "commit", "estimate") if k in extra}
    per_setting = pd.read_csv(paths[""])
    meta = per_setting[["setting", "group", "default", "spacing_m", "dt", "cfl", "iterations",
                        "divergence_iterations", "adaptive"]]
    per_run, series = pd.read_csv(paths["_runs"]), pd.read_csv(paths["_series"])
    for col in ("device", "commit"):     # without the old verdict: the runs' own, where they agree
        values = per_setting[col].dropna().astype(str).unique() if col in per_setting else []
        if col not in extra and len(values) == 1:
            extra[col] = values[0]
    frame, verdict = analyse(per_run, series, meta, extra, replicates)
    for col in ("device", "commit"):
        frame[col] = per_setting[col] if col in per_setting else extra.get(col)
    write_outputs(Path(data), scene_name, frame, per_run, series, verdict)
    return {"settings": frame, "verdict": verdict}


def time_to_solution_command(
    scene: Annotated[str, typer.Option(help="growing (default), cumulus or cycling")] = "growing",
    seeds: Annotated[int, typer.Option(min=2, max=100, help="noise seeds per setting (>= 8 for the verdict at "
                                                               "the GPU scale)")] = 8,
    resamples: Annotated[int, typer.Option(min=0, max=100000, help="resamples of the seeds for the intervals")
                         ] = BOOTSTRAP_REPLICATES,
    groups: Annotated[Optional[str], typer.Option(
        help=f"only these groups of settings, comma-separated ({', '.join(GROUPS)}), with the defaults and the "
             "reference: a study in parts that fit a time limit (a later run of all finds them cached)")] = None,
    estimate_only: Annotated[bool, typer.Option("--estimate", help="print the plan's runs, steps and a rough GPU "
                                                                   "time, run nothing")] = False,
    from_data: Annotated[bool, typer.Option("--from-data", help="run nothing: rebuild the verdict from the "
                                                                 "study's CSVs in OUT/data")] = False,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
) -> None:
    """Time to solution at equal error: dt (fixed, CFL), iterations, spacing, adaptivity; the cheapest settings."""
    if scene not in SCENES:
        raise click.UsageError(f"--scene {scene!r}: allowed {', '.join(SCENES)}")
    chosen = None
    if groups is not None:
        chosen = tuple(g.strip() for g in groups.split(",") if g.strip())
        unknown = [g for g in chosen if g not in GROUPS]
        if unknown or not chosen:
            raise click.UsageError(f"--groups {groups!r}: allowed {', '.join(GROUPS)} (comma-separated)")
    if from_data:
        try:
            result = rebuild(Path(out) / "data", scene, resamples)
        except (FileNotFoundError, ValueError, KeyError) as exc:
            raise click.UsageError(str(exc)) from None
        typer.echo(result["verdict"]["verdict"])
        return
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            if estimate_only:
                study, entries, sizes, base = plan(ctx, scene, seeds, groups=chosen)
                est = estimate(entries, sizes, base)
                typer.echo(f"{len(study)} settings x {seeds} seeds: " + describe_estimate(est))
                typer.echo(", ".join(s.name for s in study))
                return
            result = run_time_to_solution(ctx, scene, seeds, resamples, groups=chosen)
    cols = ["setting", "group", "stable_seeds", "wall_per_sim_s", "error", "error_p05", "error_p95", "front"]
    frame = result["settings"]
    typer.echo(frame[[c for c in cols if c in frame]].to_string(index=False))
    typer.echo(result["verdict"]["verdict"])


register(Study("time-to-solution", order=47, sections=("time_to_solution",),
               report=(ReportSection("time_to_solution", "Time to solution at equal error",
                                     time_to_solution_section, 8, "Time to solution"),),
               glance=(GlanceCard(time_to_solution_card, 50),),
               outputs=("time_to_solution.csv", "time_to_solution_runs.csv", "time_to_solution_series.csv",
                        "time_to_solution_verdict.json"),
               scale={"time_to_solution": SIZES},
               command=time_to_solution_command))
