"""What a constant gravity on the whole domain does to the cloud scenes (paper example 2).

The paper's second example adds a constant gravity to every particle and reports clouds that vanish
and come back.  In an incompressible, closed atmosphere a uniform gravity is balanced by a hydrostatic
pressure and changes nothing (the grid baseline's exact projection removes it completely); in PBF it
can only act through the solver's finite stiffness.  This study measures that: the `growing` scene
(eq. 6's cloud weight k_g = g, no constant gravity) with a constant gravity g_c of each given size
added, beside the shipped `cycling` scene (no constant gravity; time-of-day heating with large-scale
relaxation and rain, docs/cycling.md, run for its own 2100 steps).  For each run it records
whether it stayed stable, the mean density error and largest speed of the last step, and the cloud
cover (fraction of columns with cloud, cloudpbf.statistics) over time: when it first appears, its
largest value, and whether it fell back to zero afterwards and came back (``vanished_and_returned``).

    cloudpbf constant-gravity --gravity 0.1,0.3,1.0 --out reports/gpu/data/constant_gravity.csv

Runs go through the run cache.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf import environment
from cloudpbf.cli_common import Backend, BackendOpt, QuietOpt, RunsRootOpt, parse_list, run_command
from cloudpbf.studies.registry import Study, register
from pbf_cuda.scene import load_scene

COLUMNS = ("case", "constant_gravity", "cloud_gravity", "particles", "stable", "reason", "first_cloud_s",
           "max_cover", "final_cover", "vanished_and_returned", "density_error_mean", "max_speed", "device", "commit")


def _cases(gravities):
    yield "cycling (shipped, diurnal forcing)", load_scene("cycling"), 0.0
    base = load_scene("growing")
    for g in gravities:
        yield f"growing + g_c = {g:g}", base.replace(**{"pbf.gravity": [0.0, -float(g), 0.0]}), float(g)


def cover_summary(series: pd.DataFrame) -> dict:
    """first_cloud_s, max_cover, final_cover, vanished_and_returned from a cloud_cover time series."""
    cover = series["cloud_cover"].to_numpy()
    times = series["time_s"].to_numpy()
    cloudy = cover > 0
    if not cloudy.any():
        return {"first_cloud_s": None, "max_cover": 0.0, "final_cover": float(cover[-1]) if len(cover) else 0.0,
                "vanished_and_returned": False}
    first = int(cloudy.argmax())
    after = cloudy[first:]
    gone = (~after).nonzero()[0]
    returned = bool(len(gone) and after[gone[0]:].any())
    return {"first_cloud_s": float(times[first]), "max_cover": float(cover.max()), "final_cover": float(cover[-1]),
            "vanished_and_returned": returned}


def constant_gravity(gravities=(0.1, 0.3, 1.0), particles: int | None = None, steps: int | None = None,
                     snapshot_every: int = 10, backend: str = "auto", runs_root=None, quiet: bool = False):
    rows = []
    for case, scene, g in _cases(gravities):
        if particles:
            scene = scene.with_particle_count(int(particles))
        spec = runs.RunSpec("particles", scene, backend=backend, steps=steps, snapshot_every=snapshot_every,
                            keep_snapshots=1, diagnostics=True)
        res = runs.execute(spec, runs_root, quiet=quiet)
        stats = res.stats()
        row = {"case": case, "constant_gravity": g, "cloud_gravity": scene.atmosphere.cloud_gravity,
               "particles": res.max_particles, "stable": res.stable, "reason": res.reason}
        row.update(cover_summary(stats) if len(stats) else {})
        last = stats.iloc[-1] if len(stats) else {}
        for key in ("density_error_mean", "max_speed"):
            row[key] = float(last[key]) if key in last else None
        row.update(device=res.device, commit=environment.commit(), steps=spec.total_steps, run_dir=str(res.path))
        rows.append(row)
    return pd.DataFrame(rows)


def constant_gravity_command(
    gravity: Annotated[str, typer.Option(help="constant gravities g_c to add, m/s^2, comma-separated")] = "0.1,0.3,1.0",
    particles: Annotated[Optional[int], typer.Option(min=100, max=10**9, help="resample the scenes to about this many")] = None,
    steps: Annotated[Optional[int], typer.Option(min=1, max=10**7, help="steps (default: the scenes' 500)")] = None,
    backend: BackendOpt = Backend.auto,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/latest/data/constant_gravity.csv"),
    runs_root: RunsRootOpt = None, quiet: QuietOpt = False,
) -> None:
    """`growing` with a constant gravity added, beside the shipped `cycling` (docs/physics.md, Deviations from the paper)."""
    values = parse_list(gravity, "--gravity", float, 1e-9, 100.0, "0.1,0.3,1.0")
    frame = constant_gravity(values, particles, steps, backend=backend.value, runs_root=runs_root, quiet=quiet)
    runs.write_csv(frame, out)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        typer.echo(frame[[c for c in COLUMNS if c in frame.columns]].to_string(index=False))
    typer.echo(f"wrote {out}")


register(Study("constant-gravity", order=80, outputs=("constant_gravity.csv",), sections=("stress",),
               produces={"constant_gravity": "cloudpbf constant-gravity --out {out}/data/constant_gravity.csv"},
               command=constant_gravity_command))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.constant_gravity ARGS`` is ``cloudpbf constant-gravity ARGS``."""
    return run_command(constant_gravity_command, "constant-gravity", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
