"""Table 1 of the paper: per-phase milliseconds per step for its four examples.

Rows: growing / cycling clouds (Fig. 5a-d), each non-adaptive and adaptive, from the scenes
growing, growing_adaptive, cycling, cycling_adaptive.  Columns are the paper's phases: ``pbf``
(neighbour search + constraint iterations + velocity update; ``neighbors`` and ``solver`` are
sub-timers inside it and are not added again), ``smoothing``, ``cloud_dynamics``, ``splitting``,
``merging``; ``total_ms`` is the sum of the phases that ran (an empty cell: the phase did not
run, e.g. no split/merge without adaptivity).  ``max_particles`` is the largest particle count
seen during the run.  Timings are ms per step: each phase's total time over the steps after a short
warm-up, divided by the number of those steps.

At scale ``gpu`` the scenes run at the paper's particle counts; at ``cpu``/``smoke`` they are
scaled down (see cloudpbf.studies.scales) and the ``scale`` column says so.  Output:
OUT/data/table1.csv (columns TABLE1_COLUMNS, then backend, scale, steps, initial_particles,
stable, reason, paper_max_particles, paper_total_ms, speedup_vs_paper = paper_total_ms / total_ms
(the paper: GeForce GTX 780 Ti, cloudpbf/data/paper_table1.csv) only at the gpu scale and where the row's
largest particle count is within MATCH_TOLERANCE of the paper's (a ratio of runs of other particle counts is
not a speed-up), particle_steps_per_s = max_particles / (total_ms / 1000), the per-step spread where the run
recorded each step's wall time (steps.csv ``wall_ms``: step_ms_median, step_ms_p05, step_ms_p95 over the
timed steps, timed_steps), run_dir), and what the timing was bought with: mass_centre_rise_m,
density_excess_mean, density_deficit_mean (:func:`incompressibility`).

Beside the paper's rows: when OUT/data/adaptive_verdict.json (``cloudpbf adaptive-pareto --scene growing``)
names a best adaptive variant that is not the scene's own setting, a fifth row times ``growing_adaptive``
with that variant's criterion, finest level and thresholds (and, at the GPU scale, its level-0 spacing); its ``variant`` column holds the
variant's name (empty on the paper's rows) and its paper columns are those of the paper's adaptive row.
"""
from __future__ import annotations

import math
import json

import numpy as np
import pandas as pd
import typer

from cloudpbf.report import glance_plots as gp
from cloudpbf.report import plots
from cloudpbf.report.catalogue import GlanceCard
from cloudpbf.report.common import (Inputs, Section, _command, _measured_total, _missing, _paper_table, _provenance,
                                 _scale_of, _table, _variant)
from cloudpbf.report.glance import Card, data_link, missing_card, section_link
from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName, ScaleOpt,
                              refusals, study_context)
from cloudpbf.paper import PHASES, paper_table
from cloudpbf.studies.adaptive_variants import DEFAULT_MAX_LEVEL, VERDICT, Config
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.registry import ReportSection, Study, register
from cloudpbf.studies.scales import scale_scene
from pbf_cuda.scene import load_scene

ROWS = (  # example, figure, mode, scene
    ("growing", "5a", "non-adaptive", "growing"),
    ("growing", "5b", "adaptive", "growing_adaptive"),
    ("cycling", "5c", "non-adaptive", "cycling"),
    ("cycling", "5d", "adaptive", "cycling_adaptive"),
)
TABLE1_COLUMNS = ("example", "figure", "mode", "variant", "max_particles", *(f"{p}_ms" for p in PHASES),
                  "total_ms", "device", "commit")


MATCH_TOLERANCE = 0.2
"""A row's speed-up against the paper needs its particle count within 20% of the paper's row."""

TIMING_STEPS = {"smoke": 100, "cpu": 500, "gpu": None}
"""The most steps a row runs at each scale (None: the scene's own): per-step timings need no 4200 s cycling run
below the GPU scale, and at the smoke scale (the CI demo) 100 steps time the phases as well as 250 did."""


def paper_rows() -> dict[tuple[str, str], dict]:
    """(example, mode) -> the paper's row, with its total_ms (sum of the phases it lists)."""
    return {(r["example"], r["mode"]): r for r in paper_table().to_dict("records")}


