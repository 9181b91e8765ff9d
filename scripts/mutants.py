#!/usr/bin/env python3
"""Mutation testing: apply each mutant of scripts/mutants.toml alone to a copy of the tree, rebuild the CPU
solver module incrementally where the mutant is C++, run the mutant's tests, and report which tests caught it.

    .venv/bin/python scripts/mutants.py                 # every mutant; a table on stdout, JSON in the work dir
    .venv/bin/python scripts/mutants.py --only cloud-loading-sign --only pareto-dominance
    .venv/bin/python scripts/mutants.py --list

Nothing in the repository is modified: the copy (the committed tree of --ref, default HEAD, with the working
tree's tests/ and scripts/mutants.toml laid over it, so uncommitted tests can be tried) lives in --workdir
(default /tmp/cloudpbf-mutants), with its own CMake build of pbf_cuda._core (CLOUDPBF_CUDA=OFF, Ninja) and a
small virtual environment holding the build's requirements (nanobind, the CCCL headers; pyproject.toml's
build-system pins). The tests run with the project's interpreter (--python, default: this one) on the copy: a
sitecustomize drops the editable install's import hook, so `pbf_cuda`, `cloudpbf` and `grid_baseline` are the
copy's. A second run reuses the copy and the build (an incremental rebuild per C++ mutant: one translation unit
and the module's link).

A mutant is caught where one of its tests fails, and caught by its property where a failing test is one of
those its `catch` list names. Exit status 0 when every mutant is caught by its property, 1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "scripts" / "mutants.toml"
MODULE_GLOB = "_core*.so"
SITECUSTOMIZE = '''import sys
sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != "ScikitBuildRedirectingFinder"]
'''
# A pytest plugin (-p mutants_hypothesis): hypothesis reports a mutant's first failing example without shrinking it
# (the verdict is the same; shrinking only costs time).
PLUGIN = '''try:
    from hypothesis import Phase, settings
    settings.register_profile("mutants", phases=[Phase.explicit, Phase.reuse, Phase.generate])
    settings.load_profile("mutants")
except ImportError:
    pass
'''


def log(msg: str) -> None:
    print(f"[mutants {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def run(cmd, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, text=True, capture_output=True, **kw)


def load_mutants(path: Path) -> list[dict]:
    with open(path, "rb") as f:
        mutants = tomllib.load(f)["mutant"]
    ids = [m["id"] for m in mutants]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise SystemExit(f"{path}: duplicated mutant ids {sorted(dup)}")
    for m in mutants:
        missing = {"id", "file", "find", "replace", "tests", "catch"} - set(m)
        if missing:
            raise SystemExit(f"{path}: mutant {m.get('id')} lacks {sorted(missing)}")
    return mutants


# ---- the copy ------------------------------------------------------------------------------------------
def make_tree(tree: Path, ref: str) -> None:
    """tree = the committed files of `ref`, then the working tree's tests/ and scripts/mutants.toml over them."""
    if tree.exists():
        shutil.rmtree(tree)
    tree.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    commit = run(["git", "-C", str(REPO), "rev-parse", "--short", ref]).stdout.strip()
    (tree / ".mutants-commit").write_text(commit + "\n")
    overlay(tree)


def overlay(tree: Path) -> None:
    for src in (REPO / "tests").glob("*.py"):
        shutil.copy2(src, tree / "tests" / src.name)
    shutil.copy2(DATA, tree / "scripts" / "mutants.toml")


def build_requirements() -> list[str]:
    with open(REPO / "pyproject.toml", "rb") as f:
        reqs = tomllib.load(f)["build-system"]["requires"]
    return [r for r in reqs if not r.startswith("scikit-build-core")]


