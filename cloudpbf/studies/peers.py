"""A peer benchmark: SPlisHSPlasH's PBF dam break and cloudpbf's on the same geometry, in one run.

    cloudpbf peers --threads 2,16 --repeats 2 --out reports/gpu/data/cpu_peer.csv

SPlisHSPlasH (the ``peers`` extra: ``pip install pysplishsplash==2.19.0``, or any Python that has it,
``--splish-python``): its DamBreakModel with PBF (simulationMethod 2), 4 fixed iterations, dt 0.002 s, particle
radius 0.011 m, a 1 m water cube in a 4 x 3 x 1.5 m box of Akinci boundary particles (the wheel's UnitBox.obj
scaled), 0.1 s = 50 steps; its ``runSimulation`` is timed (set-up excluded).  It links libGL: on a headless
machine libGLdispatch.so.0 is preloaded.  Where it is missing the command says so and times cloudpbf alone.

cloudpbf: the ``dam_break`` scene with the same box, cube and spacing (``--spacing``, 0.022 m), dt and
iterations, 2 warm-up steps then 20 timed, on the CPU at each thread count and on the GPU where one exists.  The
tools alternate ``--repeats`` times at each thread count (OMP_NUM_THREADS); each CSV row is one timing:
threads (0: the GPU), tool, fluid_particles, ms_per_step, particle_steps_per_s, device, commit, run (the UTC
minute the run started: the repeats of one run are compared with each other, never with another run's, because a
shared host's speed drifts between runs).  Not part of the demo.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Optional

import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf.environment import commit, cpu_name, gpu_names
from cloudpbf.report.common import Inputs, Section, _missing, _table
from cloudpbf.cli_common import parse_list, run_command
from cloudpbf.studies.registry import ReportSection, Study, register
from pbf_cuda import available_backends

SPLISH_SCENE = {
    "Configuration": {"particleRadius": 0.011, "simulationMethod": 2, "gravitation": [0, -9.81, 0],
                      "timeStepSize": 0.002, "cflMethod": 0, "stopAt": 0.1, "boundaryHandlingMethod": 0,
                      "enablePartioExport": False, "enableVTKExport": False, "dataExportFPS": 0,
                      "PBF": {"minIterations": 4, "maxIterations": 4, "maxError": 0.0001}},
    "Materials": [{"id": "Fluid", "density0": 1000, "viscosityMethod": 1, "Standard viscosity": {"viscosity": 0.01}}],
    "RigidBodies": [{"geometryFile": "", "translation": [0, 1.5, 0], "rotationAxis": [1, 0, 0], "rotationAngle": 0,
                     "scale": [4, 3, 1.5], "isDynamic": False, "isWall": True, "mapInvert": True,
                     "mapThickness": 0.0, "mapResolution": [40, 30, 15]}],
    "FluidBlocks": [{"denseMode": 0, "start": [-0.5, 0.0, -0.5], "end": [0.5, 1.0, 0.5],
                     "translation": [-1.45, 0.05, 0.0], "scale": [1, 1, 1]}],
}
STEPS = 50   # stopAt / timeStepSize
SPLISH = "SPlisHSPlasH 2.19.0"   # the peer's name in the CSV's tool column
RATIO = "cloudpbf / SPlisHSPlasH"

SPLISH_DRIVER = """
import json, sys, time
import pysplishsplash as sph
base = sph.Exec.SimulatorBase()
base.init(useGui=False, outputDir=sys.argv[2], sceneFile=sys.argv[1])
base.initSimulation()
n = sph.Simulation.getCurrent().getFluidModel(0).numActiveParticles()
t = time.perf_counter()
base.runSimulation()
wall = time.perf_counter() - t
base.cleanup()
print("RESULT", json.dumps({"fluid": int(n), "wall": wall}))
"""

CLOUDPBF_DRIVER = """
import json, sys, time
from pbf_cuda import Simulation, load_scene
scene = load_scene("dam_break", **{"domain.size": [4.0, 3.0, 1.5], "particles.spacing": float(sys.argv[1]),
    "particles.fill_min": [0.0, 0.0, 0.0], "particles.fill_max": [1.0, 1.0, 1.0], "time.dt": 0.002,
    "pbf.iterations": 4})
