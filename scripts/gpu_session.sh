#!/usr/bin/env bash
# One batch on a CUDA machine: build, GPU tests, benchmarks (PBF scaling, Table 1, split/merge cost,
# grid scaling).
# Results go to $OUT (default reports/gpu/session); set CLOUDPBF_COMMIT when the tree has no .git.
# Wheels missing on the machine can be carried in .whl/ (installed into /tmp/site first).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-reports/gpu/session}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 CLOUDPBF_RUNS=${CLOUDPBF_RUNS:-/tmp/cloudpbf-runs}
stage() { echo "=== $1 ($(date +%T))"; }
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
stage "device"; nvidia-smi -L; nvcc --version | tail -1
stage "build"
export CUDAARCHS=${CUDAARCHS:-native}   # this machine's GPU only: a faster build than the portable default
python3 -m pip install -q --no-build-isolation --no-deps -e . > "$OUT/build.log" 2>&1 || { tail -40 "$OUT/build.log"; exit 1; }
python3 -c "import pbf_cuda; print('backends', pbf_cuda.available_backends())"
stage "gpu tests"
[ -n "${SKIP_GPU_TESTS:-}" ] || timeout 420 python3 -m pytest -q -m gpu -p no:cacheprovider tests/test_solver_core.py tests/test_cloud_physics.py \
  tests/test_adaptive.py tests/test_atmosphere_energy.py tests/test_cycling.py 2>&1 | tee "$OUT/gpu_tests.log" | tail -15
R=${REPORT_DIR:-reports/gpu}
for step in "$@"; do
  stage "$step"
  case "$step" in
    table1) timeout 300 python3 -X faulthandler -m cloudpbf.cli table1 --scale gpu --out "$R" -q && cat "$R/data/table1.csv" ;;
    scaling) timeout 300 python3 -m cloudpbf.cli pbf-scaling --sizes 250000,1000000,4000000,16000000 --steps 20 --quiet \
               --out "$R/data/pbf_scaling.csv" && cat "$R/data/pbf_scaling.csv" ;;
    grid) timeout 240 python3 -m cloudpbf.cli grid-scaling --sizes 32,64,128 --steps 10 --devices cpu,gpu \
            --commit "${CLOUDPBF_COMMIT:-unknown}" --out "$R/data/grid_scaling.csv" && cat "$R/data/grid_scaling.csv" ;;
    adaptive_cost)  # level-0 spacings 45 m and 40 m: about 430k and 600k adaptive particles on average
      timeout 300 python3 -m cloudpbf.cli adaptive-cost --spacing 45 --steps 500 --quiet --out /tmp/ac45.csv &&
      timeout 300 python3 -m cloudpbf.cli adaptive-cost --spacing 40 --steps 500 --quiet --out /tmp/ac40.csv &&
      python3 -c "import pandas as pd, sys; pd.concat([pd.read_csv('/tmp/ac45.csv'), pd.read_csv('/tmp/ac40.csv')]).to_csv(sys.argv[1], index=False)" \
        "$R/data/adaptive_cost.csv" && cat "$R/data/adaptive_cost.csv" ;;
    constant_gravity) timeout 600 python3 -m cloudpbf.cli constant-gravity --gravity 0.1,0.3,1.0 --quiet \
                        --out "$R/data/constant_gravity.csv" ;;
    adaptive_pareto|adaptive_pareto_cumulus)  # paper scale, 3 seeds; runs cached in $CLOUDPBF_RUNS across calls
      scene=growing; [ "$step" = adaptive_pareto_cumulus ] && scene=cumulus
      timeout ${STUDY_TIMEOUT:-560} python3 -m cloudpbf.cli adaptive-pareto --scene "$scene" --seeds 3 --scale gpu \
        --backend cuda ${PARETO_ARGS---scheduler inline} --out "$R" -q ;;
    cycling)  # paper example 2 at the scene files' size (930k particles, 4200 s), 3 seeds x 3 modes
      timeout ${CYCLING_TIMEOUT:-3000} python3 -m cloudpbf.cli cycling --scale gpu --seeds 3 --backend cuda ${CYCLING_ARGS---scheduler inline} \
        --out "$R" -q && cat "$R/data/cycling_cycles.csv" ;;
    cycling_states)  # seed 0's states at its first cycle's peak and clearest moment, for renders where pyvista is
      python3 -c "import sys, pandas as pd; from cloudpbf.studies.cycling import cycle_states
