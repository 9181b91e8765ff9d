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

import json

import numpy as np
import pandas as pd
import typer

from cloudpbf.report import glance_plots as gp
from cloudpbf.report import plots
from cloudpbf.report.catalogue import GlanceCard
from cloudpbf.report.common import Inputs, Section, _command, _missing, _provenance, _table
from cloudpbf.report.glance import Card, data_link, missing_card, section_link
from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.registry import ReportSection, Study, register
from cloudpbf.studies.scales import scale_scene
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
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            frame = run_stress(ctx)
    typer.echo(frame[["parameter", "value", "stable", "step", "reason"]].to_string(index=False))
    summary = json.loads((ctx.data / "stress_summary.json").read_text())
    typer.echo(f"largest stable dt: {summary['largest_stable_dt']} s; largest usable dt: "
               f"{summary['largest_usable_dt']} s (usable: {summary['usable_bound']})")
    typer.echo(f"wrote {ctx.data / 'stress.csv'}")


# ---- report: the stability map, the verdict card -------------------------------------------------
STRESS_LABELS = {   # stress.csv column -> table header (cloudpbf.studies.stress writes the columns)
    "value": "value (dt in s, heating in K/s)", "step": "last step", "particles": "unstable particle ids",
    "max_speed": "max speed (m/s)", "density_error_mean": "density error, last step",
    "density_error_max": "density error, worst step", "energy_jump": "kinetic energy jump (x per step)",
    "dt": "dt (s)", "iterations": "PBF iterations", "heating_rate": "heating S_e (K/s)",
    "phase_rate": "phase rate α (1/s)", "alpha_dt": "α dt", "n_particles": "particles (max)",
    "last_good_step": "last good step", "reference_error": "error vs converged reference",
    "reference_dt": "reference dt (s)", "reference_iterations": "reference iterations",
    "reference_reason": "no reference error because"}
"""Density errors are the per-step mean of |rho/rho0 - 1| (a fraction, eq. 1)."""


GRAVITY_LABELS = {   # constant_gravity.csv column -> table header
    "constant_gravity": "g_c (m/s²)", "cloud_gravity": "cloud gravity (m/s²)", "first_cloud_s": "first cloud (s)",
    "max_cover": "max cloud cover (fraction)", "final_cover": "final cloud cover (fraction)",
    "vanished_and_returned": "vanished and returned", "density_error_mean": "density error, last step",
    "max_speed": "max speed (m/s)"}


