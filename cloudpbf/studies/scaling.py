"""Cost per step against problem size, for the particle solver and the grid baseline.

Particles: the growing-cloud scene (or --scene) resampled to N particles, 4 PBF iterations, two
warm-up steps, then `timing_steps` timed steps.  ``step_ms`` is the wall time of one whole step
(all phases, as a user sees it); ``pbf_ms`` the pbf phase (eq. 1-4 constraint solve plus velocity
update) and ``neighbors_ms`` / ``solver_ms`` its sub-timers, each a mean over the timed steps.
Grid: the same scene on n^3 cells, per dtype, measured by cloudpbf.grid_scaling (``step_ms`` is the
grid's own mean step time, compiled before the clock starts).

    cloudpbf pbf-scaling --sizes 250000,1000000,4000000 --out reports/gpu/data/pbf_scaling.csv

writes particles,iterations,step_ms,neighbors_ms,solver_ms,device,commit (then pbf_ms, backend,
scene, steps, stable, reason, run_dir, and the roofline: roofline_ms, the least bytes a step moves over
the copy bandwidth measured in the same run (cloudpbf.roofline); roofline_ratio = step_ms / roofline_ms;
bytes_per_particle, the device memory the run held at its peak per particle (CUDA only);
step_bytes_per_particle and copy_bandwidth_gbs) to --out.  Particle runs go through the run cache, so a rerun
costs nothing.  For the grid alone: ``cloudpbf grid-scaling``.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Annotated, Optional

import pandas as pd
import typer

from cloudpbf.grid_scaling import measure
from cloudpbf.report import plots
from cloudpbf.report.common import Inputs, Section, _missing, _provenance, _table
from cloudpbf import environment, roofline, runs
from cloudpbf.solvers import ParticleAdapter
from cloudpbf.cli_common import (Backend, BackendOpt, DEFAULT_OUT, OutOpt, QuietOpt, RunsRootOpt, ScaleName, ScaleOpt,
                              parse_sizes, refusals, run_command, scene_arg, study_context)
from cloudpbf.studies.registry import ReportSection, Study, register
from pbf_cuda.scene import load_scene

SCENE = "growing"
WARMUP_STEPS = 2
PBF_COLUMNS = ("particles", "iterations", "step_ms", "neighbors_ms", "solver_ms", "device", "commit")
ROOFLINE_COLUMNS = ("roofline_ms", "roofline_ratio", "bytes_per_particle")
GRID_COLUMNS = ("cells", "step_ms", "dtype", "device", "commit")


def _mean(timings: dict, phase: str):
    return timings[phase]["mean_ms"] if phase in timings else None


def pbf_scaling(sizes, backend: str = "auto", runs_root=None, scene_name: str = SCENE, iterations: int = 4,
                timing_steps: int = 10, quiet: bool = False) -> pd.DataFrame:
    """One timing run per size, one after another; a DataFrame with PBF_COLUMNS first, then the roofline
    (cloudpbf.roofline: the device's copy bandwidth measured once, here, before the runs)."""
    rows = []
    bandwidth = roofline.copy_bandwidth(ParticleAdapter.resolve_backend(backend))
    for n in sizes:
        scene = load_scene(scene_name).with_particle_count(int(n)).replace(**{
            "pbf.iterations": int(iterations), "time.steps": WARMUP_STEPS + timing_steps,
            "time.snapshot_every": WARMUP_STEPS + timing_steps})
        spec = runs.RunSpec("particles", scene, backend=backend, diagnostics=False, keep_snapshots=0,
                            warmup_steps=WARMUP_STEPS)
        res = runs.execute(spec, runs_root, quiet=quiet)
        t = res.timings()
        floor = roofline.roofline_ms(scene, res.max_particles, bandwidth)
        held = res.info.get("device_bytes")
        rows.append({"particles": res.max_particles, "iterations": int(iterations),
                     "step_ms": res.step_ms if res.stable else None,
                     "neighbors_ms": _mean(t, "neighbors"), "solver_ms": _mean(t, "solver"),
                     "device": res.device, "commit": environment.commit(), "pbf_ms": _mean(t, "pbf"),
                     "backend": res.backend, "scene": scene_name, "steps": timing_steps,
                     "stable": res.stable, "reason": res.reason, "run_dir": str(res.path),
                     "neighbor_list": bool(scene.pbf.neighbor_list),
                     "roofline_ms": floor,
                     "roofline_ratio": res.step_ms / floor if floor and res.stable else None,
                     "bytes_per_particle": held / res.max_particles if held else None,
                     "step_bytes_per_particle": roofline.step_bytes(scene),
                     "copy_bandwidth_gbs": bandwidth / 1e9 if bandwidth else None})
    return pd.DataFrame(rows)


def grid_scaling(sizes, scene_name: str = SCENE, dtypes=None, timing_steps: int = 10) -> pd.DataFrame:
    """One measurement per n^3 grid and dtype on jax's default device, by cloudpbf.grid_scaling.measure
    (compiled first, WARMUP_STEPS untimed steps, then `timing_steps`); a DataFrame with GRID_COLUMNS first."""
    import jax  # grid extra (jax)
    platform = jax.default_backend()
    dtypes = dtypes or (("float64",) if platform == "cpu" else ("float32",))   # each solver's default precision
    scene = load_scene(scene_name)
    rows = []
    for n in sizes:
        for dtype in dtypes:
            r = measure(scene, int(n), platform, dtype, timing_steps, WARMUP_STEPS)
            device = environment.cpu_name() if platform == "cpu" else r["device"]
            rows.append({"cells": r["cells"], "step_ms": float(r["step_ms"]), "dtype": dtype, "device": device,
                         "commit": environment.commit(), "n": int(n), "wall_ms": r["wall_ms"],
                         "compile_s": r["compile_s"], "substeps": r["substeps"], "platform": platform})
    return pd.DataFrame(rows, columns=[*GRID_COLUMNS, "n", "wall_ms", "compile_s", "substeps", "platform"])


def run_scaling(ctx) -> dict[str, pd.DataFrame]:
    """The study at the context's scale: OUT/data/pbf_scaling.csv and grid_scaling.csv."""
    scale = ctx.scale
    ctx.say(f"scaling: particles {list(scale.scaling_particles)}, grid {list(scale.scaling_grid_cells)}^3")
    pbf = pbf_scaling(scale.scaling_particles, ctx.backend, ctx.runs_root, timing_steps=scale.timing_steps,
                      quiet=ctx.quiet)
    runs.write_csv(pbf, ctx.data / "pbf_scaling.csv")
    grid = grid_scaling(scale.scaling_grid_cells, timing_steps=scale.timing_steps)
    runs.write_csv(grid, ctx.data / "grid_scaling.csv")
    return {"pbf_scaling": pbf, "grid_scaling": grid}


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.scaling ARGS`` is ``cloudpbf pbf-scaling ARGS``."""
    return run_command(pbf_scaling_command, "pbf-scaling", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())


def scaling_command(
    sizes: Annotated[Optional[str], typer.Option(help="particle counts, comma-separated (default: the scale's)")] = None,
    grid_sizes: Annotated[Optional[str], typer.Option(help="n for n^3 grids, comma-separated (default: the scale's)")] = None,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, quiet: QuietOpt = False,
) -> None:
    """ms per step against particle count (pbf_scaling.csv) and grid cells (grid_scaling.csv)."""
    particle_sizes = parse_sizes(sizes, "--sizes", 100)
    cell_sizes = parse_sizes(grid_sizes, "--grid-sizes", 2)
    with study_context(out, runs_root, scale, backend, None, None, quiet) as ctx:
        if particle_sizes or cell_sizes:
            ctx.scale = dataclasses.replace(ctx.scale, scaling_particles=tuple(particle_sizes or ctx.scale.scaling_particles),
                                            scaling_grid_cells=tuple(cell_sizes or ctx.scale.scaling_grid_cells))
        with refusals():
            frames = run_scaling(ctx)
    typer.echo(frames["pbf_scaling"][[*PBF_COLUMNS, *ROOFLINE_COLUMNS]].to_string(index=False))
    typer.echo(frames["grid_scaling"][list(GRID_COLUMNS)].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'pbf_scaling.csv'} and grid_scaling.csv")


def pbf_scaling_command(
    sizes: Annotated[str, typer.Option(help="particle counts, comma-separated")] = "250000,1000000,4000000",
    steps: Annotated[int, typer.Option(min=1, max=10_000, help="timed steps per size (after 2 warm-up steps)")] = 20,
    iterations: Annotated[int, typer.Option(min=1, max=200, help="PBF solver iterations")] = 4,
    scene: Annotated[str, typer.Option(help="scene name or path")] = "growing",
    backend: BackendOpt = Backend.auto,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/latest/data/pbf_scaling.csv"),
    runs_root: RunsRootOpt = None, quiet: QuietOpt = False,
) -> None:
    """ms per particle step at the given sizes, one CSV (the GPU benchmark form of `scaling`)."""
    counts = parse_sizes(sizes, "--sizes", 100)
    scene_arg(scene, param="--scene")
    frame = pbf_scaling(counts, backend.value, runs_root, scene, iterations, steps, quiet)
    runs.write_csv(frame, out)
    typer.echo(frame[[*PBF_COLUMNS, *ROOFLINE_COLUMNS]].to_string(index=False))
    typer.echo(f"wrote {out}")


# ---- report: step time against size --------------------------------------------------------------
def _scaling(inp: Inputs, sec: Section, env: dict | None) -> None:
    frames = []
    for study, solver, unit, plot in (("pbf_scaling", "particle solver", "particle", plots.pbf_scaling_plot),
                                      ("grid_scaling", "grid baseline", "cell", plots.grid_scaling_plot)):
        frame, path = inp.csv(study)
        frames.append(frame)
        if frame is None:
            _missing(sec, f"{study}.csv ({solver} step time against {unit} count)", study, inp)
            continue
        name = "PBF" if study == "pbf_scaling" else solver
        sec.add("image", plot(frame), caption=f"{name} step (log-log) from {path.name}")
        extra = frame.copy()
        if "step_ms" in extra and f"{unit}s" in extra:
            extra[f"ns per {unit}"] = 1e6 * extra["step_ms"] / extra[f"{unit}s"]
        sec.add("table", _table(extra))
    sec.provenance = _provenance(*frames, env=env)


register(Study("scaling", order=20, run=lambda ctx, scene: run_scaling(ctx), sections=("scaling",),
                report=(ReportSection("scaling", "Scaling", _scaling, 30),),
                produces={"grid_scaling": "cloudpbf grid-scaling --sizes 32,64,128 --out {out}/data/grid_scaling.csv"},
                outputs=("pbf_scaling.csv", "grid_scaling.csv"),
                scale={"scaling_particles": {"smoke": (2000, 8000), "cpu": (10_000, 50_000, 250_000),
                                             "gpu": (250_000, 1_000_000, 4_000_000)},
                       "scaling_grid_cells": {"smoke": (12, 20), "cpu": (16, 32, 48), "gpu": (32, 64, 96)},  # n^3
                       "timing_steps": {"smoke": 5, "cpu": 10, "gpu": 20}},    # timed steps after 2 warm-up steps
                command=scaling_command))
register(Study("pbf-scaling", order=75, outputs=("pbf_scaling.csv",), sections=("scaling",),
               produces={"pbf_scaling": "cloudpbf scaling --out {out}"},
               command=pbf_scaling_command))