sim = Simulation(scene, backend=sys.argv[2], seed=0)
sim.step(2)
t = time.perf_counter()
sim.step(20)
print("RESULT", json.dumps({"fluid": int(sim.stats()["n_particles"]), "wall": time.perf_counter() - t, "steps": 20}))
"""


def _result(cmd, env):
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"{cmd[0]} gave no result: {out.stderr[-500:]}")


def _unit_box(python):
    # found without importing the module, which needs libGL preloaded on a headless machine; under the
    # environment's prefix, or beside the module where it was installed with pip --target
    code = ("import importlib.util, pathlib, sys; spec = importlib.util.find_spec('pysplishsplash'); assert spec; "
            "roots = [pathlib.Path(sys.prefix), pathlib.Path(spec.origin).parent]; "
            "print(next(p for r in roots for p in r.rglob('UnitBox.obj')))")
    return subprocess.run([python, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def splish_available(python: str) -> str | None:
    """SPlisHSPlasH's UnitBox.obj when `python` has pysplishsplash, else None."""
    try:
        return _unit_box(python)
    except (subprocess.CalledProcessError, OSError):
        return None


def run_peers(threads: list[int], repeats: int = 2, splish_python: str | None = None, spacing: float = 0.022,
              echo=print):
    """The timing rows (a DataFrame): SPlisHSPlasH where `splish_python` has it, cloudpbf on the CPU at each
    thread count and on the GPU where one exists."""
    python = splish_python or sys.executable
    box = splish_available(python)
    if box is None:
        echo(f"peers: SPlisHSPlasH skipped: pysplishsplash is not installed for {python} (the peers extra: "
             "pip install 'cloudpbf[peers]', or --splish-python with a Python that has it)")
    work = Path(tempfile.mkdtemp(prefix="cloudpbf-peers-"))
    scene = dict(SPLISH_SCENE, RigidBodies=[dict(SPLISH_SCENE["RigidBodies"][0], geometryFile=box or "")])
    (work / "scene.json").write_text(json.dumps(scene))
    (work / "splish.py").write_text(SPLISH_DRIVER)
    (work / "cloudpbf.py").write_text(CLOUDPBF_DRIVER)
    gl = next((p for p in ("/lib/x86_64-linux-gnu/libGLdispatch.so.0", "/usr/lib/x86_64-linux-gnu/libGLdispatch.so.0")
               if Path(p).exists()), None)
    cpu = f"{cpu_name()}, {os.cpu_count()} cores"
    started = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%MZ")   # the run's label: repeats of one run compare
    rows = []

    def timed(tool, n_threads, device, cmd, env, steps=None):
        r = _result(cmd, env)
        ms = 1e3 * r["wall"] / (steps or r["steps"])
        rows.append({"threads": n_threads, "tool": tool, "fluid_particles": r["fluid"], "ms_per_step": ms,
                     "particle_steps_per_s": r["fluid"] / (ms / 1e3), "device": device})
        echo(f"peers: {tool:22s} threads {n_threads:3d}  {r['fluid']:7d} particles  {ms:9.2f} ms per step")

    for n_threads in threads:
        env = dict(os.environ, OMP_NUM_THREADS=str(n_threads))
        for _ in range(repeats):
            if box is not None:
                timed(SPLISH, n_threads, cpu,
                      [python, str(work / "splish.py"), str(work / "scene.json"), str(work / "out")],
                      dict(env, **({"LD_PRELOAD": gl} if gl else {})), steps=STEPS)
            timed("cloudpbf", n_threads, cpu, [sys.executable, str(work / "cloudpbf.py"), str(spacing), "cpu"], env)
    if "cuda" in available_backends():
        for _ in range(repeats):
            timed("cloudpbf (cuda)", 0, ", ".join(gpu_names()),
                  [sys.executable, str(work / "cloudpbf.py"), str(spacing), "cuda"], dict(os.environ))
    frame = pd.DataFrame(rows)
    frame["commit"] = commit()
    frame["run"] = started
    return frame


