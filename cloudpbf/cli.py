"""The ``cloudpbf`` command: single runs, the studies, the report, and the demo that does it all.

    cloudpbf scenes                          list the shipped scenes
    cloudpbf run growing --steps 50          one run of a scene (particles or --solver grid)
    cloudpbf table1                          the paper's Table 1, measured here
    cloudpbf compare growing                 particles (non-adaptive, adaptive) against the grid, >= 5 seeds
    cloudpbf sweep                           run time against error, Pareto front
    cloudpbf stress                          stability map (dt, iterations, heating, alpha*dt)
    cloudpbf scaling                         ms per step against particle and cell counts
    cloudpbf report                          HTML report from OUT/data
    cloudpbf demo                            all of the above at a scale that fits this machine
    cloudpbf runs                            the runs of the cache; `runs show ID`, `runs prune`
    cloudpbf export RUN --format vtp         a run's snapshots for ParaView (vtu, vtp), Houdini (bgeo) or xarray (netcdf, zarr)
    cloudpbf adaptive-cost                   split and merge cost of the adaptive scenes (GPU benchmark)
    cloudpbf constant-gravity                growing with a constant gravity added (the cycling deviation)
    cloudpbf pbf-scaling                     ms per particle step at given sizes, one CSV (GPU benchmark)
    cloudpbf grid-scaling                    ms per grid step at n^3 cells on CPU and GPU, one CSV
    cloudpbf budgets ; cloudpbf cbl          both solvers' heat and water budgets; the dry boundary layer
    cloudpbf --version                       the installed version

Lists are comma-separated everywhere: --sizes 250000,1000000 --gravity 0.1,0.3.

Bad arguments exit with code 2 and a message naming the argument and what is allowed.
See docs/harness.md.
"""
from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, Solver, WorkersOpt, check_backend, check_folder, click, parse_list,
                              parse_overrides, refusals, refusing, scene_arg, study_context)
from cloudpbf.cli_runs import physics_lines, resolve_run, runs_app
from cloudpbf.export import ExportError, FormatError, export_run
from cloudpbf.grid_scaling import grid_scaling_command
from cloudpbf.store.identity import effective_seed
from cloudpbf.studies.registry import studies
from pbf_cuda._version import version
from pbf_cuda.scene import SceneError, list_scenes, load_scene

app = typer.Typer(name="cloudpbf", no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  rich_markup_mode=None,
                  help="Adaptive cloud simulation with Position Based Fluids: runs, studies and the report.")


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"cloudpbf {version()}")
        raise typer.Exit()


@app.callback()
def _main_options(
    version: Annotated[bool, typer.Option("--version", callback=_version_callback, is_eager=True,
                                          help="print the installed cloudpbf version and exit")] = False,
) -> None:
    """Adaptive cloud simulation with Position Based Fluids: runs, studies and the report."""


# ---- commands -------------------------------------------------------------------------------------
@app.command()
def scenes() -> None:
    """List the shipped scenes with their particle counts and descriptions."""
    for name in list_scenes():
        scene = load_scene(name)
        kind = "cloud" if scene.thermodynamics else "fluid"
        if scene.adaptive.enabled:
            kind += ", adaptive"
        typer.echo(f"{name:18s} {scene.estimated_particles():>9,} particles  {scene.time.steps:>5} steps  "
                   f"[{kind}]  {scene.description}")