def best_variant(ctx: StudyContext) -> tuple[str, dict] | None:
    """(name, scene overrides) of the growing study's best adaptive variant (adaptive_verdict.json in OUT/data),
    or None: no verdict, no best variant, or the best is the scene's own setting (the 5b row already)."""
    path = ctx.data / VERDICT
    try:
        best = json.loads(path.read_text()).get("best") or {}
    except (OSError, ValueError):
        return None
    criterion, spacing = best.get("criterion"), best.get("spacing_m")
    if not best.get("name") or not criterion:
        return None
    base = load_scene("growing_adaptive")
    variant = Config(best["name"], "adaptive", float(spacing or base.particles.spacing), criterion,
                     int(best.get("max_level") or DEFAULT_MAX_LEVEL), float(best.get("threshold_scale") or 1.0),
                     int(best.get("adapt_every") or 0), str(best.get("pair_kernel") or ""))
    over = variant.adaptive_overrides(base)
    if ctx.scale.particles is None and spacing:          # the study's spacings are those of the GPU scale
        over["particles.spacing"] = float(spacing)
    if base.replace(**over) == base:
        return None
    return str(best["name"]), over


def table1_rows(ctx: StudyContext) -> list[tuple]:
    """(example, figure, mode, variant, scene) of every row: the paper's four, then the best variant's."""
    rows = [(example, figure, mode, "", load_scene(name)) for example, figure, mode, name in ROWS]
    best = best_variant(ctx)
    if best is not None:
        rows.append(("growing", "5b", "adaptive", best[0], load_scene("growing_adaptive").replace(**best[1])))
    return rows


