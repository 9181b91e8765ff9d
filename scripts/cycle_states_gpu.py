"""The compact states behind example 2's renders, for a study whose runs are no longer in the run cache.

    python scripts/cycle_states_gpu.py OUT_DIR           # on a GPU machine, then locally:
    python -c "from bench.studies.cycling import render_cycle_states; render_cycle_states('OUT_DIR', 'reports/gpu/data/renders')"

Runs the seed-0 specs of `cloudpbf cycling --scale gpu` again (the same scenes; seed 0 keeps every diagnostic
state) on three local dask workers, then writes cycle_<mode>_<peak|min>.npz at the first cycle's peak and
clearest moment of the committed reports/gpu/data/cycling_cycles.csv and cycling_budgets.csv
(bench.studies.cycling.cycle_states).  Rendering needs pyvista, which the GPU machine may lack."""
import sys
from pathlib import Path

import pandas as pd

from bench.cli_common import Backend, ScaleName, study_context
from bench.studies.cycling import cycle_states, cycling_specs

out = Path(sys.argv[1])
with study_context(Path("/tmp/cycle_states_study"), Path("/tmp/runs"), ScaleName.gpu, Backend.cuda, 3, None,
                   True) as ctx:
    plan = [p for p in cycling_specs(ctx, 3) if p[1] == 0]
    results = ctx.run_parallel([spec for _, _, spec in plan], "cycling seed 0")
cycles = pd.read_csv("reports/gpu/data/cycling_cycles.csv")
budgets = pd.read_csv("reports/gpu/data/cycling_budgets.csv")
for (mode, _seed, _spec), res in zip(plan, results):
    cycles.loc[(cycles["mode"] == mode) & (cycles["seed"] == 0), "run_dir"] = str(res.path)
print(cycle_states(cycles, budgets, out))
