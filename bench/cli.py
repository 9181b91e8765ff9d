"""The ``cloudpbf`` command: single runs, the studies, the report, and the demo that does it all.

    cloudpbf scenes                          list the shipped scenes
    cloudpbf run growing --steps 50          one run of a scene (particles or --solver grid)
    cloudpbf table1                          the paper's Table 1, measured here
    cloudpbf compare growing                 particles (non-adaptive, adaptive) against the grid, >= 5 seeds
    cloudpbf cycling                         paper example 2: clouds' disappear/reappear cycles, both solvers
    cloudpbf sweep                           run time against error, Pareto front
    cloudpbf stress                          stability map (dt, iterations, heating, alpha*dt)
    cloudpbf scaling                         ms per step against particle and cell counts
    cloudpbf report                          HTML report from OUT/data
    cloudpbf demo                            all of the above at a scale that fits this machine
    cloudpbf export RUN --format vtp         a run's snapshots for ParaView (vtu, vtp) or xarray (netcdf, zarr)
    cloudpbf adaptive-cost                   split and merge cost of the adaptive scenes (GPU benchmark)
    cloudpbf constant-gravity                growing with a constant gravity added (the cycling deviation)
    cloudpbf pbf-scaling                     ms per particle step at given sizes, one CSV (GPU benchmark)
    cloudpbf grid-scaling                    ms per grid step at n^3 cells on CPU and GPU, one CSV
    cloudpbf --version                       the installed version

Lists are comma-separated everywhere: --sizes 250000,1000000 --gravity 0.1,0.3.

Bad arguments exit with code 2 and a message naming the argument and what is allowed.
See docs/harness.md.
"""
from __future__ import annotations

import contextlib
import sys
import tomllib
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import importlib

import typer
import typer.rich_utils

# The click that typer runs on: the click package up to typer 0.24, typer's own vendored copy from 0.25
# on.  Exceptions must come from that one, or typer does not turn them into "Usage: ... Error: ..." and
# exit code 2.
# `click.UsageError`, `click.BadParameter`, `click.ClickException`, ... below are that click's exceptions.
click = importlib.import_module(typer.BadParameter.__module__)

# typer 0.19 escapes the "[default: ...]" / "[required]" of option help for rich's HTML export even when
# rich_markup_mode is None, so plain help would print "\\[default: ...]".  Plain help has no markup
# to escape: show it as written.
typer.rich_utils.escape_before_html_export = lambda text: text.strip()

app = typer.Typer(name="cloudpbf", no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  rich_markup_mode=None,
                  help="Adaptive cloud simulation with Position Based Fluids: runs, studies and the report.")

DEFAULT_OUT = Path("reports/latest")


class Solver(str, Enum):
    particles = "particles"
    grid = "grid"


