#!/usr/bin/env bash
# Set up (scripts/setup.sh) and run the whole test suite. GPU tests run where a CUDA device exists.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh all
# One pytest-xdist worker per core, each with one OpenMP thread (two threads per worker on two cores
# oversubscribe them); an idle worker steals queued tests from a busy one (--dist worksteal), so the
# smoke demo does not hold a queue behind it. CLOUDPBF_TEST_WORKERS=0 runs the suite in this process.
workers=${CLOUDPBF_TEST_WORKERS:-$(nproc)}
if [ "$workers" -gt 1 ]; then
  export OMP_NUM_THREADS=1
  exec .venv/bin/python -m pytest -q -n "$workers" --dist worksteal "$@"
fi
exec .venv/bin/python -m pytest -q "$@"
