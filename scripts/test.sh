#!/usr/bin/env bash
# Set up (scripts/setup.sh) and run the tests.
#   scripts/test.sh               the whole suite (what CI runs)
#   scripts/test.sh --quick       the quick tier for contributors: every test not marked `slow`
#   scripts/test.sh [--quick] ARGS...   ARGS go to pytest (a file, -k EXPR, -x, ...)
# Tests marked `gpu` run where a CUDA device exists and the CUDA backend was built; elsewhere they are
# skipped, and this script says so before the run and lists the skip reasons after it (-rs).
set -euo pipefail
cd "$(dirname "$0")/.."
tier=full
args=()
for arg in "$@"; do
  case "$arg" in
    --quick) tier=quick ;;
    *) args+=("$arg") ;;
  esac
done

scripts/setup.sh all

select=()
if [ "$tier" = quick ]; then
  select=(-m "not slow")
  what="the quick tier (tests not marked slow: no smoke demo, no long physics runs)"
else
  what="the whole suite"
fi

# Why the GPU tests will or will not run, in one line.
gpu_note=$(.venv/bin/python - <<'EOF' 2>/dev/null || echo "gpu tests: skipped (the solver module did not import)"
import pbf_cuda
from pbf_cuda import _core
if "cuda" in pbf_cuda.available_backends():
    print("gpu tests: run (CUDA backend built, device found)")
elif not _core.cuda_built():
    print("gpu tests: skipped: this build has no CUDA backend (set-up builds one where nvcc and a GPU are found, "
          "or with CLOUDPBF_CUDA=ON)")
elif _core.cuda_device_count() == 0:
    print("gpu tests: skipped: no CUDA device on this machine (they run on a machine with an NVIDIA GPU)")
else:
    from pbf_cuda.cuda_arch import cuda_problem
    print(f"gpu tests: skipped: {cuda_problem()}")
EOF
)

# One pytest-xdist worker per core, each with one OpenMP thread (two threads per worker on two cores
# oversubscribe them); an idle worker steals queued tests from a busy one (--dist worksteal), so the
# smoke demo does not hold a queue behind it. CLOUDPBF_TEST_WORKERS=0 runs the suite in this process.
workers=${CLOUDPBF_TEST_WORKERS:-$(nproc)}
if [ "$workers" -gt 1 ]; then how="with ${workers} workers"; else how="in one process"; fi
echo "test: running ${what} ${how}; ${gpu_note}"
# pytest's own last line (passed, failed, skipped, seconds) closes the output.
if [ "$workers" -gt 1 ]; then
  export OMP_NUM_THREADS=1
  exec .venv/bin/python -m pytest -q -rs -n "$workers" --dist worksteal ${select[@]+"${select[@]}"} ${args[@]+"${args[@]}"}
fi
exec .venv/bin/python -m pytest -q -rs ${select[@]+"${select[@]}"} ${args[@]+"${args[@]}"}
