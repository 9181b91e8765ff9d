"""Sections of trade-offs and limits: run time against error (sweep), the adaptive mode at equal error
(adaptive-pareto) and the stability map (stress)."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd

from . import plots
from bench.pareto import pareto_front

from .common import Inputs, Section, _command, _missing, _provenance, _table

SWEEP_HIDDEN = ("device", "commit", "run_dir")
SWEEP_LABELS = {   # sweep.csv column -> table header (bench.studies.sweep writes the columns)
    "value": "value (spacings in m)", "wall_s": "wall time (s)",
    "error_self": "error vs own finest run", "error_other": "error vs other method's finest run",
    "error_cover_self": "cover error vs own finest", "error_profile_self": "profile error vs own finest",
    "error_cover_other": "cover error vs other's finest", "error_profile_other": "profile error vs other's finest",
    "particles": "particles (max)", "initial_particles": "particles (initial)", "cells": "grid cells",
    "spacing_m": "spacing (m)", "iterations": "PBF iterations", "resolution_m": "resolution (m)",
    "cloud_base_mean": "cloud base (m)", "cloud_top_mean": "cloud top (m)", "cover_mean": "cloud cover (fraction)",
    "lwp_mean": "LWP (kg/m²)", "split_threshold": "split threshold α", "reference": "reference run",
    "pareto": "on Pareto front"}
"""Errors are relative L2 differences of the cover series and the cloud-fraction profile (dimensionless);
cover, LWP, base and top are time means over the run's cloudy snapshots (cover > 1%)."""


