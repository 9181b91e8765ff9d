"""One writer per run directory: an exclusive lock, portable (filelock), POSIX flock where it is missing."""
from __future__ import annotations

import contextlib
from pathlib import Path

from cloudpbf.store.manifest import quarantine
from cloudpbf.store.safe import entry_kind

__all__ = ["locked"]


@contextlib.contextmanager
def locked(directory: Path):
    """Exclusive lock on the run directory, so two processes never run the same spec at once.  A `.lock` that
    is not a regular file (a folder, a link) is moved to the quarantine first, never followed."""
    kind = entry_kind(directory / ".lock")
    if kind not in (None, "file"):
        quarantine(directory, [".lock"], f".lock is a {kind}, not a lock file")
    try:
        from filelock import FileLock  # portable: fcntl on POSIX, msvcrt on Windows (the harness extra)
    except ImportError:                # a bare POSIX machine without it (e.g. a GPU node): plain flock
        import fcntl  # POSIX flock: the fallback without the harness extra (filelock)
        with open(directory / ".lock", "a+") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)
        return
    with FileLock(str(directory / ".lock")):
        yield
