"""What every command of `cloudpbf` shares: the click typer runs on, the common options, the helpers that
turn bad arguments into one line and exit code 2, and the StudyContext a study command opens.

It sits on the studies' floor (beside cloudpbf.studies.context and scales, below every study): the study modules
build their commands from it, and so does the face (cloudpbf.cli, which finds the studies' commands through
cloudpbf.studies.registry).  It never imports a study or the face."""
from __future__ import annotations

import contextlib
import functools
import importlib
import os
import tomllib
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
import typer.rich_utils

from cloudpbf import environment, runs
from cloudpbf.store.safe import StoreError
from cloudpbf.studies.context import GpuError, SchedulerError, StudyContext, check_scheduler_address
from cloudpbf.studies.scales import resolve_scale
from pbf_cuda.buildinfo import StaleBuildError
from pbf_cuda.scene import SceneError, list_scenes, load_scene
from pbf_cuda.simulation import _core, available_backends

# The click that typer runs on: the click package up to typer 0.24, typer's own vendored copy from 0.25
# on.  Exceptions must come from that one, or typer does not turn them into "Usage: ... Error: ..." and
# exit code 2.
# `click.UsageError`, `click.BadParameter`, `click.ClickException`, ... below are that click's exceptions.
click = importlib.import_module(typer.BadParameter.__module__)

# typer 0.19 escapes the "[default: ...]" / "[required]" of option help for rich's HTML export even when
# rich_markup_mode is None, so plain help would print "\\[default: ...]".  Plain help has no markup
# to escape: show it as written.
typer.rich_utils.escape_before_html_export = lambda text: text.strip()

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
    "--scale", help="smoke (a small box, minutes on a CPU), cpu (~50k particles, hours on 2 cores), gpu (the "
                    "paper's counts); auto: gpu if CUDA, else smoke")]
BackendOpt = Annotated[Backend, typer.Option("--backend", help="particle solver backend")]
WorkersOpt = Annotated[Optional[int], typer.Option(
    "--workers", min=1, max=4096, help="dask workers of the local cluster (default: CPU cores; 1 per GPU on GPU)")]
