#!/usr/bin/env bash
# Before and after a solver change on one machine, in one run: builds the solver of OLD (a commit) and of the
# working tree, each into its own folder (pip install --target, never over an installed solver), then times the
# cases of benchmarks/step_timing.py with each, twice, interleaved, and prints the table (docs/benchmarks.md).
#
#   benchmarks/compare_builds.sh OLD [backend]        # e.g. 993d377 cuda; CUDAARCHS=native for this GPU only
#
# Both builds are imported from their folders: run it where no editable install of cloudpbf shadows them
# (pip uninstall cloudpbf first, or use a fresh environment).
set -uo pipefail
cd "$(dirname "$0")/.."
old=${1:?usage: benchmarks/compare_builds.sh OLD_COMMIT [backend]}
backend=${2:-cuda}
root=${TMPDIR:-/tmp}/cloudpbf-compare
rm -rf "$root" && mkdir -p "$root/old_tree"
git archive "$old" | tar -x -C "$root/old_tree" || exit 1
python3 -m pip install -q --no-build-isolation --no-deps --target "$root/old" "$root/old_tree" > "$root/old.log" 2>&1 \
  || { tail -30 "$root/old.log"; exit 1; }
python3 -m pip install -q --no-build-isolation --no-deps --target "$root/new" . > "$root/new.log" 2>&1 \
  || { tail -30 "$root/new.log"; exit 1; }
for repeat in 1 2; do
  PYTHONPATH="$root/old" python3 benchmarks/step_timing.py "$old" --backend "$backend" >> "$root/timing.jsonl"
  PYTHONPATH="$root/new" python3 benchmarks/step_timing.py working-tree --backend "$backend" >> "$root/timing.jsonl"
done
python3 benchmarks/step_timing.py --table "$root/timing.jsonl"
echo "lines: $root/timing.jsonl"
