"""Stability map of the particle solver: one parameter at a time pushed away from a small cloud scene.

Swept: the time step dt (s), the PBF iterations, the ground heating rate S_e (eq. 5, multiples of
the scene's, up to the schema's 100 K/s) and alpha*dt (the phase-transition rate of eq. 9 times dt;
the exact exponential update must stay stable for any value).  The alpha*dt cases start 20%
supersaturated (initial_vapor_ratio 1.2) so that the phase transition and its latent heat act from
the first step.  Every case runs a fixed number of steps with stats() after every
step; it is unstable when the solver raises (NaN/Inf, a speed above pbf.max_velocity, a mean density
error above pbf.max_density_error) or when particles leave the domain through a wall, and the row
names the reason, the step and the particle ids.  NaN never reaches the data: the failing state is not
analysed, and max_speed / density_error_mean are those of the last good step.

Outputs in OUT/data: stress.csv (parameter, value, stable, reason, step, particles, max_speed,
density_error_mean, then the case's dt, iterations, heating_rate, phase_rate, alpha_dt, steps,
last_good_step, device, commit, run_dir) and stress_summary.json (the largest dt up to which every
tried dt is stable).
"""
from __future__ import annotations

import pandas as pd
import typer

from bench import runs
from bench.cli_common import (DEFAULT_OUT, Backend, BackendOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName, ScaleOpt,
                              SchedulerOpt, WorkersOpt, refusals, study_context)
from bench.studies.context import StudyContext
from bench.studies.registry import Study, register
from bench.studies.scales import scale_scene
from pbf_cuda.scene import Scene, load_scene

SCENE = "growing"
HEATING_FACTORS = (1.0, 10.0, 100.0, 1000.0, 10000.0)
MAX_HEATING_RATE = 100.0     # K/s: the scene schema's bound
SUPERSATURATION = 1.2        # initial v / saturation of the alpha*dt cases: condensation from the first step


def stress_cases(base: Scene, scale) -> list[tuple[str, float, Scene]]:
    """(parameter, value, scene) for every case."""
    dt = base.time.dt
    cases = [("dt", float(v), base.replace(**{"time.dt": float(v)})) for v in scale.stress_dt]
    cases += [("iterations", int(v), base.replace(**{"pbf.iterations": int(v)})) for v in scale.stress_iterations]
    rate = base.atmosphere.heating_rate
    for value in sorted({min(rate * factor, MAX_HEATING_RATE) for factor in HEATING_FACTORS}):
        cases.append(("heating_rate", value, base.replace(**{"atmosphere.heating_rate": value})))
    wet = base.replace(**{"atmosphere.initial_vapor_ratio": SUPERSATURATION})
    cases += [("alpha_dt", float(v), wet.replace(**{"atmosphere.phase_rate": float(v) / dt}))
              for v in scale.stress_alpha_dt]
    return cases


def stress_specs(ctx: StudyContext, scene_name: str = SCENE) -> list[tuple[str, float, runs.RunSpec]]:
    scale = ctx.scale
    base = scale_scene(load_scene(scene_name), scale.stress_particles)
    base = base.replace(**{"time.steps": scale.stress_steps, "time.snapshot_every": scale.stress_steps,
                           "time.check_every": 1})
    return [(parameter, value, runs.RunSpec("particles", scene, backend=ctx.backend, seed=0, record_steps=True,
                                            diagnostics=False, keep_snapshots=0))
            for parameter, value, scene in stress_cases(base, scale)]


def largest_stable_dt(frame: pd.DataFrame) -> dict:
    """The largest dt such that it and every smaller tried dt ran stably."""
    dts = frame[frame.parameter == "dt"].sort_values("value")
    largest, first_bad = None, None
    for row in dts.itertuples():
        if not row.stable:
            first_bad = row.value
            break
        largest = row.value
    return {"largest_stable_dt": largest, "smallest_unstable_dt": first_bad,
            "dt_tried": dts.value.tolist()}


def run_stress(ctx: StudyContext, scene_name: str = SCENE) -> pd.DataFrame:
    plan = stress_specs(ctx, scene_name)
    results = ctx.run_parallel([spec for _, _, spec in plan], "stress")
    rows = []
    for (parameter, value, spec), res in zip(plan, results):
        steps = res.steps_table()
        last = steps.iloc[-1] if len(steps) else {}
        scene = spec.scene
        rows.append({
            "parameter": parameter, "value": value, "stable": bool(res.stable), "reason": res.reason or "",
            "step": res.step, "particles": " ".join(map(str, res.particles)),
            "max_speed": last.get("max_speed"), "density_error_mean": last.get("density_error_mean"),
            "dt": scene.time.dt, "iterations": scene.pbf.iterations,
            "heating_rate": scene.atmosphere.heating_rate, "phase_rate": scene.atmosphere.phase_rate,
            "alpha_dt": scene.atmosphere.phase_rate * scene.time.dt, "steps": spec.total_steps,
            "n_particles": res.max_particles, "last_good_step": res.last_good_step, "device": res.device,
            "commit": ctx.commit, "run_dir": str(res.path)})
    frame = pd.DataFrame(rows)
    runs.write_csv(frame, ctx.data / "stress.csv")
    runs.atomic_write_json(ctx.data / "stress_summary.json",
                           {**largest_stable_dt(frame), "scene": scene_name, "steps": ctx.scale.stress_steps,
                            "particles": plan[0][2].scene.estimated_particles(), "commit": ctx.commit})
    return frame


STRESS_DT = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0)    # s
STRESS_ITERATIONS = (1, 2, 4, 8)
STRESS_ALPHA_DT = (0.1, 1.0, 10.0, 100.0, 1000.0)                                 # phase_rate * dt

def stress_command(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
                   backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
                   quiet: QuietOpt = False) -> None:
    """Stability map: dt, iterations, heating rate and alpha*dt; the largest stable dt."""
    import json
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet) as ctx:
        with refusals():
            frame = run_stress(ctx)
    typer.echo(frame[["parameter", "value", "stable", "step", "reason"]].to_string(index=False))
    summary = json.loads((ctx.data / "stress_summary.json").read_text())
    typer.echo(f"largest stable dt: {summary['largest_stable_dt']} s")
    typer.echo(f"wrote {ctx.data / 'stress.csv'}")


register(Study("stress", order=50, run=lambda ctx, scene: run_stress(ctx), sections=("stress",),
               outputs=("stress.csv", "stress_summary.json"),
               scale={"stress_particles": {"smoke": 2000, "cpu": 10_000, "gpu": 100_000},
                      "stress_steps": {"smoke": 30, "cpu": 100, "gpu": 200},
                      "stress_dt": dict.fromkeys(("smoke", "cpu", "gpu"), STRESS_DT),
                      "stress_iterations": dict.fromkeys(("smoke", "cpu", "gpu"), STRESS_ITERATIONS),
                      "stress_alpha_dt": dict.fromkeys(("smoke", "cpu", "gpu"), STRESS_ALPHA_DT)},
               command=stress_command))
