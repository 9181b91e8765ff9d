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

Two 2-D maps follow: dt against the PBF iterations (parameter "dt x iterations") and dt against the
heating rate (parameter "dt x heating_rate", multiples of the scene's rate); each case's row carries
its dt, iterations and heating rate.

Stable is not usable: a run can end without blowing up while it no longer solves the scene (a fluid
collapsed onto the floor holds no density error at all).  A case is **usable** when it is stable, its
result is within REFERENCE_ERROR_LIMIT of a converged reference of the same scene, its mean density
error |rho/rho0 - 1| stayed at most DENSITY_ERROR_LIMIT over every step, and no step multiplied the
kinetic energy by more than ENERGY_JUMP_LIMIT (the runaway that precedes a blow-up; physical growth
from the heating is far slower per step).  The reference is the case's scene at dt / REFERENCE_DT_DIVISOR
with REFERENCE_ITERATIONS PBF iterations over the same simulated time (one reference serves every case
that differs only in its iterations); it is run for the cases that pass the other checks.  The smoke scale
(the CI demo) uses a cheaper reference (dt / 2, 8 iterations) for the dt and iterations lines and the
dt x iterations map only (they share their references); its other cases have none and are not usable
(the scale table's stress_reference_* fields).  The error (``reference_error``, :func:`reference_error`)
is the larger of the mass centre's distance from the reference's in particle spacings and the mean
temperature's distance from the reference's relative to the reference's change of it (at least
REFERENCE_TEMPERATURE_FLOOR), both at the end of the run.

Outputs in OUT/data: stress.csv (parameter, value, stable, usable, reason, step, particles, max_speed,
density_error_mean (last step), density_error_max (largest per-step mean), energy_jump (largest
per-step kinetic-energy ratio), reference_error, reference_dt, reference_iterations, reference_reason
(why a case has no reference error: not run, the reference blew up), then the case's dt, iterations,
heating_rate, phase_rate, alpha_dt, steps, last_good_step, device, commit, run_dir) and stress_summary.json
(the largest dt up to which every tried dt is stable, the largest up to which every tried dt is usable, and
the usable bound in words).
"""
from __future__ import annotations

import pandas as pd
import typer

from bench import runs
from bench.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
from bench.studies.context import StudyContext
from bench.studies.registry import ReportSection, Study, register
from bench.studies.scales import scale_scene
from pbf_cuda.scene import Scene, load_scene

SCENE = "growing"
HEATING_FACTORS = (1.0, 10.0, 100.0, 1000.0, 10000.0)
MAX_HEATING_RATE = 100.0     # K/s: the scene schema's bound
SUPERSATURATION = 1.2        # initial v / saturation of the alpha*dt cases: condensation from the first step
DENSITY_ERROR_LIMIT = 0.01   # usable: mean |rho/rho0 - 1| at most 1% at every step (eq. 1)
ENERGY_JUMP_LIMIT = 2.0      # usable: no step more than doubles the kinetic energy
MAP_HEATING_FACTORS = (1.0, 10.0, 100.0)
REFERENCE_DT_DIVISOR = 4       # the converged reference: dt / 4 ... (the cpu and gpu scales)
REFERENCE_ITERATIONS = 16      # ... with 16 PBF iterations, over the same simulated time
REFERENCE_ERROR_LIMIT = 0.1    # usable: within 10% of the reference (reference_error)
REFERENCE_TEMPERATURE_FLOOR = 1.0   # K: the smallest temperature change the relative error divides by


def usable_bound_text(divisor: float = REFERENCE_DT_DIVISOR, iterations: int = REFERENCE_ITERATIONS) -> str:
    """The usable bound as the study's outputs and the report's maps state it."""
    return (f"error against a converged reference (dt/{divisor:g}, {iterations} iterations, "
            f"same simulated time) <= {REFERENCE_ERROR_LIMIT:g}, density error <= {100 * DENSITY_ERROR_LIMIT:g}% "
            f"at every step, no step more than {ENERGY_JUMP_LIMIT:g}x the kinetic energy")


def reference_error(steps: pd.DataFrame, reference: pd.DataFrame, spacing: float) -> float:
    """max(|z_c - z_c,ref| / spacing, |T - T_ref| / max(|T_ref - T_ref,0|, REFERENCE_TEMPERATURE_FLOOR)) at the end of
    both runs (z_c the mass centre's height, T the mean temperature, T_ref,0 the reference's first recorded step);
    NaN where either run recorded neither."""
    if not len(steps) or not len(reference):
        return float("nan")
    end, ref = steps.iloc[-1], reference.iloc[-1]
    errors = []
    if "mass_centre_height" in steps and "mass_centre_height" in reference:
        errors.append(abs(float(end["mass_centre_height"]) - float(ref["mass_centre_height"])) / spacing)
    if "mean_temperature" in steps and "mean_temperature" in reference:
        change = abs(float(ref["mean_temperature"]) - float(reference["mean_temperature"].iloc[0]))
        errors.append(abs(float(end["mean_temperature"]) - float(ref["mean_temperature"]))
                      / max(change, REFERENCE_TEMPERATURE_FLOOR))
    finite = [e for e in errors if e == e]
    return max(finite) if finite else float("nan")


def usable_mask(frame: pd.DataFrame, density_limit: float = DENSITY_ERROR_LIMIT,
                energy_limit: float = ENERGY_JUMP_LIMIT, reference_limit: float | None = REFERENCE_ERROR_LIMIT
                ) -> pd.Series:
    """Stable, within `reference_limit` of the converged reference (``reference_error``; a case without one is not
    usable; ``reference_limit=None`` leaves this check out, for the cases whose reference is still to run),
    density error within `density_limit` (the per-step maximum where recorded, else the last step's) and
    kinetic-energy jumps within `energy_limit` (where recorded). An unstable run is never usable."""
    stable = frame["stable"].astype(str).str.lower().isin(("true", "1"))
    density = pd.to_numeric(frame.get("density_error_mean", pd.Series(index=frame.index, dtype=float)),
                            errors="coerce")
    if "density_error_max" in frame.columns:     # the per-step maximum where recorded
        density = pd.to_numeric(frame["density_error_max"], errors="coerce").fillna(density)
    ok = stable & (density <= density_limit)
    if "energy_jump" in frame.columns:
        jump = pd.to_numeric(frame["energy_jump"], errors="coerce")
        ok &= ~(jump > energy_limit)
    if reference_limit is not None:
        error = pd.to_numeric(frame.get("reference_error", pd.Series(index=frame.index, dtype=float)),
                              errors="coerce")
        ok &= error <= reference_limit
    return (ok.fillna(False) & stable).astype(bool)


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
    for step in scale.stress_map_dt:
        at = base.replace(**{"time.dt": float(step)})
        cases += [("dt x iterations", float(step), at.replace(**{"pbf.iterations": int(it)}))
                  for it in scale.stress_iterations]
        cases += [("dt x heating_rate", float(step),
                   at.replace(**{"atmosphere.heating_rate": min(rate * factor, MAX_HEATING_RATE)}))
                  for factor in MAP_HEATING_FACTORS]
    return cases


def stress_specs(ctx: StudyContext, scene_name: str = SCENE) -> list[tuple[str, float, runs.RunSpec]]:
    scale = ctx.scale
    base = scale_scene(load_scene(scene_name), scale.stress_particles)
    base = base.replace(**{"time.steps": scale.stress_steps, "time.snapshot_every": scale.stress_steps,
                           "time.check_every": 1})
    return [(parameter, value, runs.RunSpec("particles", scene, backend=ctx.backend, seed=0, record_steps=True,
                                            diagnostics=False, keep_snapshots=0))
            for parameter, value, scene in stress_cases(base, scale)]


def _largest_run(values, ok) -> tuple:
    """(the largest value such that it and every smaller one is ok, the first one that is not)."""
    largest, first_bad = None, None
    for value, good in sorted(zip(values, ok)):
        if not good:
            first_bad = value
            break
        largest = value
    return largest, first_bad


def largest_stable_dt(frame: pd.DataFrame) -> dict:
    """The largest dt such that it and every smaller tried dt ran stably, and the largest such that they
    were all usable (usable_mask)."""
    dts = frame[frame.parameter == "dt"].sort_values("value")
    largest, first_bad = _largest_run(dts.value, dts.stable.astype(bool))
    ok = (dts["usable"].astype(bool) & dts.stable.astype(bool)) if "usable" in dts.columns else usable_mask(dts)
    usable, first_unusable = _largest_run(dts.value, ok)
    return {"largest_stable_dt": largest, "smallest_unstable_dt": first_bad,
            "largest_usable_dt": usable, "smallest_unusable_dt": first_unusable,
            "density_error_limit": DENSITY_ERROR_LIMIT, "energy_jump_limit": ENERGY_JUMP_LIMIT,
            "reference_error_limit": REFERENCE_ERROR_LIMIT, "reference_dt_divisor": REFERENCE_DT_DIVISOR,
            "reference_iterations": REFERENCE_ITERATIONS,
            "dt_tried": dts.value.tolist()}


def _energy_jump(steps: pd.DataFrame) -> float | None:
    """Largest ratio of one step's kinetic energy to the previous step's (None: not recorded)."""
    if "kinetic_energy" not in steps.columns or len(steps) < 2:
        return None
    ke = pd.to_numeric(steps["kinetic_energy"], errors="coerce").to_numpy(float)
    prev, nxt = ke[:-1], ke[1:]
    ok = (prev > 0) & pd.notna(prev) & pd.notna(nxt)
    return float((nxt[ok] / prev[ok]).max()) if ok.any() else None


def reference_spec(spec: runs.RunSpec, divisor: int = REFERENCE_DT_DIVISOR,
                   iterations: int = REFERENCE_ITERATIONS) -> runs.RunSpec:
    """The converged reference of a case: its scene at dt / `divisor` and `iterations` PBF iterations over the same
    simulated time (the same spec for cases that differ only in their iterations)."""
    scene = spec.scene
    steps = scene.time.steps * divisor
    ref = scene.replace(**{"time.dt": scene.time.dt / divisor, "time.steps": steps,
                           "time.snapshot_every": steps, "pbf.iterations": iterations})
    return runs.RunSpec("particles", ref, backend=spec.backend, seed=spec.seed, record_steps=True, diagnostics=False,
                        keep_snapshots=0)


def _add_reference_errors(ctx: StudyContext, frame: pd.DataFrame, plan, results) -> None:
    """Run the references of the cases that pass every other check (one per distinct reference spec; at the
    scale's divisor and iterations, for the parameters it names) and fill reference_error, reference_dt,
    reference_iterations and reference_reason."""
    scale = ctx.scale
    divisor = getattr(scale, "stress_reference_divisor", None) or REFERENCE_DT_DIVISOR
    iterations = getattr(scale, "stress_reference_iterations", None) or REFERENCE_ITERATIONS
    checked = getattr(scale, "stress_reference_parameters", None)
    candidates = usable_mask(frame, reference_limit=None)
    reasons = []
    wanted = {}
    for i, ((parameter, _, spec), ok) in enumerate(zip(plan, candidates)):
        if checked is not None and parameter not in checked:
            reasons.append(f"not run: no reference for {parameter} at the {scale.name} scale")
        elif not ok:
            reasons.append("not run: the case failed another check")
        else:
            reasons.append("")
            ref = reference_spec(spec, divisor, iterations)
            wanted.setdefault(ref.key(), (ref, []))[1].append(i)
    frame["reference_error"] = float("nan")
    frame["reference_dt"] = [spec.scene.time.dt / divisor for _, _, spec in plan]
    frame["reference_iterations"] = iterations
    frame["reference_reason"] = reasons
    if not wanted:
        return
    refs = ctx.run_parallel([ref for ref, _ in wanted.values()], "stress references")
    for (ref, cases), res in zip(wanted.values(), refs):
        for i in cases:
            if not res.stable:
                frame.loc[i, "reference_reason"] = f"the reference blew up: {res.reason}"
                continue
            spec = plan[i][2]
            frame.loc[i, "reference_error"] = reference_error(results[i].steps_table(), res.steps_table(),
                                                              spec.scene.particles.spacing)


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
            "density_error_max": (float(pd.to_numeric(steps["density_error_mean"], errors="coerce").max())
                                  if "density_error_mean" in steps.columns else None),
            "energy_jump": _energy_jump(steps),
            "dt": scene.time.dt, "iterations": scene.pbf.iterations,
            "heating_rate": scene.atmosphere.heating_rate, "phase_rate": scene.atmosphere.phase_rate,
            "alpha_dt": scene.atmosphere.phase_rate * scene.time.dt, "steps": spec.total_steps,
            "n_particles": res.max_particles, "last_good_step": res.last_good_step, "device": res.device,
            "commit": ctx.commit, "run_dir": str(res.path)})
    frame = pd.DataFrame(rows)
    _add_reference_errors(ctx, frame, plan, results)
    frame.insert(3, "usable", usable_mask(frame))
    tail = ["device", "commit", "run_dir"]
    frame = frame[[c for c in frame.columns if c not in tail] + tail]
    runs.write_csv(frame, ctx.data / "stress.csv")
    runs.atomic_write_json(ctx.data / "stress_summary.json",
                           {**largest_stable_dt(frame), "scene": scene_name, "steps": ctx.scale.stress_steps,
                            "particles": plan[0][2].scene.estimated_particles(),
                            "usable_bound": usable_bound_text(getattr(ctx.scale, "stress_reference_divisor", None)
                                                              or REFERENCE_DT_DIVISOR,
                                                              getattr(ctx.scale, "stress_reference_iterations", None)
                                                              or REFERENCE_ITERATIONS),
                            "commit": ctx.commit})
    return frame


STRESS_DT = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0)    # s
STRESS_ITERATIONS = (1, 2, 4, 8)
STRESS_ALPHA_DT = (0.1, 1.0, 10.0, 100.0, 1000.0)                                 # phase_rate * dt

def stress_command(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
                   backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
                   quiet: QuietOpt = False, gpus: GpusOpt = None) -> None:
    """Stability map: dt, iterations, heating rate and alpha*dt, dt x iterations and dt x heating rate; the
    largest stable and the largest usable dt."""
    import json
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            frame = run_stress(ctx)
    typer.echo(frame[["parameter", "value", "stable", "step", "reason"]].to_string(index=False))
    summary = json.loads((ctx.data / "stress_summary.json").read_text())
    typer.echo(f"largest stable dt: {summary['largest_stable_dt']} s; largest usable dt: "
               f"{summary['largest_usable_dt']} s (usable: {summary['usable_bound']})")
    typer.echo(f"wrote {ctx.data / 'stress.csv'}")


register(Study("stress", order=50, run=lambda ctx, scene: run_stress(ctx), sections=("stress",),
               report=(ReportSection("stress", "Stability map", "bench.report.build:_stress", 80),),
               outputs=("stress.csv", "stress_summary.json"),
               scale={"stress_particles": {"smoke": 2000, "cpu": 10_000, "gpu": 100_000},
                      "stress_steps": {"smoke": 30, "cpu": 100, "gpu": 200},
                      "stress_dt": dict.fromkeys(("smoke", "cpu", "gpu"), STRESS_DT),
                      "stress_iterations": dict.fromkeys(("smoke", "cpu", "gpu"), STRESS_ITERATIONS),
                      "stress_alpha_dt": dict.fromkeys(("smoke", "cpu", "gpu"), STRESS_ALPHA_DT),
                      # the converged reference: dt / divisor, these PBF iterations; at the smoke scale (the CI demo)
                      # a cheaper one and only for the dt and iterations lines and the dt x iterations map
                      "stress_reference_divisor": {"smoke": 2, "cpu": REFERENCE_DT_DIVISOR,
                                                   "gpu": REFERENCE_DT_DIVISOR},
                      "stress_reference_iterations": {"smoke": 8, "cpu": REFERENCE_ITERATIONS,
                                                      "gpu": REFERENCE_ITERATIONS},
                      "stress_reference_parameters": {"smoke": ("dt", "iterations", "dt x iterations"), "cpu": None,
                                                      "gpu": None},
                      "stress_map_dt": {"smoke": (2.0, 8.0, 32.0, 128.0), "cpu": (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0),
                                        "gpu": (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)}},
               command=stress_command))
