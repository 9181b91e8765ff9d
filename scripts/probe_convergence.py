"""Probe: both solvers' cloud statistics against resolution over a wider range than the smoke sweep
(docs/validation.md, "Convergence of both solvers with resolution").

    python scripts/probe_convergence.py [--spacings 100,80,64,50] [--cells 12,16,24,32] [--seconds 1000]
    python scripts/probe_convergence.py --cells "" --particles-set '{"smoothing.fields": ["temperature", "vapor"]}'
    python scripts/probe_convergence.py --full-domain --backend cuda --spacings 68,54,43,34 --cells 48,64,80,94 \
        --out reports/gpu/data/convergence.csv          # the paper's domain on a GPU (103k-831k particles)

Runs `growing` in the smoke sweep's small box (1.2 x 1.6 x 1.2 km; --full-domain: the scene's 3.2 km cube),
seed 0, on the CPU (--backend cuda: particles on the GPU, the grid on jax's default device): uniform particles at
each spacing, the grid at each cell count along the longest axis, all deposited on the analysis grid of the
middle particle spacing, and prints each run's time means over its cloudy period (cover above 1%) of cover,
mean LWP, cloud base and top (bench.studies.sweep.cloud_means) as CSV on stdout (and to --out, with the
columns the report's convergence plot reads: parameter, method, device, commit). Runs are cached in the
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
parser.add_argument("--full-domain", action="store_true", help="the scene's own domain instead of the small box")
parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"), help="the particle solver's backend")
parser.add_argument("--out", type=Path, default=None, help="also write the rows to this CSV")
args = parser.parse_args()
try:
    particle_overrides = json.loads(args.particles_set)
except json.JSONDecodeError as exc:
    parser.error(f"--particles-set: not JSON ({exc})")
spacings = [float(s) for s in args.spacings.split(",")]
cells = [int(c) for c in args.cells.split(",") if c.strip()]
box = {} if args.full_domain else {**SMOKE_BOX_SCENE}
box["time.steps"] = int(round(args.seconds / box.get("time.dt", load_scene("growing").time.dt)))
base = load_scene("growing").replace(**box)
middle = base.replace(**{"particles.spacing": sorted(spacings)[len(spacings) // 2]})
analysis, _ = grid_for_scene(middle)
ctx = StudyContext(out=Path("/tmp/probe_convergence"), scale=SCALES["smoke"],
                   runs_root=args.runs_root or runs.default_root(), backend=args.backend, quiet=False,
                   scheduler="inline")
specs, labels = [], []
for s in spacings:
    specs.append(runs.RunSpec("particles", base.replace(**{"particles.spacing": s, **particle_overrides}), backend=args.backend,
                              seed=0, keep_snapshots=1, diagnostics_resolution=analysis))
    labels.append(("particles", s))
size = max(base.domain.size)
for n in cells:
    shape = tuple(max(2, int(round(n * L / size))) for L in base.domain.size)
    specs.append(runs.RunSpec("grid", middle, seed=0, resolution=shape, keep_snapshots=1))
    labels.append(("grid", size / n))
results = ctx.run_parallel(specs, "convergence")
rows = [{"solver": solver, "resolution_m": round(res_m, 1), "stable": r.stable, **cloud_means(r),
         "parameter": "spacing" if solver == "particles" else "cells", "method": solver,
         "device": r.info.get("device", ""), "commit": ctx.commit}
        for (solver, res_m), r in zip(labels, results)]
frame = pd.DataFrame(rows)
frame.to_csv(sys.stdout, index=False, float_format="%.4g")
if args.out is not None:
    runs.write_csv(frame, args.out)