def build_python(workdir: Path, given: str | None) -> str:
    """An interpreter with nanobind and the CCCL headers (the CMake configure step imports both)."""
    if given:
        return given
    venv = workdir / "buildenv"
    py = venv / "bin" / "python"
    if not py.exists():
        log(f"creating {venv} with {' '.join(build_requirements())}")
        base = getattr(sys, "_base_executable", sys.executable)
        subprocess.run([base, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", *build_requirements()], check=True)
    return str(py)


def configure(tree: Path, build: Path, bpy: str) -> None:
    if (build / "build.ninja").exists():
        return
    log(f"configuring {build}")
    cmd = ["cmake", "-S", str(tree), "-B", str(build), "-G", "Ninja", "-DCLOUDPBF_CUDA=OFF",
           f"-DPython_EXECUTABLE={bpy}", "-DCMAKE_BUILD_TYPE=Release"]
    out = run(cmd)
    if out.returncode:
        raise SystemExit(f"cmake configure failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")


def build_module(tree: Path, build: Path, jobs: int) -> tuple[bool, str, float]:
    """Incremental build of _core; the module copied into the tree's pbf_cuda/. (ok, log tail, seconds)."""
    t0 = time.time()
    out = run(["nice", "-n", "10", "ninja", "-C", str(build), f"-j{jobs}", "_core"])
    secs = time.time() - t0
    if out.returncode:
        return False, (out.stdout + out.stderr)[-2000:], secs
    modules = sorted(build.glob(MODULE_GLOB))
    if not modules:
        return False, "no module built", secs
    for old in (tree / "pbf_cuda").glob(MODULE_GLOB):
        old.unlink()
    shutil.copy2(modules[0], tree / "pbf_cuda" / modules[0].name)
    return True, "", secs


# ---- tests ----------------------------------------------------------------------------------------------
def run_tests(tree: Path, workdir: Path, python: str, tests: list[str],
              timeout: float) -> tuple[str, list[str], float]:
    """('passed' | 'failed' | 'error' | 'timeout', failing test ids, seconds)."""
    site = workdir / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    (site / "mutants_hypothesis.py").write_text(PLUGIN)
    env = dict(os.environ, PYTHONPATH=f"{site}{os.pathsep}{tree}", OMP_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1")
    env.pop("PYTHONHOME", None)
    junit = workdir / "junit.xml"
    if junit.exists():
        junit.unlink()
    cmd = [python, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "mutants_hypothesis", "-n", "0",
           "-m", "not gpu", f"--junitxml={junit}", *tests]
    t0 = time.time()
    try:
        out = subprocess.run(cmd, cwd=tree, env=env, text=True, capture_output=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", [], time.time() - t0
    secs = time.time() - t0
    failing = []
    if junit.exists():
        for case in ET.parse(junit).getroot().iter("testcase"):
            if case.find("failure") is not None or case.find("error") is not None:
                # junit's classname is the dotted module (tests.test_x): back to pytest's node id, tests/test_x.py::name
                module = case.get("classname", "").replace(".", "/")
                failing.append(f"{module}.py::{case.get('name', '')}")
    if out.returncode == 0:
        return "passed", failing, secs
    if failing:
        return "failed", failing, secs
    return "error", [(out.stdout + out.stderr)[-1500:]], secs


# ---- one mutant -------------------------------------------------------------------------------------------
def apply(tree: Path, m: dict) -> str:
    path = tree / m["file"]
    text = path.read_text()
    count = text.count(m["find"])
    if count != 1:
        raise ValueError(f"{m['id']}: the text to mutate occurs {count} times in {m['file']} (stale mutant?)")
    path.write_text(text.replace(m["find"], m["replace"]))
    return text


def is_cpp(m: dict) -> bool:
    return m["file"].startswith("pbf_cuda/csrc/")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", default="/tmp/cloudpbf-mutants", help="where the copy, its build and the report go")
    ap.add_argument("--ref", default="HEAD", help="the commit whose tree is copied (tests/ from the working tree)")
    ap.add_argument("--python", default=sys.executable, help="interpreter that runs the tests (the project's venv)")
    ap.add_argument("--build-python", default=None,
                    help="interpreter with nanobind and nvidia-cuda-cccl for CMake (default: a venv in the workdir)")
    ap.add_argument("--only", action="append", default=[], help="run only this mutant id (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--fresh", action="store_true", help="copy the tree again (keeps the build directory)")
    ap.add_argument("--jobs", type=int, default=2, help="parallel compile jobs")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per mutant's test run")
    args = ap.parse_args()

    mutants = load_mutants(DATA)
    if args.list:
        for m in mutants:
            print(f"{m['id']:40s} {m['file']:36s} {m.get('property', '')}")
        return 0
    if args.only:
        unknown = set(args.only) - {m["id"] for m in mutants}
        if unknown:
            raise SystemExit(f"unknown mutant ids: {sorted(unknown)}")
        mutants = [m for m in mutants if m["id"] in args.only]

    workdir = Path(args.workdir)
    tree, build = workdir / "tree", workdir / "build"
    workdir.mkdir(parents=True, exist_ok=True)
    if args.fresh or not (tree / "pyproject.toml").exists():
        log(f"copying {args.ref} to {tree}")
        make_tree(tree, args.ref)
    else:
        overlay(tree)
    bpy = build_python(workdir, args.build_python)
    configure(tree, build, bpy)
    ok, tail, secs = build_module(tree, build, args.jobs)
    if not ok:
        raise SystemExit(f"the unmutated module does not build:\n{tail}")
    log(f"unmutated module built ({secs:.0f} s)")

    # Python mutants first, then the C++ ones (each rebuild then starts from the last), a clean rebuild at the end.
    mutants = sorted(mutants, key=is_cpp)
    all_tests = sorted({t for m in mutants for t in m["tests"]})
    log(f"baseline: {len(all_tests)} test selections on the unmutated tree")
    status, failing, secs = run_tests(tree, workdir, args.python, all_tests, args.timeout * 2)
    if status != "passed":
        raise SystemExit(f"baseline {status} ({secs:.0f} s): {failing}")
    log(f"baseline passed ({secs:.0f} s)")

    results = []
    for m in mutants:
        original = apply(tree, m)
        build_s = 0.0
        try:
            if is_cpp(m):
                ok, tail, build_s = build_module(tree, build, args.jobs)
                if not ok:
                    results.append(dict(id=m["id"], file=m["file"], outcome="does not compile", by=[], caught=False,
                                        by_property=False, build_s=build_s, test_s=0.0, detail=tail))
                    log(f"{m['id']}: does not compile")
                    continue
            status, failing, secs = run_tests(tree, workdir, args.python, m["tests"], args.timeout)
        finally:
            (tree / m["file"]).write_text(original)
        caught = status in ("failed", "error", "timeout")
        by_property = status == "failed" and any(c in f for f in failing for c in m["catch"])
        outcome = {"passed": "SURVIVED", "failed": "caught", "error": "caught (error)",
                   "timeout": "caught (timeout)"}[status]
        results.append(dict(id=m["id"], file=m["file"], outcome=outcome, by=failing if status == "failed" else [],
                            caught=caught, by_property=by_property, build_s=build_s, test_s=secs,
                            detail=failing[0] if status == "error" else ""))
        log(f"{m['id']}: {outcome}{' by its property' if by_property else ''} "
            f"({build_s:.0f} s build, {secs:.0f} s tests)")
    if any(is_cpp(m) for m in mutants):
        ok, tail, _ = build_module(tree, build, args.jobs)   # leave the copy's module unmutated
        if not ok:
            log(f"warning: the unmutated rebuild failed: {tail}")

    commit_file = tree / ".mutants-commit"
    commit = commit_file.read_text().strip() if commit_file.exists() else "unknown"
    caught = sum(r["caught"] for r in results)
    by_prop = sum(r["by_property"] for r in results)
    print(f"\nMutation score at {commit} (tests from the working tree): {caught}/{len(results)} caught, "
          f"{by_prop}/{len(results)} by a test of the property they break\n")
    print("| mutant | file | outcome | caught by |")
    print("|---|---|---|---|")
    for r in results:
        names = sorted({re.sub(r"\[.*\]$", "", f.split("::")[-1]) for f in r["by"]})
        shown = ", ".join(names[:4]) + (f" (+{len(names) - 4})" if len(names) > 4 else "")
        flag = "" if r["by_property"] or not r["caught"] else " (not by its property)"
        print(f"| {r['id']} | {r['file']} | {r['outcome']}{flag} | {shown} |")
    report = workdir / "mutants-report.json"
    report.write_text(json.dumps({"ref": args.ref, "commit": commit, "results": results}, indent=1))
    print(f"\n(JSON: {report})")
    return 0 if by_prop == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
