#!/usr/bin/env bash
# Set up cloudpbf on a fresh machine: system libraries for off-screen rendering, a virtual
# environment in .venv, and the package with its compiled solver (CPU backend always, CUDA backend
# when nvcc is found). Usage: scripts/setup.sh [extras]   (default extras: all)
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-all}"

# Off-screen OpenGL for pyvista/VTK renders in the report (OSMesa, EGL).
need_pkgs=()
for lib in libOSMesa.so libEGL.so.1 libGL.so.1 libXrender.so.1; do
  ldconfig -p 2>/dev/null | grep -q "$lib" || need_pkgs+=("$lib")
done
if [ "${#need_pkgs[@]}" -gt 0 ] && command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo"
  echo "setup: installing off-screen rendering libraries (missing: ${need_pkgs[*]})"
  $SUDO apt-get update -qq || true
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 libegl1 libgl1 libxrender1 libxt6 >/dev/null \
    || echo "setup: could not install rendering libraries; renders will be reported as unavailable"
fi

# CUDA backend of this (editable, from-source) build: on a machine with a GPU it is built for that GPU
# (native). A machine without one (CI, laptops) builds the CPU backend only, unless CLOUDPBF_CUDA=ON
# asks for the CUDA backend too (then for one architecture, sm_90, to check that it compiles). Set
# CUDAARCHS to choose; `pip install .` or a wheel build without it carries the portable default (every
# architecture since Volta, see CMakeLists.txt).
if [ -z "${CUDAARCHS:-}" ] && command -v nvcc >/dev/null 2>&1; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L 2>/dev/null | grep -q "^GPU"; then
    export CUDAARCHS=native
  elif [ "${CLOUDPBF_CUDA:-AUTO}" = "ON" ]; then
    export CUDAARCHS=90
  else
    export CLOUDPBF_CUDA=${CLOUDPBF_CUDA:-OFF}
  fi
fi

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# Exact versions from constraints.txt (the lock CI and the demo use); CLOUDPBF_CONSTRAINTS=none takes the
# newest versions pyproject.toml's ranges allow, CLOUDPBF_CONSTRAINTS=FILE another lock.
constraints="${CLOUDPBF_CONSTRAINTS:-constraints.txt}"
if [ "$constraints" = "none" ]; then
  .venv/bin/python -m pip install -q -e ".[${extras}]"
else
  .venv/bin/python -m pip install -q -c "$constraints" -e ".[${extras}]"
fi
.venv/bin/python -c "import pbf_cuda; print('setup: pbf_cuda backends available:', pbf_cuda.available_backends())"
