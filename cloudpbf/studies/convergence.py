"""Both solvers against resolution, over several seeds: convergence.csv (docs/validation.md, "Convergence of both
solvers with resolution").

The cloud scene is run by the particle solver (non-adaptive) at each spacing h and by the grid baseline with cells
of about h along the longest axis (round(L / h) cells), every resolution with the same noise seeds (the seed shifts
the ground-heating pattern, eq. 5, identically in both solvers and at every h).  Particle runs are deposited on the
analysis grid of the middle spacing; grid runs are analysed on their own cells.  Each run gives the time means
over its cloudy period (cover above CLOUDY_COVER) of cover, mean LWP, cloud base and top
(cloudpbf.statistics.cloudy_period_means).

    cloudpbf convergence growing --resolutions 68,54,43,34,27 --seeds 3 --out reports/gpu

Output OUT/data/convergence.csv: one row per run (seed 0, 1, ...) and one per solver and resolution with seed
"mean" (the mean over its stable seeds): solver, resolution_m, seed, stable, cloud_base_mean, cloud_top_mean (m),
cover_mean (fraction), lwp_mean (kg/m^2), parameter (spacing | cells), method, cells, particles, device, commit.
The report's compare section draws the mean rows and fits each statistic's order of convergence, bootstrapped
over the seeds (cloudpbf.report.inference.convergence_orders).
"""
from __future__ import annotations

import math
from typing import Annotated, Optional

import numpy as np
import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                                 ScaleOpt, SchedulerOpt, WorkersOpt, click, parse_list, refusals, scene_arg,
                                 study_context)
from cloudpbf.statistics import CLOUD_MEANS, cloudy_period_means, grid_for_scene
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.plans import SMOKE_CLOUD_BOX
from cloudpbf.studies.registry import Study, register
from pbf_cuda.scene import load_scene

MEANS = tuple(f"{name}_mean" for name, _ in CLOUD_MEANS)
COLUMNS = ("solver", "resolution_m", "seed", "stable", *MEANS, "parameter", "method", "cells", "particles", "device",
           "commit")


def convergence_plan(ctx: StudyContext, scene_name: str = "growing", resolutions=None,
                     seeds: int | None = None) -> list[tuple[str, float, int, runs.RunSpec]]:
    """(solver, resolution in m, seed, spec) of every run: particles at spacing h, the grid at round(L / h) cells
    along the longest axis L (the others in proportion), each at seeds 0..seeds-1."""
    scale = ctx.scale
    resolutions = sorted((float(h) for h in (resolutions or scale.convergence_resolutions)), reverse=True)
    seeds = seeds or scale.convergence_seeds
    base = load_scene(scene_name)
    if base.atmosphere is None:
        raise ValueError(f"convergence needs a cloud scene (one with an [atmosphere] section); '{scene_name}' has none")
    if scale.convergence_box:
        base = base.replace(**scale.convergence_box)
    middle = base.replace(**{"particles.spacing": resolutions[len(resolutions) // 2]})
    analysis, _ = grid_for_scene(middle)
    size = max(base.domain.size)
    plan = []
    for seed in range(seeds):
        for h in resolutions:
            plan.append(("particles", h, seed, runs.RunSpec("particles", base.replace(**{"particles.spacing": h}),
                                                            backend=ctx.backend, seed=seed, keep_snapshots=1,
                                                            diagnostics_resolution=analysis)))
            cells = tuple(max(2, int(round(length / h))) for length in base.domain.size)
            plan.append(("grid", size / max(cells), seed, runs.RunSpec("grid", middle, seed=seed, resolution=cells,
                                                                       keep_snapshots=1)))
    return plan


def convergence_rows(plan, results, commit: str) -> pd.DataFrame:
    """convergence.csv from the plan and its results (in plan order): one row per run, then the mean rows (seed
    "mean": each statistic's mean over the stable seeds of a solver and resolution; stable: all were)."""
    rows = []
    for (solver, h, seed, spec), res in zip(plan, results):
        rows.append({"solver": solver, "resolution_m": round(h, 1), "seed": str(seed), "stable": bool(res.stable),
                     **cloudy_period_means(res.stats() if res.stable else pd.DataFrame()),
                     "parameter": "spacing" if solver == "particles" else "cells", "method": solver,
                     "cells": "x".join(str(c) for c in spec.resolution) if spec.resolution else "",
                     "particles": getattr(res, "max_particles", math.nan), "device": str(getattr(res, "device", "")),
                     "commit": commit})
    frame = pd.DataFrame(rows, columns=COLUMNS)
    if not len(frame):
        return frame
    means = []
    for (solver, h), group in frame.groupby(["solver", "resolution_m"], sort=False):
        stable = group[group["stable"]]
        row = {**group.iloc[0].to_dict(), "seed": "mean", "stable": bool(group["stable"].all()),
               "particles": pd.to_numeric(group["particles"], errors="coerce").mean(),
               "device": " / ".join(sorted(set(group["device"]))), "commit": commit}
        row.update({m: float(np.nanmean(stable[m])) if stable[m].notna().any() else math.nan for m in MEANS})
        means.append(row)
    return pd.concat([frame, pd.DataFrame(means, columns=COLUMNS)], ignore_index=True)


def run_convergence(ctx: StudyContext, scene_name: str = "growing", resolutions=None,
                    seeds: int | None = None) -> pd.DataFrame:
    """Run (or read) every solver x resolution x seed and write OUT/data/convergence.csv."""
    plan = convergence_plan(ctx, scene_name, resolutions, seeds)
    results = ctx.run_parallel([spec for *_, spec in plan], "convergence")
    frame = convergence_rows(plan, results, ctx.commit)
    runs.write_csv(frame, ctx.data / "convergence.csv")
    return frame


def convergence_command(
    scene: Annotated[str, typer.Argument(help="a cloud scene")] = "growing",
    resolutions: Annotated[Optional[str], typer.Option(
        help="particle spacings = grid cell sizes, m, comma-separated (default: the scale's)")] = None,
    seeds: Annotated[Optional[int], typer.Option(min=1, max=1000, help="noise seeds per resolution "
                                                 "(>= 3 for bootstrap intervals on the orders)")] = None,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
) -> None:
    """Both solvers at several resolutions and seeds: convergence.csv, the report's orders of convergence."""
    scene_arg(scene)
    values = parse_list(resolutions, "--resolutions", float, 1.0, 1e4, "68,54,43,34,27")
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        try:
            with refusals():
                frame = run_convergence(ctx, scene, values, seeds)
        except ValueError as exc:
            raise click.UsageError(str(exc)) from None
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        typer.echo(frame[frame["seed"] == "mean"][["solver", "resolution_m", "stable", *MEANS]].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'convergence.csv'}")


register(Study("convergence", order=35, sections=("compare",), outputs=("convergence.csv",),
               produces={"convergence": "cloudpbf convergence growing --out {out}"},
               scale={"convergence_resolutions": {"smoke": (100.0, 80.0, 64.0, 50.0),
                                                  "cpu": (100.0, 86.0, 74.0, 64.0),
                                                  "gpu": (68.0, 54.0, 43.0, 34.0, 27.0)},
                      "convergence_seeds": {"smoke": 3, "cpu": 3, "gpu": 3},
                      # the smoke scale's small box (None: the scene's own domain and steps)
                      "convergence_box": {"smoke": SMOKE_CLOUD_BOX, "cpu": None, "gpu": None}},
               command=convergence_command))
