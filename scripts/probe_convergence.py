"""Probe: both solvers' cloud statistics against resolution over a wider range than the smoke sweep
(docs/validation.md, "Convergence of both solvers with resolution").

    python scripts/probe_convergence.py [--spacings 100,80,64,50] [--cells 12,16,24,32] [--seconds 1000]
    python scripts/probe_convergence.py --cells "" --particles-set '{"smoothing.fields": ["temperature", "vapor"]}'

Runs `growing` in the smoke sweep's small box (1.2 x 1.6 x 1.2 km), seed 0, on the CPU: uniform particles at
each spacing, the grid at each cell count along the longest axis, all deposited on the analysis grid of the
middle particle spacing, and prints each run's time means over its cloudy period (cover above 1%) of cover,
mean LWP, cloud base and top (bench.studies.sweep.cloud_means) as CSV on stdout. Runs are cached in the
run store (--runs-root), so a second call prints at once."""
import argparse
import json
import sys
from pathlib import Path

import pandas as pd

from bench import runs
from bench.statistics import grid_for_scene
from bench.studies.context import StudyContext
from bench.studies.scales import SCALES
from bench.studies.sweep import SMOKE_BOX_SCENE, cloud_means
from pbf_cuda import load_scene

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--spacings", default="100,80,64,50", help="particle spacings, m")
parser.add_argument("--cells", default="12,16,24,32", help="grid cells along the longest axis")
parser.add_argument("--seconds", type=float, default=1000.0, help="model time, s")
parser.add_argument("--particles-set", default="{}", help="scene overrides of the particle runs, as JSON")
parser.add_argument("--runs-root", type=Path, default=None)
args = parser.parse_args()
try:
    particle_overrides = json.loads(args.particles_set)
except json.JSONDecodeError as exc:
    parser.error(f"--particles-set: not JSON ({exc})")
spacings = [float(s) for s in args.spacings.split(",")]
cells = [int(c) for c in args.cells.split(",") if c.strip()]
box = {**SMOKE_BOX_SCENE}
box["time.steps"] = int(round(args.seconds / box["time.dt"]))
base = load_scene("growing").replace(**box)
middle = base.replace(**{"particles.spacing": sorted(spacings)[len(spacings) // 2]})
analysis, _ = grid_for_scene(middle)
ctx = StudyContext(out=Path("/tmp/probe_convergence"), scale=SCALES["smoke"],
                   runs_root=args.runs_root or runs.default_root(), backend="cpu", quiet=False, scheduler="inline")
specs, labels = [], []
for s in spacings:
    specs.append(runs.RunSpec("particles", base.replace(**{"particles.spacing": s, **particle_overrides}), backend="cpu", seed=0,
                              keep_snapshots=1, diagnostics_resolution=analysis))
    labels.append(("particles", s))
size = max(base.domain.size)
for n in cells:
    shape = tuple(max(2, int(round(n * L / size))) for L in base.domain.size)
    specs.append(runs.RunSpec("grid", middle, seed=0, resolution=shape, keep_snapshots=1))
    labels.append(("grid", size / n))
results = ctx.run_parallel(specs, "convergence")
rows = [{"solver": solver, "resolution_m": round(res_m, 1), "stable": r.stable, **cloud_means(r)}
        for (solver, res_m), r in zip(labels, results)]
pd.DataFrame(rows).to_csv(sys.stdout, index=False, float_format="%.4g")
