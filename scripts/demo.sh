#!/usr/bin/env bash
# Set up and run the main job: Table 1, adaptive vs non-adaptive, particles vs grid, sweeps,
# stability map and the HTML report: the paper's counts on a GPU, the smoke scale (minutes) on a CPU;
# CLOUDPBF_SCALE=smoke|cpu|gpu overrides (cpu: ~50k particles, hours on 2 cores).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh all
exec .venv/bin/cloudpbf demo --scale "${CLOUDPBF_SCALE:-auto}" "$@"