def best_rates(frame):
    """Each tool's fastest repeat (fluid particle-steps per second) per run (its commit and start time, where the CSV
    has them: rows of several runs are never mixed), device and thread count, one column per tool, with cloudpbf's ratio to
    SPlisHSPlasH where both ran: of the fastest repeats, and of the means over the repeats (RATIO + " (means)"),
    which a single fast or slow repeat of either tool moves less."""
    frame = frame.copy()
    keys = ["threads", "device"]
    for label in ("run", "commit"):
        if label in frame:
            frame[label] = frame[label].fillna("").astype(str)
            keys = [label] + keys
    rates = frame.groupby(keys + ["tool"], as_index=False)["particle_steps_per_s"].agg(best="max", mean="mean")
    wide = rates.pivot_table(index=keys, columns="tool", values="best").reset_index()
    wide.columns.name = None
    if SPLISH in wide and "cloudpbf" in wide:
        wide[RATIO] = wide["cloudpbf"] / wide[SPLISH]
        means = rates.pivot_table(index=keys, columns="tool", values="mean").reset_index()
        wide[RATIO + " (means)"] = (means["cloudpbf"] / means[SPLISH]).to_numpy()
    return wide


def peers_command(
    threads: Annotated[str, typer.Option(help="CPU thread counts, comma-separated (default: 2 and all cores)")] = "",
    repeats: Annotated[int, typer.Option(min=1, max=20, help="alternating repeats per thread count")] = 2,
    splish_python: Annotated[Optional[str], typer.Option(help="a Python with pysplishsplash 2.19.0 "
                                                                 "(default: this one)")] = None,
    spacing: Annotated[float, typer.Option(min=0.01, max=0.2, help="cloudpbf's particle spacing, m")] = 0.022,
    out: Annotated[Path, typer.Option("--out", help="CSV to write")] = Path("reports/latest/data/cpu_peer.csv"),
) -> None:
    """SPlisHSPlasH's PBF dam break against cloudpbf's on the same geometry (cpu_peer.csv)."""
    counts = parse_list(threads, "--threads", int, 1, 1024, "2,16") if threads else sorted({2, os.cpu_count() or 2})
    if splish_python is not None and shutil.which(splish_python) is None and not Path(splish_python).is_file():
        raise typer.BadParameter(f"'{splish_python}': no such Python", param_hint="'--splish-python'")
    frame = run_peers(counts, repeats, splish_python, spacing, echo=typer.echo)
    runs.write_csv(frame, out)
    typer.echo(best_rates(frame).to_string(index=False))
    typer.echo(f"wrote {out}")


# ---- report: against SPlisHSPlasH ----------------------------------------------------------------
def _peers(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, path = inp.csv("cpu_peer")
    if df is None:
        _missing(sec, "cpu_peer.csv (SPlisHSPlasH's PBF dam break against cloudpbf's: cloudpbf peers)", "peers", inp)
        return
    sec.add("text", "SPlisHSPlasH's DamBreakModel with PBF (4 iterations, dt 0.002 s) and cloudpbf's dam break on the "
                    "same box, water cube and spacing, timed alternately in one run; per run the faster repeat of each "
                    "and cloudpbf's ratio to SPlisHSPlasH of the faster repeats and of the means. A shared host's "
                    "speed drifts between runs: compare within a row. Fluid particle-steps per second: more is "
                    "faster.")
    wide = best_rates(df)
    wide["threads"] = wide["threads"].map(lambda t: "GPU" if int(t) == 0 else str(int(t)))
    commits = ", ".join(sorted(df["commit"].astype(str).unique()))
    sec.add("table", _table(wide, float_format="{:.3g}"), caption=f"from {path.name}, commit {commits}")


register(Study("peers", order=96, outputs=("cpu_peer.csv",), command=peers_command,
               report=(ReportSection("peers", "Against SPlisHSPlasH (CPU)", _peers, 36, "SPlisHSPlasH"),),
               produces={"peers": "cloudpbf peers --out {out}/data/cpu_peer.csv"}))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.peers ARGS`` is ``cloudpbf peers ARGS``."""
    return run_command(peers_command, "peers", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
