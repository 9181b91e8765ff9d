#!/usr/bin/env bash
# Set up (scripts/setup.sh) and run the whole test suite. GPU tests run where a CUDA device exists.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh all
exec .venv/bin/python -m pytest -q "$@"
