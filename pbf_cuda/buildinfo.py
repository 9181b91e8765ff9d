"""Is the compiled module built from the sources on disk?

CMakeLists.txt hashes ``pbf_cuda/csrc`` when it configures the build and embeds the hash in
``pbf_cuda._core`` (``source_hash()``).  :func:`csrc_hash` computes the same hash from the files on
disk; :func:`check_core` refuses a module built from other sources, so a stale build never runs (and
never has its results cached under the new sources' code version).
"""
from __future__ import annotations

import functools
import hashlib
from pathlib import Path

__all__ = ["CSRC", "csrc_hash", "check_core", "StaleBuildError", "REBUILD_HINT"]

CSRC = Path(__file__).resolve().parent / "csrc"
REBUILD_HINT = "rebuild it: scripts/setup.sh (or pip install -e . in the virtual environment)"


class StaleBuildError(ImportError):
    """pbf_cuda._core was compiled from sources that differ from pbf_cuda/csrc."""


def csrc_hash(directory: Path = CSRC) -> str | None:
    """sha256 (hex) of the lines '<name> <sha256 of the file>\\n' of the files in csrc, sorted by name
    (the hash CMakeLists.txt computes); None where the sources are not present (an installed wheel)."""
    if not directory.is_dir():
        return None
    lines = "".join(f"{p.name} {hashlib.sha256(p.read_bytes()).hexdigest()}\n"
                    for p in sorted(directory.iterdir(), key=lambda p: p.name) if p.is_file())
    return hashlib.sha256(lines.encode()).hexdigest()


def check_core(core, expected: str | None = None) -> None:
    """Raise StaleBuildError when `core` was not built from the csrc sources on disk."""
    expected = csrc_hash() if expected is None else expected
    if expected is None:
        return
    built = core.source_hash() if hasattr(core, "source_hash") else "unknown (a build without source_hash)"
    if built != expected:
        raise StaleBuildError(f"pbf_cuda._core was built from other sources than pbf_cuda/csrc (built from "
                              f"{built[:16]}, sources on disk {expected[:16]}); {REBUILD_HINT}")


@functools.lru_cache(maxsize=None)
def checked_core():
    """pbf_cuda._core, once checked against the sources on disk."""
    from . import _core as core
    check_core(core)
    return core
