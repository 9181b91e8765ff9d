#!/usr/bin/env bash
# Set up and run the main job: Table 1, adaptive vs non-adaptive, particles vs grid, sweeps,
# stability map and the HTML report (scaled down automatically on a CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh all
exec .venv/bin/cloudpbf demo --scale "${CLOUDPBF_SCALE:-auto}" "$@"
