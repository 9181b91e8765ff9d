"""Probe: the grid baseline in the shallow-cumulus regime, beside the particles' study
(docs/validation.md, "Shallow cumulus").

    python scripts/probe_shallow_grid.py [--seeds 0,1,2] [--cells 94] [--out grid_shallow.csv]

Runs `shallow_cumulus` in the grid baseline (jax; its default device) at --cells per side (94: one cell per
particle spacing of the scene, 34 m), one run per seed (the seed shifts the heating pattern as it does for the
particles), and analyses each run as the study analyses the particle runs (bench.studies.shallow_cumulus.analyse:
cover, cloud-fraction profile, base, top, LWP, clouds over the last half of the run). Prints one CSV row per seed
and their mean (with_seed_mean, as the study's); --out also writes them."""
import argparse
import sys
from pathlib import Path

import pandas as pd

from bench import runs
from bench.studies.context import StudyContext
from bench.studies.scales import SCALES
from bench.studies.shallow_cumulus import SCENE, analyse, with_seed_mean
from pbf_cuda import load_scene

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--seeds", default="0,1,2")
parser.add_argument("--cells", type=int, default=94, help="grid cells per side")
parser.add_argument("--runs-root", type=Path, default=None)
parser.add_argument("--out", type=Path, default=None)
args = parser.parse_args()
scene = load_scene(SCENE)
ctx = StudyContext(out=Path("/tmp/probe_shallow_grid"), scale=SCALES["gpu"],
                   runs_root=args.runs_root or runs.default_root(), quiet=False, scheduler="inline")
seeds = [int(s) for s in args.seeds.split(",")]
specs = [runs.RunSpec("grid", scene, seed=s, resolution=(args.cells,) * 3, keep_snapshots=1) for s in seeds]
rows = []
for spec, res in zip(specs, ctx.run_parallel(specs, "shallow grid")):
    row, _, _ = analyse(res, spec.scene)
    rows.append({"solver": "grid", "seed": str(spec.seed), "cells": args.cells, **row,
                 "device": res.info.get("device", ""), "commit": ctx.commit})
frame = with_seed_mean(pd.DataFrame(rows))
frame.to_csv(sys.stdout, index=False, float_format="%.4g")
if args.out is not None:
    runs.write_csv(frame, args.out)
