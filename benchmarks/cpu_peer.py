"""CPU against SPlisHSPlasH: its DamBreakModel with PBF and cloudpbf's dam break on the same geometry, one run.

    python benchmarks/cpu_peer.py --threads 2 --repeats 2 --out reports/gpu/data/cpu_peer.csv

SPlisHSPlasH (``pip install pysplishsplash==2.19.0``, run by the Python it is installed in: ``--splish-python``):
PBF (simulationMethod 2) with 4 fixed iterations, dt 0.002 s, particle radius 0.011 m, a 1 m water cube in a
4 x 3 x 1.5 m box of Akinci boundary particles (the wheel's UnitBox.obj scaled), 0.1 s = 50 steps; its
``runSimulation`` is timed (set-up excluded).  It links libGL: on a headless machine libGLdispatch.so.0 is
preloaded.  cloudpbf: the ``dam_break`` scene with the same box, cube, spacing 0.022 m, dt and iterations, on
the CPU backend, 2 warm-up steps then 20 timed.  The two alternate ``--repeats`` times at each thread count
(OMP_NUM_THREADS); each row of the CSV is one timing: threads, tool, fluid_particles, ms_per_step,
particle_steps_per_s, device, commit.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

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
import json, time
from pbf_cuda import Simulation, load_scene
scene = load_scene("dam_break", **{"domain.size": [4.0, 3.0, 1.5], "particles.spacing": 0.022,
    "particles.fill_min": [0.0, 0.0, 0.0], "particles.fill_max": [1.0, 1.0, 1.0], "time.dt": 0.002,
    "pbf.iterations": 4})
sim = Simulation(scene, backend="cpu", seed=0)
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
    # found without importing the module, which needs libGL preloaded on a headless machine
    code = ("import importlib.util, pathlib, sys; assert importlib.util.find_spec('pysplishsplash'); "
            "print(next(pathlib.Path(sys.prefix).rglob('UnitBox.obj')))")
    return subprocess.run([python, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", default=str(os.cpu_count()), help="comma-separated thread counts")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--splish-python", default=sys.executable, help="a Python with pysplishsplash 2.19.0")
    ap.add_argument("--out", type=Path, default=Path("reports/gpu/data/cpu_peer.csv"))
    a = ap.parse_args(argv)
    try:
        box = _unit_box(a.splish_python)
    except subprocess.CalledProcessError:
        print(f"cpu_peer: pysplishsplash is not importable by {a.splish_python}; "
              "pip install pysplishsplash==2.19.0 there (it needs libGL)", file=sys.stderr)
        return 2
    import pandas as pd
    from bench.environment import commit, cpu_name
    work = Path(tempfile.mkdtemp(prefix="cpu-peer-"))
    scene = dict(SPLISH_SCENE, RigidBodies=[dict(SPLISH_SCENE["RigidBodies"][0], geometryFile=box)])
    (work / "scene.json").write_text(json.dumps(scene))
    (work / "splish.py").write_text(SPLISH_DRIVER)
    (work / "cloudpbf.py").write_text(CLOUDPBF_DRIVER)
    gl = next((p for p in ("/lib/x86_64-linux-gnu/libGLdispatch.so.0", "/usr/lib/x86_64-linux-gnu/libGLdispatch.so.0")
               if Path(p).exists()), None)
    rows = []
    for threads in [int(t) for t in a.threads.split(",")]:
        env = dict(os.environ, OMP_NUM_THREADS=str(threads))
        splish_env = dict(env, **({"LD_PRELOAD": gl} if gl else {}))
        for _ in range(a.repeats):
            for tool in ("SPlisHSPlasH 2.19.0", "cloudpbf"):
                if tool == "cloudpbf":
                    r = _result([sys.executable, str(work / "cloudpbf.py")], env)
                    steps = r["steps"]
                else:
                    r = _result([a.splish_python, str(work / "splish.py"), str(work / "scene.json"), str(work / "out")],
                                splish_env)
                    steps = STEPS
                ms = 1e3 * r["wall"] / steps
                rows.append({"threads": threads, "tool": tool, "fluid_particles": r["fluid"], "ms_per_step": ms,
                             "particle_steps_per_s": r["fluid"] / (ms / 1e3)})
                print(rows[-1], flush=True)
    frame = pd.DataFrame(rows)
    frame["device"] = f"{cpu_name()}, {os.cpu_count()} cores"
    frame["commit"] = commit()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(a.out, index=False)
    best = frame.groupby(["threads", "tool"])["particle_steps_per_s"].max().unstack()
    best["cloudpbf / SPlisHSPlasH"] = best["cloudpbf"] / best["SPlisHSPlasH 2.19.0"]
    print(best.to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
