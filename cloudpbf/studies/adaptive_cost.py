"""Cost of splitting and merging at a given adaptive particle count, against the per-step targets.

The adaptive scenes (growing_adaptive, cycling_adaptive) run with their level-0 lattice spacing set
by --spacing, so that the adaptive particle count lands near the size of interest (45 m gives about
500k particles on average in growing_adaptive).  Solver stats are recorded every step, so the mean and
largest particle counts are the ones the timings were taken over.  Timings are ms per step after the
warm-up: ``splitting_ms`` and ``merging_ms`` are the paper's phases (``merge_passes_ms`` and
``compaction_ms`` are sub-timers inside merging), and ``pbf_ms`` is the same run's constraint solve,
the baseline each adaptive phase is compared with (``split_vs_pbf``, ``merge_vs_pbf``).

    cloudpbf adaptive-cost --spacing 45 --out reports/gpu/data/adaptive_cost.csv

writes scene,spacing_m,mean_particles,max_particles,splitting_ms,merging_ms,merge_passes_ms,
compaction_ms,pbf_ms,total_ms,split_vs_pbf,merge_vs_pbf,split_target_ms,merge_target_ms,meets_targets
(empty off the GPU or below 400k particles),device,commit (then backend, steps, stable, reason, run_dir).  Runs go through the run cache.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf import environment
from cloudpbf.cli_common import Backend, BackendOpt, QuietOpt, RunsRootOpt, parse_list, run_command, scene_arg
from cloudpbf.paper import PHASES
from cloudpbf.studies.registry import Study, register
from pbf_cuda.scene import load_scene

SCENES = ("growing_adaptive", "cycling_adaptive")
SPLIT_TARGET_MS = 0.3      # per step, at ~500k particles on an H100/H200
MERGE_TARGET_MS = 1.0
TARGET_MIN_PARTICLES = 400_000   # meets_targets is left empty below this mean count or off the GPU
WARMUP_STEPS = 5


def _per_step(timings: dict, phase: str, steps: int):
    return timings[phase]["total_ms"] / steps if phase in timings and steps else None


def adaptive_cost(scenes=SCENES, spacing: float = 45.0, steps: int = 500, backend: str = "auto",
                  runs_root=None, quiet: bool = False) -> pd.DataFrame:
    """One run per scene at the given level-0 spacing (m); a row of per-step costs for each."""
    rows = []
    for name in scenes:
        scene = load_scene(name).with_spacing(float(spacing)).replace(**{"time.steps": int(steps)})
        spec = runs.RunSpec("particles", scene, backend=backend, diagnostics=False, keep_snapshots=0,
                            record_steps=True, warmup_steps=WARMUP_STEPS)
        res = runs.execute(spec, runs_root, quiet=quiet)
        t = res.timings()
        timed = t["pbf"]["count"] if "pbf" in t else 0
        counts = res.steps_table()
        timed_counts = counts["n_particles"].iloc[WARMUP_STEPS:] if "n_particles" in counts else pd.Series(dtype=float)
        row = {"scene": name, "spacing_m": float(spacing),
               "mean_particles": float(timed_counts.mean()) if len(timed_counts) else None,
               "max_particles": res.max_particles}
        for phase in (*PHASES, "merge_passes", "compaction"):
            row[f"{phase}_ms"] = _per_step(t, phase, timed)
        ran = [row[f"{p}_ms"] for p in PHASES if row[f"{p}_ms"] is not None]
        row["total_ms"] = sum(ran) if ran else None
        pbf = row["pbf_ms"]
        row["split_vs_pbf"] = row["splitting_ms"] / pbf if pbf and row["splitting_ms"] is not None else None
        row["merge_vs_pbf"] = row["merging_ms"] / pbf if pbf and row["merging_ms"] is not None else None
        at_target_size = res.backend == "cuda" and (row["mean_particles"] or 0) >= TARGET_MIN_PARTICLES
        row.update(split_target_ms=SPLIT_TARGET_MS, merge_target_ms=MERGE_TARGET_MS,
                   meets_targets=(bool(res.stable and row["splitting_ms"] <= SPLIT_TARGET_MS
                                       and row["merging_ms"] <= MERGE_TARGET_MS) if at_target_size else None),
                   device=res.device, commit=environment.commit(), backend=res.backend, steps=int(steps),
                   stable=res.stable, reason=res.reason, run_dir=str(res.path))
        rows.append(row)
    return pd.DataFrame(rows)


COLUMNS = ("scene", "spacing_m", "mean_particles", "max_particles", "splitting_ms", "merging_ms", "merge_passes_ms",
           "compaction_ms", "pbf_ms", "total_ms", "split_vs_pbf", "merge_vs_pbf", "meets_targets", "device")


def adaptive_cost_command(
    spacing: Annotated[float, typer.Option(min=5.0, max=1000.0, help="level-0 lattice spacing, m")] = 45.0,
    steps: Annotated[int, typer.Option(min=3, max=100_000, help="steps per run")] = 500,
    scenes: Annotated[str, typer.Option(help="adaptive scenes, comma-separated")] = "growing_adaptive,cycling_adaptive",
    backend: BackendOpt = Backend.auto,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/latest/data/adaptive_cost.csv"),
    runs_root: RunsRootOpt = None, quiet: QuietOpt = False,
) -> None:
    """Split and merge ms per step of the adaptive scenes on a given level-0 spacing (GPU benchmark)."""
    names = parse_list(scenes, "--scenes", str, example="growing_adaptive,cycling_adaptive")
    for name in names:
        scene_arg(name, param="--scenes")
    if steps <= WARMUP_STEPS:
        raise typer.BadParameter(f"{steps}: must be > {WARMUP_STEPS} (the warm-up steps)", param_hint="'--steps'")
    frame = adaptive_cost(names, spacing, steps, backend.value, runs_root, quiet)
    runs.write_csv(frame, out)
    typer.echo(frame[list(COLUMNS)].to_string(index=False))
    typer.echo(f"targets: splitting <= {SPLIT_TARGET_MS} ms, merging <= {MERGE_TARGET_MS} ms per step; "
               f"wrote {out}")


register(Study("adaptive-cost", order=70, outputs=("adaptive_cost.csv",), sections=("phases",),
               produces={"adaptive_cost": "cloudpbf adaptive-cost --spacing 45 --out {out}/data/adaptive_cost.csv"},
               command=adaptive_cost_command))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.adaptive_cost ARGS`` is ``cloudpbf adaptive-cost ARGS``."""
    return run_command(adaptive_cost_command, "adaptive-cost", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