SchedulerOpt = Annotated[Optional[str], typer.Option(
    "--scheduler", help="address of an existing dask scheduler (e.g. tcp://host:8786) instead of a local "
                        "cluster; 'inline': no dask, the runs one by one in this process")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars or progress messages")]
GpusOpt = Annotated[Optional[str], typer.Option(
    "--gpus", help="'all' or a count: one dask-cuda worker per GPU (LocalCUDACluster), each pinned to its GPU "
                   "through CUDA_VISIBLE_DEVICES; needs the multigpu extra (dask-cuda)")]



# ---- helpers ------------------------------------------------------------------------------------
def scene_arg(name: str, overrides: dict | None = None, param: str = "SCENE"):
    """A scene by name or path; unknown names list the shipped scenes (exit code 2, naming `param`: the
    argument or option that gave the name)."""
    path = Path(name)
    try:
        is_file = path.suffix == ".toml" and path.exists()
    except (OSError, ValueError):                 # a name too long for the filesystem, a NUL byte
        is_file = False
    if name not in list_scenes() and not is_file:
        if len(name) > 80:
            name = name[:77] + "..."
        raise typer.BadParameter(f"unknown scene '{name}'; shipped scenes: {', '.join(list_scenes())} "
                                 f"(or a path to a .toml file)", param_hint=f"'{param}'")
    try:
        return load_scene(name, **(overrides or {}))
    except SceneError as exc:
        raise click.UsageError(str(exc)) from None


def parse_overrides(items: list[str] | None) -> dict:
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


def parse_sizes(text: str | None, name: str, lo: int) -> list[int] | None:
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


def check_folder(path: Optional[Path], option: str) -> None:
    """A folder option: an existing folder or a path whose first existing ancestor is a writable folder.
    Without --runs-root, $CLOUDPBF_RUNS is checked in its place."""
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
    # A run cache is looked in before anything is written (a read-only cache serves the runs it holds);
    # a write it cannot do ends in one line then (cloudpbf.store.safe.StoreError).
    if option not in ("--runs-root", "$CLOUDPBF_RUNS") and not os.access(probe, os.W_OK | os.X_OK):
        raise typer.BadParameter(f"'{shown}': {probe} is not writable", param_hint=f"'{option}'")


def check_backend(backend: Backend, solver: str = "particles") -> None:
    """--backend cuda where no CUDA device (or no CUDA build) exists: exit 2 naming the option."""
    if backend is not Backend.cuda:
        return
    if solver == "grid":
        try:
            import jax  # grid extra (jax)
            ok = bool(jax.devices("gpu"))
        except Exception:  # noqa: BLE001  (jax raises RuntimeError when no GPU backend exists)
            ok = False
        why = "jax sees no GPU"
    else:
        ok = "cuda" in available_backends()
        why = "pbf_cuda was built without CUDA" if not _core().cuda_built() else "no CUDA device is visible"
    if not ok:
        raise typer.BadParameter(f"'cuda' is not available here ({why}); use auto or cpu", param_hint="'--backend'")


@contextlib.contextmanager
def refusals(particles: Optional[int] = None):
    """What a command cannot do as asked ends in one line and exit code 2: scene and memory checks,
    an unusable scheduler, a stale compiled solver, a run cache that cannot be written."""
    try:
        yield
    except StoreError as exc:
        raise click.UsageError(" ".join(str(exc).split())) from None
    except SceneError as exc:
        prefix = f"--particles {particles}: " if particles is not None else ""
        raise click.UsageError(prefix + " ".join(str(exc).split())) from None
    except SchedulerError as exc:
        raise typer.BadParameter(str(exc), param_hint="'--scheduler'") from None
    except GpuError as exc:
        raise typer.BadParameter(str(exc), param_hint="'--gpus'") from None
    except StaleBuildError as exc:
        raise click.UsageError(str(exc)) from None


def refusing(command):
    """`command` with what it cannot do as asked (a scene too large, a cache it cannot write, ...) turned into
    one line and exit code 2 (refusals), whatever path inside it raised it."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        with refusals():
            return command(*args, **kwargs)
    return wrapper


def study_context(out: Path, runs_root: Optional[Path], scale: ScaleName, backend: Backend, workers: Optional[int],
                  scheduler: Optional[str], quiet: bool, gpus: Optional[str] = None, cuda_cluster_factory=None):
    check_folder(out, "--out")
    check_folder(runs_root, "--runs-root")
    with refusals():
        check_backend(backend)
    if scheduler is not None:
        try:
            check_scheduler_address(scheduler)
        except SchedulerError as exc:
            raise typer.BadParameter(str(exc), param_hint="'--scheduler'") from None
    with refusals():
        ctx = StudyContext(out=out, scale=resolve_scale(scale.value), runs_root=runs_root or runs.default_root(),
                           backend=backend.value, workers=workers, scheduler=scheduler, quiet=quiet, gpus=gpus,
                           cuda_cluster_factory=cuda_cluster_factory)
        ctx.check_gpus()                  # no GPU, too few, no dask-cuda: one line, before any run
        if scheduler is not None and scheduler != "inline":
            ctx.client()                  # fail now, in one line, when no scheduler answers
    environment.write_environment(ctx.out, ctx.scale.environment_label, ctx.particle_backend())   # every study says where it ran
    return ctx


def parse_list(text: str | None, name: str, kind=int, lo=None, hi=None, example: str = "1,2,3") -> list | None:
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


def run_command(function, name: str, argv: list[str] | None = None) -> int:
    """Run one command function as its own program (``python -m cloudpbf.studies.MODULE ARGS`` is
    ``cloudpbf NAME ARGS``); returns the exit code."""
    single = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None)
    single.command(name)(refusing(function))
    try:
        single(args=argv, prog_name=f"cloudpbf {name}")
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 1
    return 0
