"""``cloudpbf runs``: the runs of the cache (list, show one, prune), and what ``cloudpbf run`` prints at its end.

    cloudpbf runs                         every run: id, scene, solver, backend, seed, steps, status, age, size
    cloudpbf runs show ID                 one run (ID: a unique prefix of its folder name or key), verified
    cloudpbf runs prune                   unfinished and damaged runs and the quarantine, after a confirmation
    cloudpbf runs prune --older-than 30 --status stable,unstable --yes
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import typer

from cloudpbf.cli_common import RunsRootOpt
from cloudpbf.store.catalog import RunLookupError, find_run, folder_bytes, list_runs, prune_runs, run_entry
from cloudpbf.store.identity import default_root
from cloudpbf.store.manifest import quarantine_folders, verify_run

runs_app = typer.Typer(name="runs", add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None,
                       invoke_without_command=True,
                       help="The runs of the cache: list them, show one, prune them.")

STATUSES = ("stable", "unstable", "unfinished", "damaged")


def _root(runs_root: Optional[Path]) -> Path:
    return Path(runs_root) if runs_root is not None else default_root()


def human_bytes(n: float) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{int(n)} B"


def human_age(seconds: float) -> str:
    for unit, scale in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= scale:
            return f"{seconds / scale:.0f} {unit}"
    return f"{seconds:.0f} s"


def resolve_run(text: str, runs_root: Optional[Path], param: str = "'RUN'") -> Path:
    """A run folder from a path or a run-id prefix; exit 2 naming `param` when none or several fit."""
    try:
        return find_run(text, _root(runs_root))
    except RunLookupError as exc:
        raise typer.BadParameter(str(exc), param_hint=param) from None


@runs_app.callback()
def runs_list(ctx: typer.Context, runs_root: RunsRootOpt = None) -> None:
    """List the runs of the cache, newest first (and the quarantine folders)."""
    ctx.obj = {"runs_root": runs_root}
    if ctx.invoked_subcommand is not None:
        return
    root = _root(runs_root)
    entries = list_runs(root)
    if not entries:
        typer.echo(f"no runs in {root}")
    else:
        typer.echo(f"{len(entries)} run(s) in {root}, newest first:")
        typer.echo(f"  {'id':12s} {'scene':20s} {'solver':9s} {'backend':7s} {'seed':>10s} {'steps':>13s} "
                   f"{'status':10s} {'age':>6s} {'size':>9s}")
        for e in entries:
            steps = f"{e.step if e.step is not None else '?'}/{e.steps if e.steps is not None else '?'}"
            typer.echo(f"  {e.key[:12]:12s} {e.scene[:20]:20s} {e.solver:9s} {e.backend:7s} "
                       f"{'-' if e.seed is None else e.seed:>10} {steps:>13s} {e.status:10s} "
                       f"{human_age(e.age_s):>6s} {human_bytes(e.bytes):>9s}")
    kept = quarantine_folders(root)
    if kept:
        size = sum(folder_bytes(p) for p in kept)
        typer.echo(f"quarantine: {len(kept)} folder(s), {human_bytes(size)} in {root / 'quarantine'} "
                   "(damaged files kept for inspection; `cloudpbf runs prune` removes them)")


@runs_app.command("show")
def runs_show(
    ctx: typer.Context,
    run: Annotated[str, typer.Argument(metavar="ID", help="a run folder, or a unique prefix of its name or key")],
    runs_root: RunsRootOpt = None,
) -> None:
    """One run: what it is, its result, its files verified against the manifest."""
    runs_root = runs_root or (ctx.obj or {}).get("runs_root")
    path = resolve_run(run, runs_root, "'ID'")
    e = run_entry(path)
    typer.echo(f"run {path.name}\n  path     {path}\n  key      {e.key}")
    typer.echo(f"  scene    {e.scene}\n  solver   {e.solver}\n  backend  {e.backend}\n  seed     {e.seed}")
    typer.echo(f"  steps    {e.step if e.step is not None else '?'} of {e.steps}\n  status   {e.status}")
    typer.echo(f"  age      {human_age(e.age_s)}\n  size     {human_bytes(e.bytes)}")
    if e.result is not None:
        problems = verify_run(path, e.key or None)
        typer.echo("  verified " + ("yes: every file matches the manifest" if not problems
                                    else "NO: " + "; ".join(problems[:3])))
        if not e.result.get("stable"):
            typer.echo(f"  unstable at step {e.result.get('step')}: {e.result.get('reason')}")
        for line in physics_lines(path, e.result):
            typer.echo(f"  {line}")


@runs_app.command("prune")
def runs_prune(
    ctx: typer.Context,
    status: Annotated[str, typer.Option(help="comma-separated statuses of the runs to remove: "
                                             + ", ".join(STATUSES))] = "unfinished,damaged",
    older_than: Annotated[Optional[float], typer.Option(
        min=0.0, max=1e5, help="only runs last changed more than this many days ago")] = None,
    quarantine: Annotated[bool, typer.Option("--quarantine/--no-quarantine",
                                             help="remove the quarantine folders too")] = True,
    yes: Annotated[bool, typer.Option("--yes", "-y", help="remove without asking")] = False,
    runs_root: RunsRootOpt = None,
) -> None:
    """Remove runs by status (default: unfinished and damaged) and the quarantine, after a confirmation.

    Runs being written (locked) are never removed."""
    runs_root = runs_root or (ctx.obj or {}).get("runs_root")
    chosen = {s.strip() for s in status.split(",") if s.strip()}
    bad = sorted(chosen - set(STATUSES))
    if bad or not chosen:
        raise typer.BadParameter(f"'{bad[0] if bad else status}': allowed {', '.join(STATUSES)}",
                                 param_hint="'--status'")
    root = _root(runs_root)
    plan, skipped = prune_runs(root, chosen, None if older_than is None else older_than * 86400, quarantine)
    for line in skipped:
        typer.echo(f"  kept: {line}")
    if not plan:
        typer.echo(f"nothing to remove in {root}")
        return
    for path, size, why in plan:
        typer.echo(f"  {why:10s} {human_bytes(size):>9s}  {path}")
    total = human_bytes(sum(size for _, size, _ in plan))
    if not yes and not typer.confirm(f"remove these {len(plan)} folder(s), {total}?", default=False):
        typer.echo("nothing removed")
        raise typer.Exit(1)
    done, failed = prune_runs(root, chosen, None if older_than is None else older_than * 86400, quarantine,
                              dry_run=False)
    typer.echo(f"removed {len(done)} folder(s), {human_bytes(sum(size for _, size, _ in done))}")
    failed = [line for line in failed if "could not be removed" in line]
    if failed:
        for line in failed:
            typer.echo(f"  not removed: {line}", err=True)
        raise typer.Exit(2)


def physics_lines(path: Path, info: dict) -> list[str]:
    """The physics of a finished run in a line or two: particles (or cells), steps, simulated time, the
    largest speed, the density error and, where the run has cloud, the cloud cover."""
    import pandas as pd  # harness extra (pandas)
    tables = []
    for name, reader in (("stats.parquet", pd.read_parquet), ("steps.csv", pd.read_csv)):
        try:
            if (path / name).is_file():
                tables.append(reader(path / name))
        except (OSError, ValueError):
            continue
    def column(name, stepped=False):
        """A column over both tables; `stepped`: rows after step 0 only (the solver's step statistics, such
        as the density error, describe a step and are placeholders before the first)."""
        values = [(t[t["step"] > 0] if stepped and "step" in t else t)[name].dropna() for t in tables if name in t]
        values = [v for v in values if len(v)]
        return pd.concat(values) if values else None
    size = (f"{info['max_particles']:,} particles (max)" if info.get("max_particles")
            else f"{info['cells']:,} cells" if info.get("cells") else "size unknown")
    sim_time = info.get("time_s")
    parts = [size, f"{info.get('step')} steps",
             f"{sim_time:.4g} s simulated" if isinstance(sim_time, (int, float)) else "simulated time unknown"]
    speed = column("max_speed")
    if speed is not None:
        parts.append(f"largest speed {float(speed.max()):.3g} m/s")
    err = column("density_error_max", stepped=True)
    mean = column("density_error_mean", stepped=True)
    if err is not None and mean is not None:
        parts.append(f"density error {100 * float(mean.iloc[-1]):.3g} % (mean, last step), "
                     f"{100 * float(err.max()):.3g} % (largest)")
    cover = column("cloud_cover")
    if cover is not None and math.isfinite(float(cover.max())) and float(cover.max()) > 0:
        parts.append(f"cloud cover {float(cover.iloc[-1]):.2f} at the end ({float(cover.max()):.2f} at most)")
    return ["physics: " + "; ".join(parts)]