d = sys.argv[1] + '/data/'
print(cycle_states(pd.read_csv(d + 'cycling_cycles.csv'), pd.read_csv(d + 'cycling_budgets.csv'), sys.argv[2]))" \
        "$R" /tmp/cycle_states && tar cf "$OUT/cycle_states.tar" -C /tmp cycle_states ;;
    pareto_states)  # seed 0's final states of the best adaptive variant and its uniform twins, for renders
      python3 -c "import sys, json, pathlib, pandas as pd; from cloudpbf.studies.adaptive_pareto import pareto_states
d = pathlib.Path(sys.argv[1]) / 'data'
for suffix, scene in (('', 'growing'), ('_cumulus', 'cumulus')):
    if (d / f'adaptive_verdict{suffix}.json').is_file():
        print(pareto_states(pd.read_csv(d / f'adaptive_pareto{suffix}.csv'), pd.read_csv(d / f'adaptive_pareto_configs{suffix}.csv'),
                            json.loads((d / f'adaptive_verdict{suffix}.json').read_text()), f'/tmp/pareto_states/{scene}'))" \
        "$R" && tar cf "$OUT/pareto_states.tar" -C /tmp pareto_states ;;
    multigpu)  # the sweep's particle runs on 1 GPU, then on 2 (dask-cuda: the multigpu extra, e.g. from .whl/)
      timeout ${STUDY_TIMEOUT:-590} python3 -m cloudpbf.cli multigpu-sweep --gpus-list 1,2 --scale ${MULTIGPU_SCALE:-gpu} \
        --out "$R" -q && cat "$R/data/multigpu_sweep.csv" ;;
    compare|stress|sweep)
      timeout ${STUDY_TIMEOUT:-150} python3 -m cloudpbf.cli "$step" --scale cpu --backend cuda --scheduler inline --out "$R" -q ;;
    slab)  # final states of the Figure 1 slab (kappa 0 and 0.1), for renders on a machine with pyvista
      timeout 200 python3 - "$OUT" <<'PY'
import os, sys, numpy as np
from pbf_cuda import Simulation, load_scene
base = load_scene("smoothing_slab")
for tag, scene in (("unsmoothed", base.replace(**{"smoothing.kappa": 0.0})), ("smoothed", base)):
    sim = Simulation(scene, backend="cuda", seed=0)
    sim.step(scene.time.steps)
    st = sim.state()
    np.savez_compressed(os.path.join(sys.argv[1], f"slab_{tag}.npz"), position=st["position"], cloud=st["cloud"],
                        temperature=st["temperature"], step=sim.step_count)
    print("slab", tag, sim.n_particles, "cloudy", int((st["cloud"] > 1e-5).sum()), "step", sim.step_count)
PY
      ;;
    snapshots)  # compact final states of the Table 1 runs, for renders on a machine with pyvista
      python3 - "$R" <<PY
import sys, glob, numpy as np, pandas as pd
from cloudpbf.render import compact_particles
out = sys.argv[1]
for row in pd.read_csv(f"{out}/data/table1.csv").itertuples():
    snaps = sorted(glob.glob(f"{row.run_dir}/snapshots/*.npz"))
    if not snaps:
        continue
    z = np.load(snaps[-1])
    if row.example != "growing":
        continue
    # All cloudy particles and one in ten of the clear ones: enough for the renders, small enough to copy.
    keep = compact_particles(z, threshold=1e-6)
    np.savez_compressed(f"$OUT/state_{row.example}_{row.mode}.npz", **keep)
    print("saved", row.example, row.mode, len(keep["cloud"]), "of", len(z["cloud"]))
PY
      ;;
    asv)  # the benchmark history: ASV_COMMITS (default HEAD) recorded on this GPU (docs/benchmarks.md; asv from .whl/)
      M=gpu-$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | tr -c 'A-Za-z0-9\n' '-' | tr -s '-' | sed 's/-$//')
      python3 -m asv machine --config benchmarks/asv.conf.json --machine "$M" --yes > /dev/null
      CLOUDPBF_ASV_SIZES=${CLOUDPBF_ASV_SIZES:-64000,250000,1000000} ASV_ARGS=${ASV_ARGS:-"-a rounds=1 -a repeat=5"} \
        bash benchmarks/record_commits.sh "$M" ${ASV_COMMITS:-HEAD}
      mkdir -p "$OUT/asv" && cp -r "benchmarks/results/$M" "$OUT/asv/" ;;
    *) echo "unknown step $step" ;;
  esac
done
if [ -d "$R" ]; then tar czf "$OUT/report_data.tar.gz" --exclude='*.npz' -C "$(dirname "$R")" "$(basename "$R")"; ls -la "$OUT"; fi
stage "done"