def table1_specs(ctx: StudyContext, rows: list[tuple]) -> list[runs.RunSpec]:
    """One timing run per row: the scaled scene, its own seed, no diagnostics, the final state kept."""
    specs = []
    for *_, base in rows:
        scene = scale_scene(base, ctx.scale.particles, ctx.scale.step_fraction)
        cap = ctx.scale.table1_timing_steps
        if cap is not None and scene.time.steps > cap:
            scene = scene.replace(**{"time.steps": cap})
        steps = scene.time.steps
        specs.append(runs.RunSpec("particles", scene, backend=ctx.backend, diagnostics=False, keep_snapshots=1,
                                  warmup_steps=min(5, steps // 10), record_steps=True))
    return specs


def incompressibility(result: runs.RunResult) -> dict:
    """What a timing was bought with: the rise of the mass centre over the run (m; 0 in an incompressible
    closed box) and the final mean density excess and deficit (relative to rho0), from the run's per-step
    solver statistics (steps.csv); NaN where the run has none."""
    steps = result.steps_table()
    out = {"mass_centre_rise_m": float("nan"), "density_excess_mean": float("nan"),
           "density_deficit_mean": float("nan")}
    if len(steps) and "mass_centre_height" in steps:
        out["mass_centre_rise_m"] = float(steps["mass_centre_height"].iloc[-1] - steps["mass_centre_height"].iloc[0])
    for key in ("density_excess_mean", "density_deficit_mean"):
        if len(steps) and key in steps:
            out[key] = float(steps[key].iloc[-1])
    return out


def step_spread(result: runs.RunResult, warmup: int) -> dict:
    """Median and 5-95% of the per-step wall time (ms) over the timed steps, where steps.csv records it
    (``wall_ms``); NaN otherwise."""
    steps = result.steps_table()
    out = {"step_ms_median": float("nan"), "step_ms_p05": float("nan"), "step_ms_p95": float("nan"),
           "timed_steps": float("nan")}
    if not len(steps) or "wall_ms" not in steps:
        return out
    timed = steps[steps["step"] > warmup] if "step" in steps else steps.iloc[warmup:]
    wall = pd.to_numeric(timed["wall_ms"], errors="coerce").dropna()
    if len(wall):
        lo, med, hi = wall.quantile([0.05, 0.5, 0.95])
        out.update(step_ms_median=float(med), step_ms_p05=float(lo), step_ms_p95=float(hi), timed_steps=len(wall))
    return out


def table1_row(meta: tuple, spec: runs.RunSpec, result: runs.RunResult, ctx: StudyContext) -> dict:
    example, figure, mode, variant, _ = meta
    timings = result.timings()
    steps = timings["pbf"]["count"] if "pbf" in timings else 0     # pbf runs every step: the timed steps
    row = {"example": example, "figure": figure, "mode": mode, "variant": variant,
           "max_particles": result.max_particles}
    for phase in PHASES:   # ms per step: a phase that ran on some steps only is averaged over all of them
        row[f"{phase}_ms"] = timings[phase]["total_ms"] / steps if phase in timings and steps else None
    ran = [row[f"{p}_ms"] for p in PHASES if row[f"{p}_ms"] is not None]
    row["total_ms"] = sum(ran) if ran else None
    paper = paper_rows().get((example, mode), {})
    n_paper = paper.get("max_particles")
    matched = (ctx.scale.particles is None and bool(n_paper) and bool(result.max_particles)
               and abs(result.max_particles / n_paper - 1) <= MATCH_TOLERANCE)
    row.update(device=result.device, commit=ctx.commit, backend=result.backend, scale=ctx.scale.environment_label,
               steps=spec.total_steps, initial_particles=spec.scene.estimated_particles(), stable=result.stable,
               reason=result.reason, paper_max_particles=n_paper, paper_total_ms=paper.get("total_ms"),
               speedup_vs_paper=paper["total_ms"] / row["total_ms"] if matched and row["total_ms"] else None,
               particle_steps_per_s=(result.max_particles * 1e3 / row["total_ms"] if row["total_ms"] else None),
               **step_spread(result, getattr(spec, "warmup_steps", 0)), run_dir=str(result.path))
    row.update(incompressibility(result))
    return row


def run_table1(ctx: StudyContext) -> pd.DataFrame:
    """Run (or read from the cache) the rows and write OUT/data/table1.csv."""
    rows = table1_rows(ctx)
    specs = table1_specs(ctx, rows)
    results = ctx.run_serial(specs, "table1")
    frame = pd.DataFrame([table1_row(meta, spec, res, ctx) for meta, spec, res in zip(rows, specs, results)])
    runs.write_csv(frame, ctx.data / "table1.csv")
    return frame


def table1_command(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
                   backend: BackendOpt = Backend.auto, quiet: QuietOpt = False) -> None:
    """Table 1: per-phase ms of the four examples beside the paper's (OUT/data/table1.csv)."""
    with study_context(out, runs_root, scale, backend, None, None, quiet) as ctx:
        with refusals():
            frame = run_table1(ctx)
    gpu = ctx.scale.particles is None
    shown = ["example", "mode", "variant", "max_particles", "pbf_ms", "smoothing_ms", "cloud_dynamics_ms", "splitting_ms",
             "merging_ms", "total_ms", "particle_steps_per_s"] + (
        ["paper_max_particles", "paper_total_ms", "speedup_vs_paper"] if gpu else []) + ["stable"]
    typer.echo(frame[shown].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    typer.echo(f"device: {frame['device'].iloc[0]}; scale: {ctx.scale.environment_label}"
               + ("; paper: GeForce GTX 780 Ti (speed-up only where the particle counts match)" if gpu else
                  "; the comparison with the paper's Table 1 needs the gpu scale (--scale gpu)"))
    typer.echo(f"wrote {ctx.data / 'table1.csv'}")


# ---- report: Table 1 against the paper, the per-phase cost, the verdict card ---------------------
PAPER_NEEDS_GPU = ("The comparison with the paper's Table 1 needs the gpu scale (the paper's 500k-930k particles: "
                   "cloudpbf table1 --scale gpu); at this scale the rows are throughput only.")


def step_time_text(row: dict) -> str:
    """'3.83 ms per step (median over 495 timed steps, 5-95%: 3.71-4.02)' where the row carries the per-step
    spread (step_ms_median, step_ms_p05, step_ms_p95, timed_steps), else the mean over the timed steps and a
    plain note that the spread was not recorded."""
    med, lo, hi = (pd.to_numeric(row.get(k), errors="coerce") for k in ("step_ms_median", "step_ms_p05", "step_ms_p95"))
    steps = pd.to_numeric(row.get("timed_steps", row.get("steps")), errors="coerce")
    over = f" over {int(steps)} timed steps" if np.isfinite(steps) else " over the timed steps"
    if np.isfinite(med) and np.isfinite(lo) and np.isfinite(hi):
        return f"{med:.3g} ms per step (median{over}, 5-95%: {lo:.3g}-{hi:.3g})"
    total = pd.to_numeric(row.get("total_ms"), errors="coerce")
    return f"{total:.3g} ms per step (mean{over}; per-step spread not recorded in this data)"


def paper_comparison(measured: pd.DataFrame, env: dict | None) -> pd.DataFrame:
    """One row per Table 1 row: particle counts (ours, the paper's), ms per step, throughput in particle-steps per
    second (ours, the paper's), and ``speedup_vs_paper`` (the paper's ms / ours) only where the counts match
    (gpu scale, within MATCH_TOLERANCE); elsewhere ``throughput_vs_paper`` (gpu scale) or nothing."""
    measured = measured.copy()
    measured["total_ms"] = _measured_total(measured)
    paper = _paper_table().set_index(["example", "mode"])
    scale = _scale_of(env, measured)
    rows = []
    for r in measured.to_dict("records"):
        key = (r["example"], r["mode"])
        n = pd.to_numeric(r.get("max_particles"), errors="coerce")
        t = pd.to_numeric(r.get("total_ms"), errors="coerce")
        n_p = paper["max_particles"].get(key, math.nan) if "max_particles" in paper else math.nan
        t_p = paper["total_ms"].get(key, math.nan)
        p05, p95 = (pd.to_numeric(r.get(k), errors="coerce") for k in ("step_ms_p05", "step_ms_p95"))
        rate = n * 1e3 / t if t and t > 0 else math.nan
        rate_p = n_p * 1e3 / t_p if t_p and t_p > 0 else math.nan
        matched = scale == "gpu" and np.isfinite(n) and np.isfinite(n_p) and abs(n / n_p - 1) <= MATCH_TOLERANCE
        variant = _variant(r)
        rows.append({**r, "row": f"{r['example']} {r['mode']}" + (f" ({variant})" if variant else ""),
                     "variant": variant, "paper_particles": n_p, "paper_ms": t_p, "particle_steps_per_s": rate,
                     "paper_particle_steps_per_s": rate_p, "counts_match": bool(matched),
                     "speedup_vs_paper": t_p / t if matched and t > 0 else math.nan,
                     "speedup_lo": t_p / p95 if matched and p95 > 0 else math.nan,
                     "speedup_hi": t_p / p05 if matched and p05 > 0 else math.nan,
                     "throughput_vs_paper": rate / rate_p if scale == "gpu" and not matched and rate_p > 0
                     else math.nan, "scale": scale})
    return pd.DataFrame(rows)


def _table1(inp: Inputs, sec: Section, env: dict | None) -> None:
    measured, _ = inp.csv("table1")
    if measured is None:
        _missing(sec, "table1.csv", "table1", inp)
        return
    rows = paper_comparison(measured, env)
    scale = rows["scale"].iloc[0]
    gpu = scale == "gpu"
    if not gpu:
        sec.add("note", f"Scale '{scale}': {PAPER_NEEDS_GPU}", level="warn")
    elif not rows["counts_match"].all():
        sec.add("note", "Rows whose particle count differs from the paper's by more than "
                        f"{100 * MATCH_TOLERANCE:g}% ({', '.join(rows.loc[~rows['counts_match'], 'row'])}) are "
                        "compared by throughput (particle-steps per second), not as a speed-up.", level="info")
    table = pd.DataFrame({
        "example": rows["example"], "mode": rows["row"].str.split(" ", n=1).str[1], "particles": rows["max_particles"],
        "total ms": rows["total_ms"], "particle-steps/s": rows["particle_steps_per_s"]})
    if gpu:
        table["particles (paper)"] = rows["paper_particles"]
        table["total ms (paper)"] = rows["paper_ms"]
        table["particle-steps/s (paper)"] = rows["paper_particle_steps_per_s"]
        table["speed-up vs paper (same counts)"] = rows["speedup_vs_paper"]
        table["throughput vs paper (other counts)"] = rows["throughput_vs_paper"]
    for p in PHASES:
        if f"{p}_ms" in rows.columns and rows[f"{p}_ms"].notna().any():
            table[f"{p} ms"] = rows[f"{p}_ms"]
    if {"step_ms_median", "step_ms_p05", "step_ms_p95"} <= set(rows.columns):
        table["step ms median [5-95%]"] = [step_time_text(r).split(" (")[0] + f" [{r['step_ms_p05']:.3g}, "
                                           f"{r['step_ms_p95']:.3g}]" for r in rows.to_dict("records")]
    table = table.loc[:, [c for c in table.columns if not table[c].isna().all()]]
    sec.add("table", _table(table), caption=(
        "Milliseconds per step (each phase's time over the timed steps; pbf holds the neighbour search and the "
        "constraint iterations) and throughput = particles (the run's largest count) x steps per second. "
        + ("Beside them the paper's Table 1 (GeForce GTX 780 Ti): a speed-up only where the particle counts match, "
           "else the ratio of throughputs. " if gpu else "")
        + "A row 'adaptive (name)' is the adaptive study's best variant (cloudpbf adaptive-pareto)."))
    paper = _paper_table()
    missing_rows = set(paper["example"] + "/" + paper["mode"]) - set(measured["example"] + "/" + measured["mode"])
    if missing_rows:
        sec.add("note", "rows not measured in this study: " + ", ".join(sorted(missing_rows)), level="missing",
                command=_command("table1", inp))
    sec.provenance = _provenance(measured, env=env)


def _phases(inp: Inputs, sec: Section, env: dict | None) -> None:
    measured, _ = inp.csv("table1")
    if measured is None:
        _missing(sec, "table1.csv (per-phase timings)", "table1", inp)
        return
    paper = _paper_table()
    sec.add("image", plots.phase_bars(measured, paper), caption=(
        "Stacked ms per step of the Table 1 phases (pbf includes neighbour search and constraint iterations). "
        "Phases a run does not have (splitting and merging without adaptivity) are absent, not zero."))
    shares = measured[["example", "mode"]].copy()
    total = _measured_total(measured)
    for p in PHASES:
        if f"{p}_ms" in measured.columns and measured[f"{p}_ms"].notna().any():
            shares[f"{p} %"] = 100.0 * pd.to_numeric(measured[f"{p}_ms"], errors="coerce") / total
    sec.add("table", _table(shares, "{:.1f}"), caption="share of each phase in the measured step time (%)")
    cost, cost_path = inp.csv("adaptive_cost")
    if cost is None:
        _missing(sec, "adaptive_cost.csv (splitting and merging at ~500k adaptive particles, GPU)", "adaptive_cost", inp)
    else:
        cols = [c for c in ("scene", "spacing_m", "mean_particles", "max_particles", "splitting_ms", "merging_ms",
                            "merge_passes_ms", "compaction_ms", "pbf_ms", "split_target_ms", "merge_target_ms",
                            "meets_targets", "device", "commit") if c in cost.columns]
        sec.add("table", _table(cost[cols]), caption=(
            f"Splitting and merging at the size of the targets, from {cost_path.name}: ms per step over the whole "
            "run (merge_passes and compaction are parts of merging; pbf is the same run's constraint solve). "
            "meets_targets is left empty off the GPU or below 400k particles."))
    sec.provenance = _provenance(measured, env=env)


def table1_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    card = Card("table1", "Table 1 against the paper")
    measured, _ = inp.csv("table1")
    if measured is None:
        return missing_card(card, inp, "no table1.csv", "table1")
    rows = paper_comparison(measured, env)
    rows = rows[rows["variant"] == ""]
    card.links = section_link("table1", titles) + data_link(inp, "table1.csv")
    scale = rows["scale"].iloc[0]
    labels = [r.replace(" non-adaptive", "").replace(" adaptive", " adapt.") for r in rows["row"]]
    if scale != "gpu":
        rates = ", ".join(f"{r['row']} {r['particle_steps_per_s']:.3g}" for r in rows.to_dict("records"))
        counts = pd.to_numeric(rows["max_particles"], errors="coerce")
        card.answer = (f"Throughput at the {scale} scale ({counts.min():,.0f}-{counts.max():,.0f} particles): "
                       f"{rates} particle-steps per second.")
        card.detail = PAPER_NEEDS_GPU
        card.level = "warn"
        card.figure = gp.bars(labels, rows["particle_steps_per_s"], ylabel="particle-steps / s")
        return card
    matched = rows[rows["counts_match"]]
    other = rows[~rows["counts_match"]]
    parts = [f"{r['row']} {r['speedup_vs_paper']:.3g}x"
             + (f" [{r['speedup_lo']:.3g}, {r['speedup_hi']:.3g}]" if np.isfinite(r["speedup_lo"]) else "")
             for r in matched.to_dict("records")]
    card.answer = ("Per step faster than the paper at its particle counts: " + ", ".join(parts) + "."
                   if parts else "No row runs at the paper's particle counts: throughput only.")
    details = []
    if len(other):
        details.append("Other particle counts, so throughput (particle-steps/s) instead of a speed-up: " + ", ".join(
            f"{r['row']} {r['max_particles']:,.0f} against {r['paper_particles']:,.0f} particles, "
            f"{r['throughput_vs_paper']:.3g}x the paper's throughput" for r in other.to_dict("records")) + ".")
    first = rows.iloc[0].to_dict()
    details.append(f"{first['row']}: {step_time_text(first)}"
                   + (": no interval on the speed-ups." if not np.isfinite(first["speedup_lo"]) else
                      "; intervals: the paper's ms over our 95th and 5th percentile step."))
    card.detail = " ".join(details)
    card.figure = gp.bars(labels, rows["total_ms"], reference=rows["paper_ms"], ylabel="ms per step")
    return card


register(Study("table1", order=10, run=lambda ctx, scene: run_table1(ctx), sections=("table1", "phases"),
                report=(ReportSection("table1", "Table 1: phase timings against the paper", _table1, 10, "Table 1"),
                        ReportSection("phases", "Per-phase cost", _phases, 20, "Phases"),),
                glance=(GlanceCard(table1_card, 10),), produces={"table1": "cloudpbf table1 --out {out}"},
                outputs=("table1.csv",), command=table1_command, scale={"table1_timing_steps": TIMING_STEPS}))
