"""Shared test set-up: the repo root on sys.path; `gpu` tests skipped where no CUDA device exists."""
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _cuda_available() -> bool:
    try:
        from pbf_cuda import available_backends
        return "cuda" in available_backends()
    except Exception:
        return False


# The longest tests go first: with pytest-xdist (scripts/test.sh runs one worker per core) a worker that
# starts the smoke demo last would finish minutes after the others.
LONGEST_FIRST = ("test_harness_demo.py", "test_atmosphere_energy.py")


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: next((i for i, name in enumerate(LONGEST_FIRST) if item.nodeid.startswith(f"tests/{name}")),
                                     len(LONGEST_FIRST)))
    if _cuda_available():
        return
    skip = pytest.mark.skip(reason="no CUDA device (gpu tests run on the device machine)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)
