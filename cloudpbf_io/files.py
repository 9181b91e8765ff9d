"""Atomic file writes: the one helper every writer of the project uses (run cache, checkpoints,
snapshots, study outputs, the report).

A file is written to a temporary name in its own folder (``.NAME.PID.RANDOM.tmp``, created with mode
``FILE_MODE`` less the umask, so shared caches and reports stay readable), flushed and fsynced, moved
over the final name with ``os.replace``, and the folder is fsynced, so after a crash (or kill -9, or
a power cut) a reader finds the old file or the new one, never a partial one.  Temporary files left by
an interrupted writer are removed by :func:`remove_stale_temps`.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import time
import uuid
from pathlib import Path

import numpy as np

__all__ = ["FILE_MODE", "atomic_path", "atomic_write_bytes", "atomic_write_text", "atomic_write_json", "json_default",
           "atomic_savez", "read_meta",
           "fsync_dir", "remove_stale_temps", "is_temp"]

FILE_MODE = 0o666          # less the umask: the mode of every file this project writes
_TEMP = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{12}\.tmp(\.[A-Za-z0-9]+)?$")


def fsync_dir(directory: str | Path) -> None:
    """fsync a folder, so a rename inside it survives a crash (best effort where unsupported)."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path, keep_suffix: bool = False):
    """Yield a temporary path beside `path`; write it, and on success it replaces `path`
    (fsync of the file, os.replace, fsync of the folder).  On failure the temporary file is removed.
    keep_suffix: the temporary name ends in `path`'s suffix too (for writers that pick the format from it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp{path.suffix if keep_suffix else ''}"
    os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, FILE_MODE))
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def json_default(value):
    """numpy scalars and arrays and paths as JSON."""
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def atomic_write_json(path: str | Path, obj, sort_keys: bool = True) -> Path:
    """`obj` as indented JSON (numpy scalars and arrays, paths allowed), atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=sort_keys, default=json_default) + "\n")


def atomic_savez(path: str | Path, meta: dict, **arrays) -> Path:
    """Write arrays and a JSON `meta` record (stored as bytes under 'meta') to an npz, atomically."""
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return Path(path)


def read_meta(npz) -> dict:
    """The JSON record written by atomic_savez."""
    return json.loads(bytes(npz["meta"]).decode())


def is_temp(path: Path) -> bool:
    """A temporary file of atomic_path."""
    return bool(_TEMP.match(path.name))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def remove_stale_temps(directory: str | Path, recursive: bool = True, min_age_s: float = 3600.0,
                       owned: bool = False) -> list[Path]:
    """Remove temporary files of atomic_path that no writer will finish: those whose writing process
    is gone (same machine) and those older than `min_age_s`; with `owned` (the caller holds the
    folder's lock, so nobody writes in it) every one.  Returns the removed paths."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    removed = []
    now = time.time()
    for p in (directory.rglob(".*.tmp*") if recursive else directory.glob(".*.tmp*")):
        m = _TEMP.match(p.name)
        if not m or not p.is_file():
            continue
        try:
            old = now - p.stat().st_mtime > min_age_s
        except FileNotFoundError:
            continue
        if owned or old or not _alive(int(m.group(1))):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(p)
    return removed