def _sweep(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, _ = inp.csv("sweep")
    if df is None:
        _missing(sec, "sweep.csv (run time against error)", "sweep", inp.out)
        return
    df = df.copy()
    reference = (df["reference"].map(plots._truthy) if "reference" in df.columns
                 else pd.to_numeric(df["error_self"], errors="coerce") <= 0)
    sec.add("image", plots.pareto_plot(df, reference=reference), caption=(
        "Each point one run; error = difference of the cloud statistics from the finest run of the same method "
        "(left) and of the other method (right); lines: Pareto fronts per method and mode (no run on a front is "
        "beaten in both wall time and error by another of its group)."))
    keys = [k for k in ("method", "mode") if k in df.columns]
    measured = df[~reference & df["error_self"].notna() & df["wall_s"].notna()]
    fronts = [pareto_front(g, "wall_s", "error_self") for _, g in measured.groupby(keys, sort=True)]
    cols = [c for c in ("method", "mode", "parameter", "value", "particles", "cells", "wall_s", "error_self",
                        "error_other") if c in df.columns]
    if fronts:
        sec.add("table", _table(pd.concat(fronts)[cols], labels=SWEEP_LABELS), caption=(
            "runs on the Pareto front of each method / mode (wall time against the error vs the own finest run; "
            "the reference runs excluded)"))
    verdict = _study_verdict(inp)
    if verdict:
        sec.add("text", "Adaptive against non-adaptive at equal error: " + verdict + ".")
    else:
        sec.add("note", "no adaptive verdict recorded (sweep_verdict.json): rerun the sweep.", level="missing",
                command=_command("sweep", inp.out))
    convergence = plots.convergence_plot(df)
    if convergence is not None:
        sec.add("image", convergence, caption=(
            "Convergence: each solver's cloud statistics (time means over the run's cloudy period, cover > 1%) "
            "against its resolution, particle spacing or grid cell size (finer to the right); where the two "
            "lines approach each other as they refine, the solvers converge toward one answer."))
    if "stable" in df.columns:
        unstable = df[~df["stable"].map(plots._truthy)]
        if len(unstable):
            sec.add("note", f"{len(unstable)} sweep run(s) went unstable and have no wall time or error: "
                    + "; ".join(f"{r.method} {r.parameter} = {r.value}: {getattr(r, 'reason', '')}"
                                for r in unstable.itertuples()), level="warn")
    sec.add("table", _table(df.drop(columns=[c for c in SWEEP_HIDDEN if c in df.columns]), labels=SWEEP_LABELS),
            caption="all runs (errors: relative L2 of the cover series and the cloud-fraction profile; cloud cover, "
                    "LWP, base and top: time means over the run's cloudy snapshots)")
    sec.provenance = _provenance(df, env=env)


def _adaptive_pareto(inp: Inputs, sec: Section, env: dict | None) -> None:
    """Per scene (growing, cumulus): the Pareto plot, the configurations and the study's verdict."""
    shown = False
    for scene, suffix in (("growing", ""), ("cumulus", "_cumulus")):
        configs, _ = inp.csv(f"adaptive_pareto_configs{suffix}")
        verdict_path = inp.data / f"adaptive_verdict{suffix}.json"
        if configs is None or not verdict_path.is_file():
            continue
        shown = True
        verdict = json.loads(verdict_path.read_text())
        sec.add("text", f"{verdict.get('verdict', '')} PBF cost per adaptive particle against a uniform particle at "
                        f"equal count: {verdict.get('cost_ratio_per_particle') or float('nan'):.2f}x.")
        excluded = [e["name"] for e in verdict.get("excluded") or []]
        sec.add("image", plots.adaptive_pareto_plot(configs, verdict.get("noise_floor"), excluded), caption=(
            f"{scene}: ms per step against the error of each configuration's seed mean (cover, cloudy volume and "
            "LWP time series against the mean of the finer reference's seeds); bars: seed spread of the error; "
            "grey band: a single reference seed's error (differences below it cannot be told apart)"
            + ("; open markers: left out of the verdict (unstable in some seeds)." if excluded else ".")))
        cols = [c for c in ("config", "stable_seeds", "seeds", "particles", "ms_per_step", "pbf_ms_per_particle",
                            "error", "error_seed_spread",
                            "e_cover", "e_volume", "e_lwp", "e_base", "e_top", "e_profile", "speedup_at_equal_error",
                            "speedup_p05", "speedup_p95")
                if c in configs.columns]
        rule = verdict.get("min_stable_seeds")
        resampling = verdict.get("resampling") or {}
        sec.add("table", _table(configs[cols]), caption=f"{scene}: one row per configuration (means over its stable "
                "seeds)" + (f"; the verdict and the uniform front use only configurations stable in at least {rule} "
                            "seeds" if rule else "")
                + (f"; speedup_p05 and speedup_p95: the 5th and 95th percentiles of the speed-up over "
                   f"{resampling['replicates']} resamples of the seeds" if resampling else ""))
        for png in sorted(inp.renders.glob(f"pareto_{scene}_*.png")):
            name = png.stem[len(f"pareto_{scene}_"):]
            sec.add("image", plots.png_file_uri(png), source=png, caption=(
                f"{scene}, {name}, seed 0 at the end of the run: cloudy particles (w > 1e-5 kg/kg); the best "
                "adaptive variant is drawn beside the uniform runs at its level-0 and finest spacings."))
        runs_df, _ = inp.csv(f"adaptive_pareto{suffix}")
        sec.provenance = _provenance(runs_df, env=env)
    if not shown:
        _missing(sec, "adaptive_pareto_configs.csv (adaptive against uniform at equal error)", "adaptive_pareto",
                 inp.out)


def _study_verdict(inp: Inputs) -> str:
    """The sweep study's verdict (OUT/data/sweep_verdict.json) by the interval rule of bench.studies.sweep
    (speedup_summary); '' where the study wrote none."""
    path = inp.data / "sweep_verdict.json"
    if not path.is_file():
        return ""
    from .glance import sweep_verdict
    data = json.loads(path.read_text())
    text, _ = sweep_verdict(data)
    if text and data.get("metric"):
        text += f" (metric: {data['metric']}; each run one seed, wall time inside step())"
    return text


STRESS_LABELS = {   # stress.csv column -> table header (bench.studies.stress writes the columns)
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
        _missing(sec, "stress.csv (stability sweep)", "stress", inp.out)
        return
    df = stress_frame(df)
    from bench.studies.stress import ENERGY_JUMP_LIMIT
    checked = "reference_error" in df.columns
    bound = (usable_bound(df) if checked
             else "not determined: this stress.csv has no error against a converged reference")
    if not checked:
        sec.add("note", "This stress.csv predates the converged-reference check: no case is shown as usable (a stable "
                        "run can still have lost the scene, e.g. a fluid collapsed onto the floor). Rerun the stress "
                        "study for the usable region.", level="warn", command=_command("stress", inp.out))
    energy = ENERGY_JUMP_LIMIT if "energy_jump" in df.columns else None
    if df["parameter"].astype(str).str.startswith("dt x ").any():
        sec.add("image", plots.stability_map_2d(df, bound, energy), caption=(
            "Two-parameter maps: every cell one run of the stress scene. Colour: the largest per-step mean density "
            f"error (eq. 1); black line: the usable region's boundary (usable: {bound})."))
    else:
        sec.add("note", "no 2-D map in this stress.csv (made by an older version of the stress study); "
                        "rerun it for the dt x iterations and dt x heating-rate maps.", level="missing",
                command=_command("stress", inp.out))
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
                 "constant_gravity", inp.out)
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
    checked against a converged reference (bench.studies.stress.usable_mask where the CSV has no usable column);
    a row marked unstable is never usable, whatever the CSV says."""
    from bench.studies.stress import usable_mask
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
    from bench.studies.stress import usable_bound_text
    dt, ref_dt = (pd.to_numeric(df.get(c), errors="coerce") for c in ("dt", "reference_dt"))
    iterations = pd.to_numeric(df.get("reference_iterations"), errors="coerce").dropna()
    ratio = (dt / ref_dt).dropna()
    if not len(ratio) or not len(iterations):
        return usable_bound_text()
    return usable_bound_text(round(float(ratio.median()), 3), int(iterations.iloc[0]))


def stress_limits(df: pd.DataFrame) -> str:
    """'Largest usable dt (bound): ... s; largest stable dt: ... s.' from the 1-D dt cases of a stress_frame."""
    from bench.studies.stress import largest_stable_dt
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
