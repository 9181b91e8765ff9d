"""Speed-up of a sweep on several GPUs against one: the sweep study's particle runs, once per GPU count.

For each count in ``--gpus-list`` (default 1,2) the particle runs of the sweep (``sweep_plan``: the
spacing, iteration and split-threshold runs, non-adaptive and adaptive) go to a dask-cuda cluster of
that many GPU workers (``--gpus N``: one worker per GPU, each pinned through CUDA_VISIBLE_DEVICES),
into a fresh run cache of their own (OUT/multigpu-runs/gpus-N, removed afterwards unless --keep-runs),
so nothing is served from an earlier count's results.  The wall time is that of the whole batch,
from submitting the first run to the last result (cluster start-up excluded, measured separately);
the speed-up of a count is the 1-GPU wall time over its own.  Grid runs are left out: they run on
jax, whose placement dask-cuda does not decide.

    cloudpbf multigpu-sweep --gpus-list 1,2 --scale gpu --out reports/gpu

writes OUT/data/multigpu_sweep.csv: device, commit, gpus, runs, wall_s, speedup, then startup_s (the
cluster's start), workers (the CUDA_VISIBLE_DEVICES of each worker, as the workers report it),
scale, stable (runs that ended stably).
"""
from __future__ import annotations

import os
import shutil
import time
from typing import Annotated, Optional

import pandas as pd
import typer

from cloudpbf import environment, runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, OutOpt, QuietOpt, ScaleName, ScaleOpt, parse_list,
                              refusals, study_context)
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.registry import Study, register
from cloudpbf.studies.plans import sweep_plan

OUTPUT = "multigpu_sweep.csv"


def sweep_particle_specs(ctx: StudyContext) -> list[runs.RunSpec]:
    """The particle runs of the sweep study at the context's scale (unique keys, plan order)."""
    specs = {}
    for p in sweep_plan(ctx):
        if p["method"] == "particles":
            specs.setdefault(p["spec"].key(), p["spec"])
    return list(specs.values())


def _worker_devices(ctx: StudyContext) -> str:
    """'CUDA_VISIBLE_DEVICES' of every worker, as they report it ('0,1 | 1,0')."""
    seen = ctx.client().run(lambda: os.environ.get("CUDA_VISIBLE_DEVICES", ""))
    return " | ".join(sorted(str(v) for v in seen.values()))


def time_sweep(ctx: StudyContext, specs: list[runs.RunSpec], gpus: int) -> dict:
    """Run `specs` on `gpus` GPU workers into ctx.runs_root; wall time of the batch and of the start-up."""
    start = time.perf_counter()
    ctx.client()
    startup = time.perf_counter() - start
    workers = _worker_devices(ctx)
    begin = time.perf_counter()
    results = ctx.run_parallel(specs, f"multigpu-{gpus}")
    wall = time.perf_counter() - begin
    return {"gpus": gpus, "runs": len(specs), "wall_s": wall, "startup_s": startup, "workers": workers,
            "stable": sum(bool(r.stable) for r in results)}


def run_multigpu(base: StudyContext, counts: list[int], keep_runs: bool = False,
                 cuda_cluster_factory=None) -> pd.DataFrame:
    """Time the sweep's particle runs on each GPU count; write OUT/data/multigpu_sweep.csv."""
    rows = []
    for gpus in counts:
        root = base.out / "multigpu-runs" / f"gpus-{gpus}"
        if root.exists():
            shutil.rmtree(root)               # a fresh cache: every run computed on this count
        ctx = StudyContext(out=base.out, scale=base.scale, runs_root=root, backend=base.backend, quiet=base.quiet,
                           gpus=gpus, cuda_cluster_factory=cuda_cluster_factory)
        ctx.check_gpus()
        specs = sweep_particle_specs(ctx)
        base.say(f"multigpu: {len(specs)} runs on {ctx.cluster_description()}")
        with ctx:
            rows.append(time_sweep(ctx, specs, gpus))
        base.say(f"multigpu: {gpus} GPU(s): {rows[-1]['wall_s']:.1f} s for {len(specs)} runs")
        if not keep_runs:
            shutil.rmtree(root, ignore_errors=True)
        frame = _table(base, rows)            # written after every count: a batch cut short keeps what finished
    return frame


def _table(base: StudyContext, rows: list[dict]) -> pd.DataFrame:
    frame = pd.DataFrame(rows)
    one = frame.loc[frame["gpus"] == 1, "wall_s"]
    frame["speedup"] = (float(one.iloc[0]) / frame["wall_s"]) if len(one) else float("nan")
    frame.insert(0, "device", environment.device_description(base.particle_backend()))
    frame.insert(1, "commit", base.commit)
    frame["scale"] = base.scale.environment_label
    cols = ["device", "commit", "gpus", "runs", "wall_s", "speedup", "startup_s", "workers", "scale", "stable"]
    frame = frame[cols]
    runs.write_csv(frame, base.data / OUTPUT)
    return frame


def multigpu_command(
    out: OutOpt = DEFAULT_OUT, scale: ScaleOpt = ScaleName.auto, backend: BackendOpt = Backend.auto,
    quiet: QuietOpt = False,
    gpus_list: Annotated[Optional[str], typer.Option(
        "--gpus-list", help="comma-separated GPU counts to time, e.g. 1,2 (the 1-GPU time is the speed-up's base)")]
    = "1,2",
    keep_runs: Annotated[bool, typer.Option("--keep-runs", help="keep OUT/multigpu-runs (default: removed)")] = False,
) -> None:
    """Speed-up of the sweep's particle runs on N GPUs against 1 (dask-cuda; writes multigpu_sweep.csv)."""
    counts = parse_list(gpus_list, "--gpus-list", int, lo=1, hi=1024, example="1,2")
    with study_context(out, None, scale, backend, None, None, quiet, gpus=str(max(counts))) as base:
        with refusals():
            frame = run_multigpu(base, counts, keep_runs)
    typer.echo(frame[["gpus", "runs", "wall_s", "speedup", "workers"]].to_string(index=False))
    typer.echo(f"wrote {base.data / OUTPUT}")


register(Study("multigpu-sweep", order=85, outputs=(OUTPUT,), command=multigpu_command))
