#!/usr/bin/env bash
# API reference from the docstrings (pdoc): docs/api/index.html and one page per module.
# Usage: scripts/api_docs.sh [OUT]   (default OUT: docs/api; generated, not committed)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-docs/api}"
py=.venv/bin/python
[ -x "$py" ] || py=python3
"$py" -m pdoc --docformat restructuredtext --no-search --footer-text "cloudpbf $("$py" -c 'from pbf_cuda import __version__; print(__version__)')" \
  -o "$out" pbf_cuda pbf_cuda.simulation pbf_cuda.scene cloudpbf_io.export cloudpbf_io.bgeo cloudpbf_io.progress pbf_cuda.cuda_arch \
  pbf_cuda.initial_state pbf_cuda.noise pbf_cuda.kernels grid_baseline grid_baseline.simulation grid_baseline.model \
  grid_baseline.projection grid_baseline.noise grid_baseline.compat cloudpbf
echo "api_docs: wrote $out/index.html"
