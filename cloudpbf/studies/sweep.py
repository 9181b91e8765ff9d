"""Run time against error, for both methods, on the growing-cloud scene (one seed).

Swept: the particle spacing (non-adaptive and adaptive), the PBF iterations and the adaptive split
threshold at the middle spacing, and the grid's cell count.  Each method's reference is its finest
run (particles: the most particles, non-adaptive, the scene's iterations; grid: the most cells).

Error of a run against a reference (both from cloudpbf.statistics on their snapshots):

    e_cover   = ||c(t) - c_ref(t)||_2 / ||c_ref(t)||_2        projected cloud cover over the snapshot times
    e_profile = ||a(z) - a_ref(z)||_2 / ||a_ref(z)||_2        time-mean cloud-fraction profile a_c(z),
                                                              interpolated onto the reference's heights
    error     = (e_cover + e_profile) / 2

``error_self`` is against the run's own method's reference, ``error_other`` against the other
method's.  Particle runs are all deposited on one analysis grid (the middle spacing's), grid runs are
analysed on their own cells.  A reference without any cloud gives no relative error (empty cells).
Wall time is the time spent inside the solver's step() (analysis and I/O excluded).

Outputs in OUT/data: sweep.csv (one row per run; ``pareto`` marks the runs no other run of the same
method beats in both wall time and error_self) and sweep_verdict.json (adaptive against
non-adaptive at equal error: the non-adaptive wall time interpolated, linearly in error, at each
adaptive run's error; the speed-ups' geometric mean with its 95% interval, "no difference measured" where the
interval holds 1 or a single comparison leaves none: ``speedup_summary``).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import typer

from cloudpbf.pareto import pareto_front
from cloudpbf.report import glance_plots as gp
from cloudpbf.report import plots
from cloudpbf.report.catalogue import GlanceCard
from cloudpbf.report.common import Inputs, Section, _command, _missing, _provenance, _table
from cloudpbf.report.glance import Card, data_link, section_link
from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
from cloudpbf.pareto import pareto_mask
from cloudpbf.report.inference import describes_no_difference, ratio_ci
from cloudpbf.statistics import cloudy_period_means, relative_l2
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.plans import SMOKE_CLOUD_BOX, SWEEP_SCENE as SCENE, sweep_plan  # noqa: F401
from cloudpbf.studies.registry import ReportSection, Study, register



# ---- error metrics ---------------------------------------------------------------------------------
def _relative_l2(values: np.ndarray, reference: np.ndarray) -> float:
    """The relative L2 error, NaN where either sample is not finite (statistics.relative_l2)."""
    return relative_l2(values, reference)


def cloud_signature(result: runs.RunResult) -> dict | None:
    """Cover time series and time-mean cloud-fraction profile of a run (None: nothing to compare)."""
    stats, prof = result.stats(), result.profiles()
    if not len(stats) or not len(prof):
        return None
    mean_profile = prof.groupby("z", sort=True)["cloud_fraction"].mean()
    return {"time": stats["time_s"].to_numpy(float), "cover": stats["cloud_cover"].to_numpy(float),
            "z": mean_profile.index.to_numpy(float), "profile": mean_profile.to_numpy(float)}


def cloud_means(result: runs.RunResult) -> dict:
    """Time means of cover, mean LWP (kg/m^2), cloud base and top (m) over the snapshots whose cover is above
    CLOUDY_COVER (NaN without any)."""
    return cloudy_period_means(result.stats() if result.stable else pd.DataFrame())


def errors(sig: dict | None, ref: dict | None) -> tuple[float, float, float]:
    """(error, e_cover, e_profile) of a signature against a reference signature."""
    if sig is None or ref is None:
        return math.nan, math.nan, math.nan
    cover = np.interp(ref["time"], sig["time"], sig["cover"])
    e_cover = _relative_l2(cover, ref["cover"])
    profile = np.interp(ref["z"], sig["z"], sig["profile"])
    e_profile = _relative_l2(profile, ref["profile"])
    return 0.5 * (e_cover + e_profile), e_cover, e_profile


def verdict(frame: pd.DataFrame) -> dict:
    """Adaptive against non-adaptive particles at equal error (against the particle reference)."""
    fixed = frame[(frame.parameter == "spacing") & frame.stable].dropna(subset=["error_self"])
    adapt = frame[(frame.parameter == "adaptive_spacing") & frame.stable].dropna(subset=["error_self"])
    fixed = fixed.sort_values("error_self")
    out = {"metric": "error_self = (e_cover + e_profile)/2 against the finest non-adaptive run",
           "non_adaptive": fixed[["value", "particles", "wall_s", "error_self"]].to_dict("records"),
           "adaptive": adapt[["value", "particles", "wall_s", "error_self"]].to_dict("records"),
           "comparisons": []}
    if len(fixed) < 2 or not len(adapt):
        out["verdict"] = "not enough stable runs with a measurable error to compare"
        return out
    lo, hi = fixed.error_self.min(), fixed.error_self.max()
    for row in adapt.itertuples():
        if not lo <= row.error_self <= hi:
            continue
        wall_fixed = float(np.interp(row.error_self, fixed.error_self, fixed.wall_s))
        out["comparisons"].append({"error": row.error_self, "wall_adaptive_s": row.wall_s,
                                   "wall_non_adaptive_s": wall_fixed, "speedup": wall_fixed / row.wall_s})
    if not out["comparisons"]:
        out["verdict"] = (f"no overlap: adaptive errors {adapt.error_self.min():.3g}..{adapt.error_self.max():.3g}, "
                          f"non-adaptive {lo:.3g}..{hi:.3g}")
        return out
    out.update(speedup_summary([c["speedup"] for c in out["comparisons"]]))
    return out


def speedup_summary(speedups) -> dict:
    """The verdict over the comparisons' speed-ups (non-adaptive wall time over adaptive, each at an adaptive
    run's error): their geometric mean with its 95% t-interval on the logarithms (cloudpbf.report.inference.ratio_ci),
    and "no difference measured" where the interval holds 1 or one comparison leaves none. Each speed-up is a
    single wall-clock ratio of two runs, so the interval is what separates a difference from run-to-run noise."""
    speedups = [float(v) for v in speedups]
    ci = ratio_ci(speedups)
    listed = ", ".join(f"{v:.2f}x" for v in speedups)
    out = {"speedups": speedups, "speedup": ci.mean, "median_speedup": float(np.median(speedups)),
           "speedup_interval": [ci.lo, ci.hi] if ci.n >= 2 else None, "comparisons_n": ci.n,
           "no_difference": describes_no_difference(ci)}
    if ci.n < 2:
        out["verdict"] = (f"no difference measured: one comparison at equal error ({listed}, adaptive against "
                          "non-adaptive wall time) gives no interval")
    elif out["no_difference"]:
        out["verdict"] = (f"no difference measured: at equal error the adaptive runs' speed-ups are {listed} "
                          f"(geometric mean {ci.mean:.2f}x, 95% interval {ci.lo:.2f}-{ci.hi:.2f}x holds 1)")
    else:
        word = "faster" if ci.mean > 1 else "slower"
        factor, lo, hi = (ci.mean, ci.lo, ci.hi) if ci.mean > 1 else (1 / ci.mean, 1 / ci.hi, 1 / ci.lo)
        out["verdict"] = (f"at equal error, adaptive runs are {factor:.2f}x {word} than non-adaptive runs (geometric "
                          f"mean of {ci.n} comparisons, 95% interval {lo:.2f}-{hi:.2f}x)")
    return out


def run_sweep(ctx: StudyContext, scene_name: str = SCENE) -> pd.DataFrame:
    """Run (or read) the sweep; write sweep.csv and sweep_verdict.json."""
    plan = sweep_plan(ctx, scene_name)
    results = ctx.run_parallel([p["spec"] for p in plan], "sweep")
    sigs = [cloud_signature(r) if r.stable else None for r in results]

    def reference(method):
        idx = [i for i, p in enumerate(plan) if p["method"] == method and results[i].stable
               and p["parameter"] in ("spacing", "cells")]
        if not idx:
            return None, None
        key = (lambda i: results[i].max_particles) if method == "particles" else (lambda i: results[i].cells)
        best = max(idx, key=key)
        return best, sigs[best]

    refs = {m: reference(m) for m in ("particles", "grid")}
    rows = []
    for i, (p, res) in enumerate(zip(plan, results)):
        other = "grid" if p["method"] == "particles" else "particles"
        e_self, c_self, p_self = errors(sigs[i], refs[p["method"]][1])
        e_other, c_other, p_other = errors(sigs[i], refs[other][1])
        scene = p["spec"].scene
        rows.append({
            "method": p["method"], "parameter": p["parameter"], "value": p["value"], "mode": p["mode"],
            "wall_s": res.step_wall_s if res.stable else math.nan,
            "error_self": e_self, "error_other": e_other, "error_cover_self": c_self, "error_profile_self": p_self,
            "error_cover_other": c_other, "error_profile_other": p_other,
            "particles": res.max_particles, "initial_particles": scene.estimated_particles()
            if p["method"] == "particles" else None, "cells": res.cells,
            "spacing_m": scene.particles.spacing, "iterations": scene.pbf.iterations,
            "resolution_m": scene.particles.spacing if p["method"] == "particles"
            else max(scene.domain.size) / float(p["value"]),
            **cloud_means(res),
            "split_threshold": scene.adaptive.split_threshold if scene.adaptive.enabled else None,
            "reference": i == refs[p["method"]][0], "stable": bool(res.stable), "reason": res.reason,
            "steps": p["spec"].total_steps, "device": res.device, "commit": ctx.commit, "run_dir": str(res.path)})
    frame = pd.DataFrame(rows)
    frame["pareto"] = False
    for method, group in frame.groupby("method"):
        frame.loc[group.index, "pareto"] = pareto_mask(group.wall_s.to_numpy(float), group.error_self.to_numpy(float))
    runs.write_csv(frame, ctx.data / "sweep.csv")
    runs.atomic_write_json(ctx.data / "sweep_verdict.json", {**verdict(frame), "commit": ctx.commit})
    return frame


def sweep_command(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
                  backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
                  quiet: QuietOpt = False, gpus: GpusOpt = None) -> None:
    """Run time against error (spacing, iterations, split threshold, grid cells) and the Pareto front."""
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            frame = run_sweep(ctx)
    typer.echo(frame[["method", "parameter", "value", "wall_s", "error_self", "error_other", "pareto"]]
               .to_string(index=False))
    typer.echo(json.loads((ctx.data / "sweep_verdict.json").read_text())["verdict"])
    typer.echo(f"wrote {ctx.data / 'sweep.csv'}")


# ---- report: run time against error, the verdict card --------------------------------------------
SWEEP_HIDDEN = ("device", "commit", "run_dir")


SWEEP_LABELS = {   # sweep.csv column -> table header (cloudpbf.studies.sweep writes the columns)
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
        _missing(sec, "sweep.csv (run time against error)", "sweep", inp)
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
                command=_command("sweep", inp))
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


def _study_verdict(inp: Inputs) -> str:
    """The sweep study's verdict (OUT/data/sweep_verdict.json) by the interval rule of cloudpbf.studies.sweep
    (speedup_summary); '' where the study wrote none."""
    path = inp.data / "sweep_verdict.json"
    if not path.is_file():
        return ""
    data = json.loads(path.read_text())
    text, _ = sweep_verdict(data)
    if text and data.get("metric"):
        text += f" (metric: {data['metric']}; each run one seed, wall time inside step())"
    return text


def sweep_verdict(v: dict) -> tuple[str, bool]:
    """(the sweep verdict's text, no difference measured) from sweep_verdict.json, its interval recomputed from the
    comparisons so that a verdict written before the interval existed is read by the same rule."""
    comps = v.get("comparisons") or []
    if not comps:
        return str(v.get("verdict", "no verdict")), True
    summary = speedup_summary([c["speedup"] for c in comps])
    errs = [c["error"] for c in comps]
    return f"{summary['verdict']}; at errors {min(errs):.3g}-{max(errs):.3g}", summary["no_difference"]


def sweep_front_card(inp: Inputs, env: dict | None, titles: dict) -> Card | None:
    """The adaptive front from the sweep's verdict (sweep_verdict.json): it stands in for the adaptive-pareto
    study's card where that study did not run; None where the sweep did not run either."""
    path = inp.data / "sweep_verdict.json"
    if not path.is_file():
        return None
    card = Card("adaptive_front", "The adaptive front: speed-up at equal error")
    v = json.loads(path.read_text())
    text, none = sweep_verdict(v)
    card.answer = f"Sweep (one seed per run): {text}."
    card.detail = f"Error: {v.get('metric', 'against the finest run')}; wall time inside step()."
    card.level = "warn" if none else "ok"
    card.links = section_link("sweep", titles) + data_link(inp, "sweep_verdict.json", "sweep.csv")
    fixed, adapt = pd.DataFrame(v.get("non_adaptive") or []), pd.DataFrame(v.get("adaptive") or [])
    if len(fixed) and len(adapt):
        card.figure = gp.front(fixed["wall_s"], fixed["error_self"], adapt["wall_s"], adapt["error_self"],
                               xlabel="wall time in step() (s)", uniform_label="non-adaptive")
    return card


register(Study("sweep", order=40, run=lambda ctx, scene: run_sweep(ctx, scene), sections=("sweep",),
                report=(ReportSection("sweep", "Run time against error", _sweep, 60, "Time vs error"),),
                glance=(GlanceCard(sweep_front_card, 21, slot="adaptive_front"),),
                produces={"sweep": "cloudpbf sweep --out {out}"},
                outputs=("sweep.csv", "sweep_verdict.json"),
                scale={  # spacing sweep coarse to fine (the finest is the reference); iterations and the split
                       # threshold alpha at the middle spacing; grid cells along the longest axis
                       "sweep_particles": {"smoke": (2000, 3000, 5000), "cpu": (12_500, 25_000, 50_000, 100_000),
                                           "gpu": (100_000, 250_000, 840_000, 2_000_000)},
                       "sweep_iterations": {"smoke": (2, 8), "cpu": (1, 2, 8, 16), "gpu": (1, 2, 8, 16)},
                       "sweep_split_thresholds": {"smoke": (0.15, 0.6), "cpu": (0.1, 0.2, 0.5, 1.0),
                                                  "gpu": (0.1, 0.2, 0.5, 1.0)},
                       "sweep_grid_cells": {"smoke": (8, 12, 16), "cpu": (16, 24, 32, 48), "gpu": (32, 48, 64, 96)},
                       # smoke: the compare study's small box (clouds form there), spacings in m instead of counts
                       "sweep_box": {"smoke": {**SMOKE_CLOUD_BOX, "spacings": (110.0, 100.0, 90.0)},
                                     "cpu": None, "gpu": None}},
                command=sweep_command))
