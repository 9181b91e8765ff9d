"""Grid baseline scaling: ms per step at n^3 cells, on the CPU and on the GPU, through jax.

    cloudpbf grid-scaling --sizes 32,64,128 --steps 20 --out reports/gpu/data/grid_scaling.csv

Each (size, device, dtype) runs the scene (default ``growing``, its physics and dt) on an n x n x n grid
from its initial state: compile (not timed), ``--warmup`` steps, then ``--steps`` timed steps of the fused,
jitted step (one ``block_until_ready`` at the end).  Rows ``cells,step_ms,dtype,device,commit`` are
appended to --out (the header is written when the file is new or empty): cells = n^3, device =
the jax device's ``device_kind`` (e.g. ``cpu``, ``NVIDIA H100 80GB HBM3``), commit = ``git rev-parse
--short HEAD`` (``unknown`` where git or the repository is missing; ``--commit`` overrides).
"""
from __future__ import annotations

import csv
import subprocess
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from cloudpbf.cli_common import click, parse_list, parse_sizes, run_command, scene_arg
from pbf_cuda.scene import load_scene

COLUMNS = ("cells", "step_ms", "dtype", "device", "commit")
ROOT = Path(__file__).resolve().parent.parent


def git_commit(cwd: str | Path = ROOT) -> str:
    """Short commit hash of the checkout, or 'unknown' (no git binary, not a repository, any error)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=str(cwd), capture_output=True,
                             text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    sha = out.stdout.strip()
    return sha if out.returncode == 0 and sha else "unknown"


def _platforms(requested):
    import jax  # grid extra (jax)
    have = []
    for plat in ("cpu", "gpu"):
        try:
            if jax.devices(plat):
                have.append(plat)
        except RuntimeError:
            pass
    if requested in (None, "all"):
        return have
    wanted = [r.strip() for r in requested.split(",")]
    missing = [w for w in wanted if w not in have]
    if missing:
        raise ValueError(f"grid-scaling: no jax device for {', '.join(missing)} (available: {', '.join(have)})")
    return wanted


def measure(scene, n: int, platform: str, dtype: str, steps: int, warmup: int) -> dict:
    import jax  # grid extra (jax)
    from grid_baseline import GridSimulation  # grid extra (jax)
    sim = GridSimulation(scene, resolution=(n, n, n), dtype=dtype, device=platform, check_every=0)
    sim.warmup()
    if warmup:
        sim.step(warmup)
    sim.reset_timings()
    t0 = time.perf_counter()
    sim.step(steps)
    wall = (time.perf_counter() - t0) * 1e3 / steps
    sim.check()
    st = sim.stats()
    ms = sim.timings()["step"]["mean_ms"]
    return {"cells": n ** 3, "step_ms": f"{ms:.4f}", "dtype": dtype, "device": sim.device.device_kind, "wall_ms": wall,
            "compile_s": sim.compile_seconds, "substeps": st["substeps"], "max_speed": st["max_speed"],
            "platform": platform, "jax": jax.__version__}


def check_header(path: Path) -> None:
    """Refuse to append to a CSV with other columns."""
    if path.exists() and path.stat().st_size > 0:
        with open(path, newline="") as fh:
            header = next(csv.reader(fh), None)
        if header is not None and tuple(header) != COLUMNS:
            raise ValueError(f"grid-scaling: {path} has columns {header}, expected {','.join(COLUMNS)}")


def append_rows(path: Path, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    check_header(path)
    new = not path.exists() or path.stat().st_size == 0
    with open(path, "a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS), extrasaction="ignore", lineterminator="\n")
        if new:
            w.writeheader()
        for r in rows:
            w.writerow(r)


def run_grid_scaling(sizes, steps: int = 20, warmup: int = 2, scene="growing", devices: str = "all", dtypes=None,
                     out="reports/latest/data/grid_scaling.csv", commit: str | None = None, echo=print) -> list[dict]:
    """Measure every (device, dtype, size) and append each row to `out` as it finishes."""
    if steps < 1:
        raise ValueError("--steps must be >= 1")
    scene = load_scene(scene) if isinstance(scene, (str, Path)) else scene
    commit = commit or git_commit()
    out = Path(out)
    check_header(out)
    rows = []
    for platform in _platforms(devices):
        for dtype in dtypes or (["float64"] if platform == "cpu" else ["float32"]):
            for n in sizes:
                r = measure(scene, n, platform, dtype, steps, warmup)
                r["commit"] = commit
                rows.append(r)
                append_rows(out, [r])
                echo(f"{platform:4s} {dtype:8s} {n:4d}^3 = {r['cells']:9d} cells: {float(r['step_ms']):10.3f} ms/step "
                     f"(compile {r['compile_s']:.1f} s, substeps {r['substeps']}, {r['device']})")
    echo(f"wrote {len(rows)} rows to {out}")
    return rows


def grid_scaling_command(
    sizes: Annotated[str, typer.Option(help="cells per axis of n^3 grids, comma-separated")] = "32,64,128",
    steps: Annotated[int, typer.Option(min=1, max=100_000, help="timed steps per size")] = 20,
    warmup: Annotated[int, typer.Option(min=0, max=1000, help="untimed steps after compilation")] = 2,
    scene: Annotated[str, typer.Option(help="scene name or path")] = "growing",
    devices: Annotated[str, typer.Option(help="all, cpu, gpu or cpu,gpu")] = "all",
    dtypes: Annotated[Optional[str], typer.Option(
        help="float32 and/or float64, comma-separated (default: float64 on the CPU, float32 on the GPU)")] = None,
    out: Annotated[Path, typer.Option("--out", help="CSV to append to")] = Path("reports/latest/data/grid_scaling.csv"),
    commit: Annotated[Optional[str], typer.Option(help="commit to record (default: git rev-parse --short HEAD)")] = None,
) -> None:
    """ms per grid-baseline step at n^3 cells on the CPU and the GPU (appends to one CSV)."""
    cells = parse_sizes(sizes, "--sizes", 2)
    kinds = parse_list(dtypes, "--dtypes", str, example="float32,float64")
    bad = [d for d in kinds or [] if d not in ("float32", "float64")]
    if bad:
        raise typer.BadParameter(f"'{bad[0]}': allowed float32, float64", param_hint="'--dtypes'")
    scene_arg(scene, param="--scene")
    try:
        run_grid_scaling(cells, steps=steps, warmup=warmup, scene=scene, devices=devices, dtypes=kinds,
                         out=out, commit=commit, echo=typer.echo)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None


def main(argv=None) -> int:
    """``python -m cloudpbf.grid_scaling ARGS`` is ``cloudpbf grid-scaling ARGS``."""
    return run_command(grid_scaling_command, "grid-scaling", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
