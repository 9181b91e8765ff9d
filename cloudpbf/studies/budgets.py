"""Heat and water budgets of the particle solver and the grid baseline, side by side, for one scene.

Both solvers write the same budget columns with every stats() row (docs/validation.md, "Budgets of
both solvers"): the running totals of the mass-weighted mean warming from each process (K) and the
total water (kg).  This runs one scene in both (the grid at one cell per particle spacing, so both
sample the heating pattern at the same sites) and writes, every `every` steps:

    solver, time_s, step, mean_temperature, heat_source_total, heat_latent_total, heat_adiabatic_total,
    heat_smoothing_total, heat_numerical_total (grid only), total_water, mass_centre_height,
    kinetic_energy, device, commit

    cloudpbf budgets --scene growing --particles 8000 --steps 250 \\
        --out reports/gpu/data/budgets.csv --plot reports/gpu/budgets.png

(``python -m cloudpbf.studies.budgets ARGS`` is the same command.)  Not part of the demo.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer

from cloudpbf import runs
from cloudpbf.cli_common import Backend, BackendOpt, QuietOpt, check_backend, run_command, scene_arg
from cloudpbf.environment import commit as git_commit
from cloudpbf.studies.registry import Study, register
from cloudpbf.studies.scales import scale_scene
from pbf_cuda import Simulation
from pbf_cuda.scene import load_scene

COLUMNS = ("solver", "time_s", "step", "mean_temperature", "heat_source_total", "heat_latent_total",
           "heat_adiabatic_total", "heat_smoothing_total", "heat_numerical_total", "total_water",
           "mass_centre_height", "kinetic_energy", "device", "commit")
HEAT_TERMS = ("source", "latent", "adiabatic", "smoothing", "numerical")


def run_budgets(scene="growing", particles: int | None = 8000, steps: int | None = None, every: int = 10,
                seed: int = 0, backend: str = "cpu", quiet: bool = False):
    """Both solvers' budget rows (a DataFrame with COLUMNS)."""
    import pandas as pd  # harness extra (pandas)

    from grid_baseline import GridSimulation  # grid extra (jax)

    scene = load_scene(scene) if isinstance(scene, str) else scene
    scene = scale_scene(scene, particles)
    steps = scene.time.steps if steps is None else int(steps)
    part = Simulation(scene, backend=backend, seed=seed)
    grid = GridSimulation(scene, seed=seed, resolution=scene.lattice_shape())
    commit = git_commit()
    rows = []
    for name, sim in (("particles", part), ("grid", grid)):
        device = sim.backend if name == "particles" else sim.stats()["device"]
        done = 0
        first = len(rows)
        while True:
            st = sim.stats()
            rows.append({"solver": name, "time_s": sim.time, "step": sim.step_count,
                         **{c: st.get(c, np.nan) for c in COLUMNS[3:-2]}, "device": device, "commit": commit})
            if done >= steps:
                break
            n = min(every, steps - done)
            sim.step(n)
            done += n
        if not quiet:
            last = rows[-1]
            terms = ", ".join(f"{t} {last[f'heat_{t}_total']:.4g}" for t in HEAT_TERMS)
            change = last["mean_temperature"] - rows[first]["mean_temperature"]
            print(f"{name}: {scene.name} {steps} steps: mean T change {change:.4g} K; {terms}", file=sys.stderr)
    return pd.DataFrame(rows)[list(COLUMNS)]


def plot_budgets(frame, path):
    """Cumulative warming per process (K) against time, particles solid, grid dashed."""
    import matplotlib  # harness extra (matplotlib)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # harness extra (matplotlib)

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for solver, ls in (("particles", "-"), ("grid", "--")):
        f = frame[frame["solver"] == solver]
        if not len(f):
            continue
        change = f["mean_temperature"] - f["mean_temperature"].iloc[0]
        ax.plot(f["time_s"], change, color="k", ls=ls, label=f"{solver}: mean T change")
        for k, term in enumerate(HEAT_TERMS):
            col = f[f"heat_{term}_total"]
            if col.notna().any() and np.nanmax(np.abs(col)) > 0:
                ax.plot(f["time_s"], col, color=f"C{k}", ls=ls, label=f"{solver}: {term}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mass-weighted mean warming (K)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    from cloudpbf.report.plots import save_png  # harness extra (matplotlib, pandas)
    return save_png(fig, path)


def budgets_command(
    scene: Annotated[str, typer.Option(help="scene name")] = "growing",
    particles: Annotated[int, typer.Option(min=0, max=100_000_000,
                                           help="particle count (0: the scene file's spacing)")] = 8000,
    steps: Annotated[Optional[int], typer.Option(min=1, max=1_000_000,
                                                 help="steps (default: the scene's)")] = None,
    every: Annotated[int, typer.Option(min=1, max=1_000_000, help="a budget row every this many steps")] = 10,
    seed: Annotated[int, typer.Option(min=0, help="random seed")] = 0,
    backend: BackendOpt = Backend.cpu,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/latest/data/budgets.csv"),
    plot: Annotated[Optional[Path], typer.Option(help="also draw the budgets as a PNG here")] = None,
    quiet: QuietOpt = False,
) -> None:
    """Heat and water budgets of both solvers, side by side, for one scene (budgets.csv)."""
    scene_arg(scene, param="--scene")
    check_backend(backend)
    frame = run_budgets(scene, particles or None, steps, every, seed, backend.value, quiet)
    runs.write_csv(frame, out)
    typer.echo(f"wrote {out}")
    if plot is not None:
        typer.echo(f"wrote {plot_budgets(frame, plot)}")


register(Study("budgets", order=90, outputs=("budgets.csv",), command=budgets_command))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.budgets ARGS`` is ``cloudpbf budgets ARGS``."""
    return run_command(budgets_command, "budgets", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