@app.command()
def run(
    scene: Annotated[str, typer.Argument(help="scene name (see `cloudpbf scenes`) or path to a .toml file")],
    solver: Annotated[Solver, typer.Option(help="particle solver or grid baseline")] = Solver.particles,
    backend: BackendOpt = Backend.auto,
    steps: Annotated[Optional[int], typer.Option(min=1, max=10**7, help="steps (default: the scene's time.steps)")] = None,
    seed: Annotated[Optional[int], typer.Option(min=0, max=2**31 - 1, help="noise / initial-velocity seed")] = None,
    particles: Annotated[Optional[int], typer.Option(
        min=1, max=10**9, help="resample the scene to about this many particles")] = None,
    set_: Annotated[Optional[list[str]], typer.Option(
        "--set", help="override a scene field, e.g. --set pbf.iterations=8 (repeatable)")] = None,
    snapshot_every: Annotated[Optional[int], typer.Option(min=1, max=10**7, help="steps between diagnostics")] = None,
    record_steps: Annotated[Optional[bool], typer.Option(
        "--record-steps/--no-record-steps", help="stats() after every step (default: on for plain-fluid scenes)")] = None,
    cells_per_spacing: Annotated[float, typer.Option(min=0.05, max=64.0, help="grid: cells per particle spacing")] = 1.0,
    runs_root: RunsRootOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """One run of a scene through the run cache (a cached run returns at once).

    Exit code 0 when the run is stable, 1 when it went unstable (the reason, step and particles are printed)."""
    check_folder(runs_root, "--runs-root")
    scene_obj = scene_arg(scene, parse_overrides(set_))
    if particles is not None:
        try:
            scene_obj = scene_obj.with_particle_count(particles)
        except SceneError as exc:
            raise click.UsageError(f"--particles {particles}: {exc}") from None
    if solver is Solver.grid and not scene_obj.thermodynamics:
        raise typer.BadParameter(f"scene '{scene}' has no [atmosphere]; the grid baseline runs cloud scenes only",
                                 param_hint="'SCENE'")
    with refusals():
        check_backend(backend, solver.value)
    try:
        spec = runs.RunSpec(solver.value, scene_obj, backend=backend.value, steps=steps, seed=seed,
                            snapshot_every=snapshot_every, cells_per_spacing=cells_per_spacing,
                            record_steps=(not scene_obj.thermodynamics) if record_steps is None else record_steps)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    with refusals(particles):
        result = runs.execute(spec, runs_root, quiet=quiet)
    timings = result.timings()
    typer.echo(f"run directory: {result.path}{'  (cached)' if result.cached else ''}")
    typer.echo(f"{spec.solver} {scene_obj.name}: {result.step} steps, seed {effective_seed(spec.identity())}, "
               f"backend {result.backend}, "
               f"{result.max_particles or result.cells} {'particles (max)' if spec.solver == 'particles' else 'cells'}, "
               f"{result.step_wall_s:.2f} s in steps")
    for phase, t in timings.items():
        typer.echo(f"  {phase:15s} {t['mean_ms']:10.3f} ms/step")
    for line in physics_lines(result.path, result.info):
        typer.echo(line)
    if not result.stable:
        ids = ", ".join(map(str, result.particles)) or "none identified"
        typer.echo(f"UNSTABLE at step {result.step}: {result.reason}; particles: {ids}; "
                   f"last good step {result.last_good_step}", err=True)
        raise typer.Exit(1)


# ---- the studies' own commands (each declared in its study file, found through the registry) ------------
def _add_study_commands() -> None:
    for study in studies():
        if study.command is not None:
            app.command(study.name)(refusing(study.command))   # SceneError & co.: exit 2


_add_study_commands()
app.add_typer(runs_app, name="runs")


@app.command()
def report(out: OutOpt = DEFAULT_OUT) -> None:
    """Build OUT/index.html from what OUT/data holds (missing studies are shown as not run)."""
    from cloudpbf.studies.page import build_report  # harness extra (matplotlib, pandas)
    if not (out / "data").is_dir():
        raise typer.BadParameter(f"{out / 'data'} does not exist; run a study (e.g. `cloudpbf demo`) first",
                                 param_hint="'--out'")
    typer.echo(f"report: {build_report(out)}")


@app.command()
def demo(
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
    only: Annotated[Optional[str], typer.Option(
        help="comma-separated subset of the demo's studies (those of cloudpbf.studies.registry; an unknown "
             "name lists them)")] = None,
) -> None:
    """Everything: environment, Table 1, scaling, compare, sweep, stress, renders, then the report.

    Prints the path of index.html.  Exit code 1 when a study failed (the report shows which)."""
    from cloudpbf.studies.demo import run_demo, study_names  # harness extra (matplotlib, pandas)
    studies = study_names()
    chosen = tuple(s.strip() for s in only.split(",") if s.strip()) if only else studies
    bad = [s for s in chosen if s not in studies]
    if bad:
        raise typer.BadParameter(f"'{bad[0]}': allowed {', '.join(studies)}", param_hint="'--only'")
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            index, status = run_demo(ctx, only=chosen)
    failed = [name for name, st in status.items() if not st["ok"]]
    for name, st in status.items():
        typer.echo(f"  {name:8s} {'ok' if st['ok'] else 'FAILED: ' + st['error'].splitlines()[0]}"
                   + (f" ({st['seconds']} s)" if "seconds" in st else ""))
    if index is not None:
        typer.echo(f"report: {index}")
    if failed:
        raise typer.Exit(1)


class ExportFormat(str, Enum):
    vtu = "vtu"
    vtp = "vtp"
    bgeo = "bgeo"
    netcdf = "netcdf"
    zarr = "zarr"


@app.command()
def export(
    run_dir: Annotated[str, typer.Argument(metavar="RUN", help="a run folder, or a unique prefix of a run's folder "
                                                               "name or key (`cloudpbf runs` lists them)")],
    format: Annotated[ExportFormat, typer.Option("--format", "-f", help="vtu/vtp: a ParaView time series (.pvd "
                                                 "+ one file per snapshot); bgeo: Houdini, NAME.0001.bgeo, ... "
                                                 "one per snapshot (particle runs); netcdf/zarr: an xarray "
                                                 "Dataset (time, x, y, z) with CF attributes")] = ExportFormat.vtp,
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="an existing folder to write into, or the path the export becomes (default: RUN/export)")] = None,
    resolution: Annotated[Optional[str], typer.Option(
        help="netcdf/zarr of a particle run: deposition grid nx,ny,nz (default: one cell per particle spacing, "
             "the grid baseline's grid)")] = None,
    force: Annotated[bool, typer.Option("--force", help="replace an earlier export of the same run (never "
                                                         "anything else)")] = False,
    unverified: Annotated[bool, typer.Option("--unverified", help="export a run that has not finished or fails "
                                                                  "verification, its snapshots as they are")] = False,
    runs_root: RunsRootOpt = None,
) -> None:
    """Export a run's stored snapshots for ParaView (vtu, vtp), Houdini (bgeo) or xarray (netcdf, zarr).

    Particle runs: every particle with every field (units in the field data) as .vtu/.vtp or as
    Houdini's classic .bgeo (P, v and every field, units and time in detail attributes), or deposited
    on the grid baseline's grid as NetCDF/zarr, so a particle run and a grid run of one scene compare cell
    by cell.  Grid runs: the cell-centred fields (vtu, vtp, netcdf, zarr).  Nothing that exists is
    replaced (--force: an earlier export of the same run only); exit code 2 when the target exists, the
    run is unfinished or damaged, or memory or disk do not suffice."""
    cells = parse_list(resolution, "--resolution", int, 1, 4096, "64,64,64")
    if cells is not None and len(cells) != 3:
        raise typer.BadParameter(f"'{resolution}': expected three cell counts nx,ny,nz", param_hint="'--resolution'")
    if out is not None:
        text = str(out)
        if "\0" in text or len(text) > 4096:
            raise typer.BadParameter(f"'{text[:60]}': not a usable path", param_hint="'--out'")
    path = resolve_run(run_dir, runs_root)
    try:
        path = export_run(path, format.value, out, resolution=tuple(cells) if cells else None, force=force,
                          unverified=unverified)
    except FileNotFoundError as exc:
        raise typer.BadParameter(str(exc), param_hint="'RUN'") from None
    except FormatError as exc:
        raise typer.BadParameter(str(exc), param_hint="'--format'") from None
    except (ExportError, ValueError) as exc:
        raise click.UsageError(" ".join(str(exc).split())) from None
    except OSError as exc:                  # a folder on the way that cannot be made or read
        raise click.UsageError(f"{exc.filename or path}: {exc.strerror or exc}") from None
    if format is ExportFormat.bgeo:
        frames = sorted(path.glob("*.bgeo"))
        typer.echo(f"wrote {path}: {len(frames)} frames, {frames[0].name} .. {frames[-1].name}")
    else:
        typer.echo(f"wrote {path}")


app.command("grid-scaling")(refusing(grid_scaling_command))


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`cloudpbf`)."""
    try:
        app(args=argv, prog_name="cloudpbf")
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