class Backend(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


class ScaleName(str, Enum):
    auto = "auto"
    smoke = "smoke"
    cpu = "cpu"
    gpu = "gpu"


OutOpt = Annotated[Path, typer.Option("--out", help="output folder: data/ (CSV, JSON, renders) and index.html")]
RunsRootOpt = Annotated[Optional[Path], typer.Option(
    "--runs-root", help="run cache folder (default: $CLOUDPBF_RUNS, else runs/ of the checkout, else the user "
                        "cache folder, e.g. ~/.cache/cloudpbf/runs)")]
ScaleOpt = Annotated[ScaleName, typer.Option(
    "--scale", help="smoke (CI, minutes), cpu (~50k particles), gpu (the paper's counts); auto: gpu if CUDA")]
BackendOpt = Annotated[Backend, typer.Option("--backend", help="particle solver backend")]
WorkersOpt = Annotated[Optional[int], typer.Option(
    "--workers", min=1, max=4096, help="dask workers of the local cluster (default: CPU cores; 1 per GPU on GPU)")]
SchedulerOpt = Annotated[Optional[str], typer.Option(
    "--scheduler", help="address of an existing dask scheduler (e.g. tcp://host:8786) instead of a local "
                        "cluster; 'inline': no dask, the runs one by one in this process")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars or progress messages")]


# ---- helpers ------------------------------------------------------------------------------------
def _load_scene(name: str, overrides: dict | None = None):
    """A scene by name or path; unknown names list the shipped scenes (exit code 2)."""
    from pbf_cuda.scene import SceneError, list_scenes, load_scene
    path = Path(name)
    try:
        is_file = path.suffix == ".toml" and path.exists()
    except (OSError, ValueError):                 # a name too long for the filesystem, a NUL byte
        is_file = False
    if name not in list_scenes() and not is_file:
        if len(name) > 80:
            name = name[:77] + "..."
        raise typer.BadParameter(f"unknown scene '{name}'; shipped scenes: {', '.join(list_scenes())} "
                                 f"(or a path to a .toml file)", param_hint="'SCENE'")
    try:
        return load_scene(name, **(overrides or {}))
    except SceneError as exc:
        raise click.UsageError(str(exc)) from None


def _parse_overrides(items: list[str] | None) -> dict:
    """--set section.field=value (value in TOML syntax: 8, 0.5, true, "wall", [1, 2, 3])."""
    out = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        if not sep or "." not in key:
            raise typer.BadParameter(f"'{item}': expected section.field=value, e.g. pbf.iterations=8",
                                     param_hint="'--set'")
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw                       # a bare word: a string
        out[key.strip()] = value
    return out


def _parse_sizes(text: str | None, name: str, lo: int) -> list[int] | None:
    if text is None:
        return None
    try:
        sizes = [int(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise typer.BadParameter(f"'{text}': expected comma-separated integers, e.g. 250000,1000000",
                                 param_hint=f"'{name}'") from None
    if not sizes or min(sizes) < lo:
        raise typer.BadParameter(f"'{text}': every size must be an integer >= {lo}", param_hint=f"'{name}'")
    return sizes


def _check_folder(path: Optional[Path], option: str) -> None:
    """A folder option: an existing folder or a path whose first existing ancestor is a writable folder.
    Without --runs-root, $CLOUDPBF_RUNS is checked in its place."""
    import os
    if path is None and option == "--runs-root" and os.environ.get("CLOUDPBF_RUNS"):
        path, option = Path(os.environ["CLOUDPBF_RUNS"]), "$CLOUDPBF_RUNS"
    if path is None:
        return
    text = str(path)
    shown = text if len(text) <= 80 else text[:77] + "..."
    if "\0" in text or len(text) > 4096:
        raise typer.BadParameter(f"'{shown}': not a usable folder path", param_hint=f"'{option}'")
    probe = Path(path).absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe == Path(path).absolute() and not probe.is_dir():
        raise typer.BadParameter(f"'{shown}' is a file, expected a folder", param_hint=f"'{option}'")
    if not probe.is_dir():
        raise typer.BadParameter(f"'{shown}': {probe} is a file, so the folder cannot be made",
                                 param_hint=f"'{option}'")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise typer.BadParameter(f"'{shown}': {probe} is not writable", param_hint=f"'{option}'")


def _check_backend(backend: Backend, solver: str = "particles") -> None:
    """--backend cuda where no CUDA device (or no CUDA build) exists: exit 2 naming the option."""
    if backend is not Backend.cuda:
        return
    if solver == "grid":
        try:
            import jax
            ok = bool(jax.devices("gpu"))
        except Exception:  # noqa: BLE001  (jax raises RuntimeError when no GPU backend exists)
            ok = False
        why = "jax sees no GPU"
    else:
        from pbf_cuda.simulation import _core, available_backends
        ok = "cuda" in available_backends()
        why = "pbf_cuda was built without CUDA" if not _core().cuda_built() else "no CUDA device is visible"
    if not ok:
        raise typer.BadParameter(f"'cuda' is not available here ({why}); use auto or cpu", param_hint="'--backend'")


@contextlib.contextmanager
def _refusals(particles: Optional[int] = None):
    """What a command cannot do as asked ends in one line and exit code 2: scene and memory checks,
    an unusable scheduler, a stale compiled solver."""
    from bench.studies.context import SchedulerError
    from pbf_cuda.buildinfo import StaleBuildError
    from pbf_cuda.scene import SceneError
    try:
        yield
    except SceneError as exc:
        prefix = f"--particles {particles}: " if particles is not None else ""
        raise click.UsageError(prefix + " ".join(str(exc).split())) from None
    except SchedulerError as exc:
        raise typer.BadParameter(str(exc), param_hint="'--scheduler'") from None
    except StaleBuildError as exc:
        raise click.UsageError(str(exc)) from None


def _context(out: Path, runs_root: Optional[Path], scale: ScaleName, backend: Backend, workers: Optional[int],
             scheduler: Optional[str], quiet: bool):
    from bench import runs
    from bench.studies.context import SchedulerError, StudyContext, check_scheduler_address
    from bench.studies.scales import resolve_scale
    from bench.studies.environment import write_environment
    _check_folder(out, "--out")
    _check_folder(runs_root, "--runs-root")
    with _refusals():
        _check_backend(backend)
    if scheduler is not None:
        try:
            check_scheduler_address(scheduler)
        except SchedulerError as exc:
            raise typer.BadParameter(str(exc), param_hint="'--scheduler'") from None
    with _refusals():
        ctx = StudyContext(out=out, scale=resolve_scale(scale.value), runs_root=runs_root or runs.default_root(),
                           backend=backend.value, workers=workers, scheduler=scheduler, quiet=quiet)
        if scheduler is not None and scheduler != "inline":
            ctx.client()                  # fail now, in one line, when no scheduler answers
    write_environment(ctx.out, ctx.scale.environment_label, ctx.particle_backend())   # every study says where it ran
    return ctx


def _parse_list(text: str | None, name: str, kind=int, lo=None, hi=None, example: str = "1,2,3") -> list | None:
    """A comma-separated list option (the one list syntax of every command): '0.1,0.3' -> [0.1, 0.3]."""
    if text is None:
        return None
    try:
        values = [kind(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise typer.BadParameter(f"'{text}': expected comma-separated {kind.__name__}s, e.g. {example}",
                                 param_hint=f"'{name}'") from None
    if not values:
        raise typer.BadParameter(f"'{text}': expected at least one value, e.g. {example}", param_hint=f"'{name}'")
    for v in values:
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise typer.BadParameter(f"'{v}': allowed range [{lo}, {hi}]", param_hint=f"'{name}'")
    return values


def _version_callback(value: bool) -> None:
    if value:
        from pbf_cuda._version import version
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
    from pbf_cuda.scene import list_scenes, load_scene
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
    from bench import runs
    _check_folder(runs_root, "--runs-root")
    scene_obj = _load_scene(scene, _parse_overrides(set_))
    if particles is not None:
        from pbf_cuda.scene import SceneError
        try:
            scene_obj = scene_obj.with_particle_count(particles)
        except SceneError as exc:
            raise click.UsageError(f"--particles {particles}: {exc}") from None
    if solver is Solver.grid and not scene_obj.thermodynamics:
        raise typer.BadParameter(f"scene '{scene}' has no [atmosphere]; the grid baseline runs cloud scenes only",
                                 param_hint="'SCENE'")
    with _refusals():
        _check_backend(backend, solver.value)
    try:
        spec = runs.RunSpec(solver.value, scene_obj, backend=backend.value, steps=steps, seed=seed,
                            snapshot_every=snapshot_every, cells_per_spacing=cells_per_spacing,
                            record_steps=(not scene_obj.thermodynamics) if record_steps is None else record_steps)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    with _refusals(particles):
        result = runs.execute(spec, runs_root, quiet=quiet)
    timings = result.timings()
    typer.echo(f"run directory: {result.path}{'  (cached)' if result.cached else ''}")
    typer.echo(f"{spec.solver} {scene_obj.name}: {result.step} steps, seed {seed}, backend {result.backend}, "
               f"{result.max_particles or result.cells} {'particles (max)' if spec.solver == 'particles' else 'cells'}, "
               f"{result.step_wall_s:.2f} s in steps")
    for phase, t in timings.items():
        typer.echo(f"  {phase:15s} {t['mean_ms']:10.3f} ms/step")
    if not result.stable:
        ids = ", ".join(map(str, result.particles)) or "none identified"
        typer.echo(f"UNSTABLE at step {result.step}: {result.reason}; particles: {ids}; "
                   f"last good step {result.last_good_step}", err=True)
        raise typer.Exit(1)


@app.command()
def table1(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
           backend: BackendOpt = Backend.auto, quiet: QuietOpt = False) -> None:
    """Table 1: per-phase ms of the four examples beside the paper's (OUT/data/table1.csv)."""
    from bench.studies.table1 import run_table1
    with _context(out, runs_root, scale, backend, None, None, quiet) as ctx:
        with _refusals():
            frame = run_table1(ctx)
    shown = ["example", "mode", "max_particles", "pbf_ms", "smoothing_ms", "cloud_dynamics_ms", "splitting_ms",
             "merging_ms", "total_ms", "paper_max_particles", "paper_total_ms", "speedup_vs_paper", "stable"]
    typer.echo(frame[shown].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    typer.echo(f"device: {frame['device'].iloc[0]}; scale: {ctx.scale.environment_label}; "
               f"paper: GeForce GTX 780 Ti")
    typer.echo(f"wrote {ctx.data / 'table1.csv'}")


@app.command()
def compare(
    scene: Annotated[str, typer.Argument(help="a cloud scene (its NAME_adaptive twin is used when it ships)")] = "growing",
    seeds: Annotated[Optional[int], typer.Option(min=5, max=1000, help="noise seeds per mode (>= 5)")] = None,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Particles (non-adaptive and adaptive) against the grid baseline over >= 5 seeds."""
    from bench.studies.compare import run_compare
    _load_scene(scene)
    with _context(out, runs_root, scale, backend, workers, scheduler, quiet) as ctx:
        try:
            with _refusals():
                frames = run_compare(ctx, scene, seeds)
        except ValueError as exc:
            raise click.UsageError(str(exc)) from None
    typer.echo(frames["compare_runs"][["solver", "mode", "seed", "stable", "step", "step_wall_s"]].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'compare_timeseries.csv'}, compare_profiles.csv, compare_runs.csv")


@app.command()
def cycling(
    seeds: Annotated[int, typer.Option(min=3, max=1000, help="noise seeds per mode (>= 3)")] = 3,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Paper example 2: count the clouds' disappear/reappear cycles in both solvers (docs/cycling.md)."""
    from bench.studies.cycling import COLUMNS, run_cycling
    with _context(out, runs_root, scale, backend, workers, scheduler, quiet) as ctx:
        with _refusals():
            frames = run_cycling(ctx, seeds)
    typer.echo(frames["cycling_cycles"][list(COLUMNS)].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'cycling_cycles.csv'}, cycling_timeseries.csv")


@app.command()
def sweep(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
          backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
          quiet: QuietOpt = False) -> None:
    """Run time against error (spacing, iterations, split threshold, grid cells) and the Pareto front."""
    import json
    from bench.studies.sweep import run_sweep
    with _context(out, runs_root, scale, backend, workers, scheduler, quiet) as ctx:
        with _refusals():
            frame = run_sweep(ctx)
    typer.echo(frame[["method", "parameter", "value", "wall_s", "error_self", "error_other", "pareto"]]
               .to_string(index=False))
    typer.echo(json.loads((ctx.data / "sweep_verdict.json").read_text())["verdict"])
    typer.echo(f"wrote {ctx.data / 'sweep.csv'}")


@app.command()
def stress(out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
           backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
           quiet: QuietOpt = False) -> None:
    """Stability map: dt, iterations, heating rate and alpha*dt; the largest stable dt."""
    import json
    from bench.studies.stress import run_stress
    with _context(out, runs_root, scale, backend, workers, scheduler, quiet) as ctx:
        with _refusals():
            frame = run_stress(ctx)
    typer.echo(frame[["parameter", "value", "stable", "step", "reason"]].to_string(index=False))
    summary = json.loads((ctx.data / "stress_summary.json").read_text())
    typer.echo(f"largest stable dt: {summary['largest_stable_dt']} s")
    typer.echo(f"wrote {ctx.data / 'stress.csv'}")


@app.command()
def scaling(
    sizes: Annotated[Optional[str], typer.Option(help="particle counts, comma-separated (default: the scale's)")] = None,
    grid_sizes: Annotated[Optional[str], typer.Option(help="n for n^3 grids, comma-separated (default: the scale's)")] = None,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, quiet: QuietOpt = False,
) -> None:
    """ms per step against particle count (pbf_scaling.csv) and grid cells (grid_scaling.csv)."""
    import dataclasses
    from bench.studies.scaling import GRID_COLUMNS, PBF_COLUMNS, run_scaling
    particle_sizes = _parse_sizes(sizes, "--sizes", 100)
    cell_sizes = _parse_sizes(grid_sizes, "--grid-sizes", 2)
    with _context(out, runs_root, scale, backend, None, None, quiet) as ctx:
        if particle_sizes or cell_sizes:
            ctx.scale = dataclasses.replace(ctx.scale, scaling_particles=tuple(particle_sizes or ctx.scale.scaling_particles),
                                            scaling_grid_cells=tuple(cell_sizes or ctx.scale.scaling_grid_cells))
        with _refusals():
            frames = run_scaling(ctx)
    typer.echo(frames["pbf_scaling"][list(PBF_COLUMNS)].to_string(index=False))
    typer.echo(frames["grid_scaling"][list(GRID_COLUMNS)].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'pbf_scaling.csv'} and grid_scaling.csv")


@app.command()
def report(out: OutOpt = DEFAULT_OUT) -> None:
    """Build OUT/index.html from what OUT/data holds (missing studies are shown as not run)."""
    from bench.studies.demo import build_report
    if not (out / "data").is_dir():
        raise typer.BadParameter(f"{out / 'data'} does not exist; run a study (e.g. `cloudpbf demo`) first",
                                 param_hint="'--out'")
    typer.echo(f"report: {build_report(out)}")


@app.command()
def demo(
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False,
    only: Annotated[Optional[str], typer.Option(
        help="comma-separated subset of: table1, scaling, compare, sweep, stress, renders")] = None,
) -> None:
    """Everything: environment, Table 1, scaling, compare, sweep, stress, renders, then the report.

    Prints the path of index.html.  Exit code 1 when a study failed (the report shows which)."""
    from bench.studies.demo import STUDIES, run_demo
    chosen = tuple(s.strip() for s in only.split(",") if s.strip()) if only else STUDIES
    bad = [s for s in chosen if s not in STUDIES]
    if bad:
        raise typer.BadParameter(f"'{bad[0]}': allowed {', '.join(STUDIES)}", param_hint="'--only'")
    with _context(out, runs_root, scale, backend, workers, scheduler, quiet) as ctx:
        with _refusals():
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
    netcdf = "netcdf"
    zarr = "zarr"


@app.command()
def export(
    run_dir: Annotated[Path, typer.Argument(metavar="RUN", help="a run directory (printed by `cloudpbf run`)")],
    format: Annotated[ExportFormat, typer.Option("--format", "-f", help="vtu/vtp: a ParaView time series (.pvd "
                                                 "+ one file per snapshot); netcdf/zarr: an xarray Dataset "
                                                 "(time, x, y, z) with CF attributes")] = ExportFormat.vtp,
    out: Annotated[Optional[Path], typer.Option("--out", help="where to write (default: RUN/export/...)")] = None,
    resolution: Annotated[Optional[str], typer.Option(
        help="netcdf/zarr of a particle run: deposition grid nx,ny,nz (default: one cell per particle spacing, "
             "the grid baseline's grid)")] = None,
) -> None:
    """Export a run's stored snapshots for ParaView (vtu, vtp) or xarray (netcdf, zarr).

    Particle runs: every particle with every field (units in the field data) as .vtu/.vtp, or deposited
    on the grid baseline's grid as NetCDF/zarr, so a particle run and a grid run of one scene compare cell
    by cell.  Grid runs: the cell-centred fields.  (.bgeo: no maintained writer exists on PyPI.)"""
    from bench.export import export_run
    cells = _parse_list(resolution, "--resolution", int, 1, 4096, "64,64,64")
    if cells is not None and len(cells) != 3:
        raise typer.BadParameter(f"'{resolution}': expected three cell counts nx,ny,nz", param_hint="'--resolution'")
    try:
        path = export_run(run_dir, format.value, out, resolution=tuple(cells) if cells else None)
    except FileNotFoundError as exc:
        raise typer.BadParameter(str(exc), param_hint="'RUN'") from None
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    typer.echo(f"wrote {path}")


@app.command("adaptive-cost")
def adaptive_cost_cmd(
    spacing: Annotated[float, typer.Option(min=5.0, max=1000.0, help="level-0 lattice spacing, m")] = 45.0,
    steps: Annotated[int, typer.Option(min=3, max=100_000, help="steps per run")] = 500,
    scenes: Annotated[str, typer.Option(help="adaptive scenes, comma-separated")] = "growing_adaptive,cycling_adaptive",
    backend: BackendOpt = Backend.auto,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/gpu/data/adaptive_cost.csv"),
    runs_root: RunsRootOpt = None, quiet: QuietOpt = False,
) -> None:
    """Split and merge ms per step of the adaptive scenes on a given level-0 spacing (GPU benchmark)."""
    from bench import runs
    from bench.studies import adaptive_cost as ac
    names = _parse_list(scenes, "--scenes", str, example="growing_adaptive,cycling_adaptive")
    for name in names:
        _load_scene(name)
    if steps <= ac.WARMUP_STEPS:
        raise typer.BadParameter(f"{steps}: must be > {ac.WARMUP_STEPS} (the warm-up steps)", param_hint="'--steps'")
    frame = ac.adaptive_cost(names, spacing, steps, backend.value, runs_root, quiet)
    runs.write_csv(frame, out)
    typer.echo(frame[list(ac.COLUMNS)].to_string(index=False))
    typer.echo(f"targets: splitting <= {ac.SPLIT_TARGET_MS} ms, merging <= {ac.MERGE_TARGET_MS} ms per step; "
               f"wrote {out}")


@app.command("constant-gravity")
def constant_gravity_cmd(
    gravity: Annotated[str, typer.Option(help="constant gravities g_c to add, m/s^2, comma-separated")] = "0.1,0.3,1.0",
    particles: Annotated[Optional[int], typer.Option(min=100, max=10**9, help="resample the scenes to about this many")] = None,
    steps: Annotated[Optional[int], typer.Option(min=1, max=10**7, help="steps (default: the scenes' 500)")] = None,
    backend: BackendOpt = Backend.auto,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/gpu/data/constant_gravity.csv"),
    runs_root: RunsRootOpt = None, quiet: QuietOpt = False,
) -> None:
    """`growing` with a constant gravity added, beside the shipped `cycling` (README: Deviations)."""
    import pandas as pd
    from bench import runs
    from bench.studies import constant_gravity as cg
    values = _parse_list(gravity, "--gravity", float, 1e-9, 100.0, "0.1,0.3,1.0")
    frame = cg.constant_gravity(values, particles, steps, backend=backend.value, runs_root=runs_root, quiet=quiet)
    runs.write_csv(frame, out)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        typer.echo(frame[[c for c in cg.COLUMNS if c in frame.columns]].to_string(index=False))
    typer.echo(f"wrote {out}")


@app.command("pbf-scaling")
def pbf_scaling_cmd(
    sizes: Annotated[str, typer.Option(help="particle counts, comma-separated")] = "250000,1000000,4000000",
    steps: Annotated[int, typer.Option(min=1, max=10_000, help="timed steps per size (after 2 warm-up steps)")] = 20,
    iterations: Annotated[int, typer.Option(min=1, max=200, help="PBF solver iterations")] = 4,
    scene: Annotated[str, typer.Option(help="scene name or path")] = "growing",
    backend: BackendOpt = Backend.auto,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/gpu/pbf_scaling.csv"),
    runs_root: RunsRootOpt = None, quiet: QuietOpt = False,
) -> None:
    """ms per particle step at the given sizes, one CSV (the GPU benchmark form of `scaling`)."""
    from bench import runs
    from bench.studies import scaling as sc
    counts = _parse_sizes(sizes, "--sizes", 100)
    _load_scene(scene)
    frame = sc.pbf_scaling(counts, backend.value, runs_root, scene, iterations, steps, quiet)
    runs.write_csv(frame, out)
    typer.echo(frame[list(sc.PBF_COLUMNS)].to_string(index=False))
    typer.echo(f"wrote {out}")


@app.command("grid-scaling")
def grid_scaling_cmd(
    sizes: Annotated[str, typer.Option(help="cells per axis of n^3 grids, comma-separated")] = "32,64,128",
    steps: Annotated[int, typer.Option(min=1, max=100_000, help="timed steps per size")] = 20,
    warmup: Annotated[int, typer.Option(min=0, max=1000, help="untimed steps after compilation")] = 2,
    scene: Annotated[str, typer.Option(help="scene name or path")] = "growing",
    devices: Annotated[str, typer.Option(help="all, cpu, gpu or cpu,gpu")] = "all",
    dtypes: Annotated[Optional[str], typer.Option(
        help="float32 and/or float64, comma-separated (default: float64 on the CPU, float32 on the GPU)")] = None,
    out: Annotated[Path, typer.Option("--out", help="CSV to append to")] = Path("reports/gpu/grid_scaling.csv"),
    commit: Annotated[Optional[str], typer.Option(help="commit to record (default: git rev-parse --short HEAD)")] = None,
) -> None:
    """ms per grid-baseline step at n^3 cells on the CPU and the GPU (appends to one CSV)."""
    from bench import grid_scaling as gs
    cells = _parse_sizes(sizes, "--sizes", 2)
    kinds = _parse_list(dtypes, "--dtypes", str, example="float32,float64")
    bad = [d for d in kinds or [] if d not in ("float32", "float64")]
    if bad:
        raise typer.BadParameter(f"'{bad[0]}': allowed float32, float64", param_hint="'--dtypes'")
    _load_scene(scene)
    try:
        gs.run_grid_scaling(cells, steps=steps, warmup=warmup, scene=scene, devices=devices, dtypes=kinds,
                            out=out, commit=commit, echo=typer.echo)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None


def main(argv: list[str] | None = None) -> int:
    """Console entry point (`cloudpbf`)."""
    try:
        app(args=argv, prog_name="cloudpbf")
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
