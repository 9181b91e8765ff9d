"""The scripts in benchmarks/ import against today's packages: a module they name that moved or a name it
no longer exports fails here, not on the GPU machine the script was carried to."""
import importlib.util
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(BENCHMARKS.glob("*.py"))


def test_there_are_scripts_to_check():
    assert len(SCRIPTS) >= 5


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_script_imports_and_runs_only_as_main(path, monkeypatch):
    assert 'if __name__ == "__main__"' in path.read_text(), f"{path.name}: work at import time"
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(f"benchmark_script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)   # top-level imports and definitions only: each runs under __main__
    finally:
        sys.modules.pop(spec.name, None)
