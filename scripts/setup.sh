#!/usr/bin/env bash
# Set up cloudpbf on a fresh machine: system libraries for off-screen rendering, a virtual
# environment in .venv, and the package with its compiled solver (CPU backend always, CUDA backend
# when nvcc is found). Usage: scripts/setup.sh [extras]   (default extras: all)
#
# Each stage prints its name and time. Run again with nothing changed, it takes seconds: the package
# install is skipped while a stamp in .venv matches the hash of the lock, pyproject.toml, CMakeLists.txt,
# the C++ sources, the extras and the build switches (CLOUDPBF_FORCE_INSTALL=1 installs anyway).
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-all}"
setup_start=$(date +%s.%N)

stage_start=0
stage() {   # stage "name": start timing a stage
  stage_name=$1
  stage_start=$(date +%s.%N)
  echo "setup: ${stage_name} ..."
}
stage_done() {   # stage_done [note]: its time
  local took
  took=$(awk -v a="$stage_start" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }')
  echo "setup: ${stage_name}: ${1:-done} (${took} s)"
}

# 1. Off-screen OpenGL for pyvista/VTK renders in the report (OSMesa, EGL).
stage "system libraries (off-screen rendering)"
need_pkgs=()
for lib in libOSMesa.so libEGL.so.1 libGL.so.1 libXrender.so.1; do
  ldconfig -p 2>/dev/null | grep -q "$lib" || need_pkgs+=("$lib")
done
if [ "${#need_pkgs[@]}" -gt 0 ] && command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo"
  echo "setup: installing libosmesa6 libegl1 libgl1 libxrender1 libxt6 (missing: ${need_pkgs[*]})"
  $SUDO apt-get update -qq || true
  if $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 libegl1 libgl1 libxrender1 libxt6 >/dev/null; then
    stage_done "installed"
  else
    stage_done "could not install them; renders will be reported as unavailable"
  fi
elif [ "${#need_pkgs[@]}" -gt 0 ]; then
  stage_done "missing ${need_pkgs[*]} and no apt-get; renders will be reported as unavailable"
else
  stage_done "present"
fi

# 2. Build switches. The developer build is compiled for this machine: the CPU backend with
# -march=native (CLOUDPBF_CPU_NATIVE=ON; a wheel, `pip install .`, is portable), the CUDA backend, on a
# machine with a GPU, for that GPU (native). A machine without one (CI, laptops) builds the CPU backend
# only, unless CLOUDPBF_CUDA=ON asks for the CUDA backend too (then for one architecture, sm_90, to check
# that it compiles). Set CUDAARCHS to choose; a wheel build without it carries the portable default
# (every architecture since Volta, see CMakeLists.txt).
export CLOUDPBF_CPU_NATIVE=${CLOUDPBF_CPU_NATIVE:-ON}
if [ -z "${CUDAARCHS:-}" ] && command -v nvcc >/dev/null 2>&1; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L 2>/dev/null | grep -q "^GPU"; then
    export CUDAARCHS=native
  elif [ "${CLOUDPBF_CUDA:-AUTO}" = "ON" ]; then
    export CUDAARCHS=90
  else
    export CLOUDPBF_CUDA=${CLOUDPBF_CUDA:-OFF}
  fi
fi

# 3. The virtual environment.
stage "virtual environment (.venv)"
python=${PYTHON:-python3}
if [ -x .venv/bin/python ]; then
  stage_done "present ($(.venv/bin/python -V 2>&1))"
else
  "$python" -m venv .venv
  stage_done "created ($(.venv/bin/python -V 2>&1))"
fi

# 4. The package, editable, with its extras at the exact versions of constraints.txt (the lock CI and the
# demo use); CLOUDPBF_CONSTRAINTS=none takes the newest versions pyproject.toml's ranges allow,
# CLOUDPBF_CONSTRAINTS=FILE another lock.
constraints="${CLOUDPBF_CONSTRAINTS:-constraints.txt}"
stamp=.venv/cloudpbf-setup.stamp
inputs_hash() {
  {
    echo "extras=${extras} constraints=${constraints} python=$(.venv/bin/python -V 2>&1)"
    echo "cuda=${CLOUDPBF_CUDA:-} archs=${CUDAARCHS:-} native=${CLOUDPBF_CPU_NATIVE:-}"
    [ "$constraints" = "none" ] || cat "$constraints"
    cat pyproject.toml CMakeLists.txt
    find pbf_cuda/csrc -type f | LC_ALL=C sort | xargs cat
  } | sha256sum | cut -d' ' -f1
}
want=$(inputs_hash)
install_package() {
  stage "package install (pip install -e \".[${extras}]\", compiles the solver when its sources changed)"
  .venv/bin/python -m pip install -q --upgrade pip
  # --no-compile: no byte-code for every module of every package up front (a third of the install's time on
  # 2 cores); Python compiles and caches the modules a command imports, once, when it first imports them
  if [ "$constraints" = "none" ]; then
    .venv/bin/python -m pip install -q --no-compile -e ".[${extras}]"
  else
    .venv/bin/python -m pip install -q --no-compile -c "$constraints" -e ".[${extras}]"
  fi
  echo "$want" > "$stamp"
  stage_done "installed"
}
skipped=0
if [ "${CLOUDPBF_FORCE_INSTALL:-0}" != "1" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  stage "package install"
  stage_done "up to date (lock, pyproject.toml and C++ sources unchanged since the last set-up)"
  skipped=1
else
  install_package
fi

# 5. Check that the solver imports (and which backends it offers).
stage "import check"
check='import pbf_cuda; print(pbf_cuda.available_backends())'
if ! backends=$(.venv/bin/python -c "$check" 2>/dev/null); then
  if [ "$skipped" = "1" ]; then   # the stamp matched but the environment is broken: install again
    stage_done "failed; installing again"
    rm -f "$stamp"
    install_package
    stage "import check"
  fi
  backends=$(.venv/bin/python -c "$check")
fi
stage_done "pbf_cuda backends available: ${backends}"
total=$(awk -v a="$setup_start" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }')
echo "setup: ready in ${total} s"
