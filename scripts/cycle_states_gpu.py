"""The compact states behind example 2's renders, for a study whose runs are no longer in the run cache.

    python scripts/cycle_states_gpu.py OUT_DIR [MODE ...]   # on a GPU machine, then locally:
    python -c "from cloudpbf.studies.cycling import render_cycle_states; render_cycle_states('OUT_DIR', 'reports/gpu/data/renders')"

Runs the seed-0 specs of `cloudpbf cycling --scale gpu` again (the same scenes; seed 0 keeps every diagnostic
state; MODE limits it to some of non-adaptive, adaptive, grid) one after another in this process, then writes
cycle_<mode>_<peak|min>.npz at the first cycle's peak and clearest moment of the committed
reports/gpu/data/cycling_cycles.csv and cycling_budgets.csv (cloudpbf.studies.cycling.cycle_states).
CLOUDPBF_STATES_SCALE=cpu runs the CPU scale's specs on the CPU instead (to try the script without a GPU; the
committed times are the GPU study's).  Rendering needs pyvista, which the GPU machine may lack."""
import os
import sys
from pathlib import Path

import pandas as pd

from cloudpbf.cli_common import Backend, ScaleName, study_context
from cloudpbf.studies.cycling import cycle_states, cycling_specs

out = Path(sys.argv[1])
modes = set(sys.argv[2:]) or {"non-adaptive", "adaptive", "grid"}
scale, backend = (ScaleName.gpu, Backend.cuda) if os.environ.get("CLOUDPBF_STATES_SCALE", "gpu") == "gpu" \
    else (ScaleName.cpu, Backend.cpu)
# inline: the few seed-0 runs one after another in this process, with progress, no dask cluster to start
with study_context(Path("/tmp/cycle_states_study"), Path("/tmp/runs"), scale, backend, 1, "inline", False) as ctx:
    plan = [p for p in cycling_specs(ctx, 3) if p[1] == 0 and p[0] in modes]
    if not plan:
        sys.exit(f"no seed-0 run has a mode in {sorted(modes)}")
    results = ctx.run_parallel([spec for _, _, spec in plan], "cycling seed 0")
cycles = pd.read_csv("reports/gpu/data/cycling_cycles.csv")
cycles = cycles[cycles["mode"].isin(modes)].copy()
budgets = pd.read_csv("reports/gpu/data/cycling_budgets.csv")
for (mode, _seed, _spec), res in zip(plan, results):
    cycles.loc[(cycles["mode"] == mode) & (cycles["seed"] == 0), "run_dir"] = str(res.path)
print(cycle_states(cycles, budgets, out))