def _stress(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, _ = inp.csv("stress")
    if df is None:
        _missing(sec, "stress.csv (stability sweep)", "stress", inp)
        return
    df = stress_frame(df)
    checked = "reference_error" in df.columns
    bound = (usable_bound(df) if checked
             else "not determined: this stress.csv has no error against a converged reference")
    if not checked:
        sec.add("note", "This stress.csv predates the converged-reference check: no case is shown as usable (a stable "
                        "run can still have lost the scene, e.g. a fluid collapsed onto the floor). Rerun the stress "
                        "study for the usable region.", level="warn", command=_command("stress", inp))
    energy = ENERGY_JUMP_LIMIT if "energy_jump" in df.columns else None
    if df["parameter"].astype(str).str.startswith("dt x ").any():
        sec.add("image", plots.stability_map_2d(df, bound, energy), caption=(
            "Two-parameter maps: every cell one run of the stress scene. Colour: the largest per-step mean density "
            f"error (eq. 1); black line: the usable region's boundary (usable: {bound})."))
    else:
        sec.add("note", "no 2-D map in this stress.csv (made by an older version of the stress study); "
                        "rerun it for the dt x iterations and dt x heating-rate maps.", level="missing",
                command=_command("stress", inp))
    sec.add("image", plots.stability_map(df, "stable, not usable" if checked else "stable (usable not checked)"),
            caption=(
        f"One parameter at a time. Green: usable ({bound}); orange: ran to the end but not usable"
        + ("" if checked else " or not checked") + "; red: stopped as unstable (reason shown)."))
    limit = stress_limits(df)
    if limit:
        sec.add("text", limit)
    bad = df[~df["stable"]]
    numeric = [c for c in ("max_speed", "density_error_mean") if c in df.columns]
    finite = df[df["stable"]][numeric].apply(pd.to_numeric, errors="coerce")
    if numeric and not np.isfinite(finite.to_numpy(dtype=float)).all():
        sec.add("note", "a run marked stable has non-finite statistics: check stress.csv", level="error")
    sec.add("text", f"{len(df)} runs, {int(df['stable'].sum())} stable, {len(bad)} unstable.")
    sec.add("table", _table(df.drop(columns=[c for c in ("device", "commit") if c in df.columns]),
                            labels=STRESS_LABELS),
            caption="all cases (an unstable run is stopped at the step the check caught it; its NaN never "
                    "enters the statistics; density error: the mean of |rho/rho0 - 1| over the particles)")
    gravity, gravity_path = inp.csv("constant_gravity")
    if gravity is None:
        _missing(sec, "constant_gravity.csv (paper example 2: a constant gravity on the whole domain)",
                 "constant_gravity", inp)
    else:
        cols = [c for c in ("case", "constant_gravity", "cloud_gravity", "particles", "stable", "reason",
                            "first_cloud_s", "max_cover", "final_cover", "vanished_and_returned",
                            "density_error_mean", "max_speed") if c in gravity.columns]
        sec.add("table", _table(gravity[cols], labels=GRAVITY_LABELS), caption=(
            f"A constant gravity g_c (m/s^2) added to every particle of the growing scene, beside the shipped "
            f"cycling scene, from {gravity_path.name}: cloud cover (fraction of columns) and the last step's "
            "density error and largest speed (m/s)."))
    sec.provenance = _provenance(df, env=env)


def stress_frame(df: pd.DataFrame) -> pd.DataFrame:
    """stress.csv with ``stable`` and ``usable`` as booleans: usable only where the row is stable and the case was
    checked against a converged reference (cloudpbf.studies.stress.usable_mask where the CSV has no usable column);
    a row marked unstable is never usable, whatever the CSV says."""
    df = df.copy()
    df["stable"] = df["stable"].map(plots._truthy)
    if "reference_error" not in df.columns:
        df["usable"] = False
    elif "usable" in df.columns:
        df["usable"] = df["usable"].map(plots._truthy)
    else:
        df["usable"] = usable_mask(df)
    df["usable"] = df["usable"] & df["stable"]
    return df


def usable_bound(df: pd.DataFrame) -> str:
    """What usable means in this stress.csv: the bound's text with the reference's dt divisor and iterations
    read from the rows (reference_dt, reference_iterations)."""
    dt, ref_dt = (pd.to_numeric(df.get(c), errors="coerce") for c in ("dt", "reference_dt"))
    iterations = pd.to_numeric(df.get("reference_iterations"), errors="coerce").dropna()
    ratio = (dt / ref_dt).dropna()
    if not len(ratio) or not len(iterations):
        return usable_bound_text()
    return usable_bound_text(round(float(ratio.median()), 3), int(iterations.iloc[0]))


def stress_limits(df: pd.DataFrame) -> str:
    """'Largest usable dt (bound): ... s; largest stable dt: ... s.' from the 1-D dt cases of a stress_frame."""
    dt = stress_frame(df[df["parameter"] == "dt"]) if "dt" in set(df["parameter"]) else df.iloc[:0]
    if not len(dt):
        return ""
    dt["value"] = pd.to_numeric(dt["value"], errors="coerce")
    found = largest_stable_dt(dt)
    usable, stable = found["largest_usable_dt"], found["largest_stable_dt"]
    if "reference_error" in df.columns:
        text = ("Largest usable dt: " + (f"{usable:g} s" if usable is not None else "none of the tried dt")
                + f" (usable: {usable_bound(df)}); ")
    else:
        text = "Largest usable dt: not determined (no converged-reference check in this data); "
    text += (f"largest stable dt (no blow-up, accuracy aside): {stable:g} s" if stable is not None
             else "no tried dt was stable")
    if found["smallest_unstable_dt"] is not None:
        text += f"; smallest unstable dt: {found['smallest_unstable_dt']:g} s"
    return text + "."


def stability_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    card = Card("stress", "Stability map")
    df, _ = inp.csv("stress")
    if df is None:
        return missing_card(card, inp, "no stress.csv", "stress")
    df = stress_frame(df)
    card.answer = stress_limits(df)
    if "reference_error" not in df.columns:
        card.level = "warn"
    dt = df[df["parameter"] == "dt"].sort_values("value")
    if len(dt):
        states = ["usable" if u else "stable" if s else "unstable" for u, s in zip(dt["usable"], dt["stable"])]
        card.figure = gp.strip(pd.to_numeric(dt["value"], errors="coerce"), states,
                               stable_label="stable, not usable" if "reference_error" in df.columns
                               else "stable (usable not checked)")
    card.links = section_link("stress", titles) + data_link(inp, "stress.csv", "stress_summary.json")
    return card


register(Study("stress", order=50, run=lambda ctx, scene: run_stress(ctx), sections=("stress",),
               report=(ReportSection("stress", "Stability map", _stress, 80, "Stability"),),
               glance=(GlanceCard(stability_card, 40),), produces={"stress": "cloudpbf stress --out {out}"},
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
