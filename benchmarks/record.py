"""Record the benchmarks of one commit with the solver installed in this environment.

    python benchmarks/record.py [COMMIT] [--quick] [--machine NAME] [-- extra asv arguments]

runs ``asv run --python=same --set-commit-hash COMMIT`` (default: HEAD) from benchmarks/ and names the
environment ``existing-py<major>.<minor>`` instead of asv's default (the interpreter's absolute path),
so results recorded in different checkouts or virtual environments of one machine compare with each
other (``asv compare``) and the results folder holds no local path.  The installed package must be
built from COMMIT's sources (``scripts/setup.sh`` after checking COMMIT out); the compiled solver
refuses sources other than its own, so a stale build fails instead of being measured.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def normalise(results: Path, commit: str) -> list[Path]:
    """Rename this interpreter's result files of `commit` to the portable environment name."""
    portable = f"existing-py{sys.version_info.major}.{sys.version_info.minor}"
    done = []
    for path in results.glob(f"*/{commit[:8]}-existing-*.json"):
        data = json.loads(path.read_text())
        if data.get("python") not in (sys.executable, portable) and data.get("env_name") != portable:
            continue
        data["env_name"] = portable
        data["python"] = f"{sys.version_info.major}.{sys.version_info.minor}"
        data.setdefault("params", {})["python"] = data["python"]
        target = path.with_name(f"{commit[:8]}-{portable}.json")
        target.write_text(json.dumps(data, indent=None, sort_keys=True))
        if target != path:
            path.unlink()
        done.append(target)
    return done


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("commit", nargs="?", default="HEAD")
    parser.add_argument("--quick", action="store_true", help="one sample per benchmark (asv --quick)")
    parser.add_argument("--machine", default=None, help="asv machine name (default: asv's, from ~/.asv-machine.json)")
    parser.add_argument("extra", nargs=argparse.REMAINDER, help="more asv run arguments after --")
    args = parser.parse_args(argv)
    commit = subprocess.check_output(["git", "rev-parse", args.commit], cwd=HERE, text=True).strip()
    cmd = [sys.executable, "-m", "asv", "run", "--config", "asv.conf.json", "--python=same",
           "--set-commit-hash", commit]
    if args.quick:
        cmd.append("--quick")
    if args.machine:
        cmd += ["--machine", args.machine]
    cmd += [a for a in args.extra if a != "--"]
    code = subprocess.call(cmd, cwd=HERE, env=os.environ.copy())
    for path in normalise(HERE / "results", commit):
        print(f"recorded {path.relative_to(HERE.parent)}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
