#!/usr/bin/env bash
# Record the benchmarks of past commits on this machine: each commit is checked out into its own
# worktree, built into its own folder (never over the solver installed here) and measured with
# benchmarks/record.py (docs/benchmarks.md).
#
#   benchmarks/record_commits.sh MACHINE COMMIT [COMMIT ...]
#
# MACHINE is the asv machine name (described with `asv machine` on first use). Extra asv arguments
# go in ASV_ARGS (e.g. ASV_ARGS="-a rounds=1"); CLOUDPBF_ASV_SIZES narrows the sizes. The build
# uses the build requirements already installed (pip --no-build-isolation); CUDAARCHS picks the GPU
# architectures (native: this machine's).
set -uo pipefail
cd "$(dirname "$0")/.."
machine=${1:?usage: benchmarks/record_commits.sh MACHINE COMMIT [COMMIT ...]}
shift
root=${TMPDIR:-/tmp}/cloudpbf-asv
mkdir -p "$root"
status=0
for commit in "$@"; do
  sha=$(git rev-parse --verify "$commit^{commit}") || { echo "record_commits: no commit '$commit'" >&2; exit 2; }
  tree="$root/tree-${sha:0:8}" site="$root/site-${sha:0:8}"
  [ -d "$tree" ] || git worktree add -q --detach "$tree" "$sha" || exit 1
  if [ ! -d "$site/pbf_cuda" ]; then
    echo "== build ${sha:0:8} ($(date +%T))"
    python3 -m pip install -q --no-build-isolation --no-deps --target "$site" "$tree" > "$root/build-${sha:0:8}.log" 2>&1 \
      || { tail -30 "$root/build-${sha:0:8}.log"; status=1; continue; }
  fi
  echo "== record ${sha:0:8} ($(date +%T))"
  # The commit's solver and harness first (the benchmarks import cloudpbf.studies.scales). asv drops
  # PYTHONPATH from the benchmarks' environment and uses ASV_PYTHONPATH in its place.
  ASV_PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}" python3 benchmarks/record.py "$sha" --machine "$machine" \
    -- ${ASV_ARGS:-} || status=1
done
exit $status
