"""Reading back what the run store wrote without trusting it, and the one error the store cannot mend.

Every file of a run directory may have been changed by someone else: replaced by a link (to another
file, to a device that never ends, to a folder), by a folder, by a huge or deeply nested JSON file.  The
readers here never follow links (``O_NOFOLLOW``, ``lstat``), read regular files only (``S_ISREG`` on
the open descriptor, so a link swapped in between the check and the read is refused too), open without
blocking (a FIFO does not hang the reader) and read at most a given number of bytes.  A file that fails
raises :class:`UnsafeFileError` (a ValueError: the callers treat it as damage and quarantine it).

:class:`StoreError` is what cannot be mended by recomputing: a read-only or full cache, a cache folder
that is a file.  Its message is one line naming the path; the CLI turns it into exit code 2.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import stat
from pathlib import Path

import numpy as np

__all__ = ["StoreError", "UnsafeFileError", "MAX_JSON_BYTES", "MAX_JSON_DEPTH", "read_bytes", "read_json",
           "sha256_file", "entry_kind", "append_line", "store_error", "WRITE_ERRNOS"]

MAX_JSON_BYTES = 256 << 20     # no JSON file of a run is larger (bytes); partial/ rows of long runs stay far below
MAX_JSON_DEPTH = 64            # nesting levels of a JSON file of the store (it writes at most 4)
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
# errno values of a write the store cannot do here (not damage: recomputing would fail the same way)
WRITE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EPERM, getattr(errno, "EDQUOT", errno.ENOSPC),
                errno.EFBIG, errno.ENOTDIR}


class StoreError(RuntimeError):
    """The run store cannot be used as asked (read-only, full, a folder that is a file). One line, naming the
    path; the CLI exits with code 2."""


class UnsafeFileError(ValueError):
    """A file of the store is not a regular file (a link, a folder, a device), or larger than allowed."""


def entry_kind(path: str | Path) -> str | None:
    """'file', 'dir', 'link' or 'other' (device, FIFO, socket) of `path` itself (links not followed);
    None when nothing is there."""
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    if stat.S_ISLNK(mode):
        return "link"
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "dir"
    return "other"


def _open_regular(path: str | Path) -> tuple[int, os.stat_result]:
    """An open read-only descriptor of a regular file (links refused, never blocking) and its fstat."""
    try:
        fd = os.open(path, os.O_RDONLY | _NOFOLLOW | _NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UnsafeFileError(f"{Path(path).name} is a link (links are not followed)") from None
        raise
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        what = "a folder" if stat.S_ISDIR(st.st_mode) else "a device, FIFO or socket"
        raise UnsafeFileError(f"{Path(path).name} is {what}, not a regular file")
    return fd, st


def read_bytes(path: str | Path, limit: int) -> bytes:
    """The bytes of the regular file `path`, at most `limit` of them (UnsafeFileError when it holds more, is a
    link or not a regular file; FileNotFoundError when missing)."""
    fd, st = _open_regular(path)
    try:
        if st.st_size > limit:
            raise UnsafeFileError(f"{Path(path).name} has {st.st_size:,} bytes, more than the {limit:,} allowed")
        chunks, total = [], 0
        while total <= limit:
            block = os.read(fd, min(1 << 20, limit + 1 - total))
            if not block:
                break
            chunks.append(block)
            total += len(block)
        if total > limit:
            raise UnsafeFileError(f"{Path(path).name} grew beyond the {limit:,} bytes allowed")
        return b"".join(chunks)
    finally:
        os.close(fd)


_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


def json_depth(raw: bytes) -> int:
    """The deepest nesting of [ and { in a JSON text (strings left out)."""
    data = np.frombuffer(_STRING.sub(b'""', raw), dtype=np.uint8)
    if data.size == 0:
        return 0
    step = ((data == ord("[")) | (data == ord("{"))).astype(np.int64) - ((data == ord("]")) | (data == ord("}")))
    return int(np.cumsum(step).max(initial=0))


def read_json(path: str | Path, limit: int = MAX_JSON_BYTES, depth: int = MAX_JSON_DEPTH):
    """A JSON file of the store, bounded: at most `limit` bytes and `depth` nesting levels, UTF-8, a regular
    file (links never followed).  Raises FileNotFoundError when missing, ValueError (UnsafeFileError or
    json's) when it fails a bound or does not parse."""
    raw = read_bytes(path, limit)
    deepest = json_depth(raw)
    if deepest > depth:
        raise UnsafeFileError(f"{Path(path).name} nests {deepest} levels deep, more than the {depth} allowed")
    try:
        return json.loads(raw.decode("utf-8"))
    except RecursionError:                      # a bound the scan above missed: still one clear error
        raise UnsafeFileError(f"{Path(path).name} nests too deeply") from None


def sha256_file(path: str | Path, limit: int | None = None) -> str:
    """sha256 (hex) of a regular file (links refused, UnsafeFileError), reading at most `limit` bytes (a
    file that holds more fails with UnsafeFileError: a manifest's byte count bounds every read)."""
    fd, st = _open_regular(path)
    try:
        if limit is not None and st.st_size > limit:
            raise UnsafeFileError(f"{Path(path).name} has {st.st_size:,} bytes, more than the {limit:,} expected")
        digest, total = hashlib.sha256(), 0
        cap = limit if limit is not None else None
        while True:
            want = 1 << 20 if cap is None else min(1 << 20, cap + 1 - total)
            if want <= 0:
                raise UnsafeFileError(f"{Path(path).name} holds more than the {cap:,} bytes expected")
            block = os.read(fd, want)
            if not block:
                break
            digest.update(block)
            total += len(block)
        return digest.hexdigest()
    finally:
        os.close(fd)


def append_line(path: str | Path, line: str) -> bool:
    """Append `line` (and a newline) to a log file, never through a link (False when it could not)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW | _NONBLOCK, 0o666)
    except OSError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        os.write(fd, (line + "\n").encode())
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def store_error(exc: OSError, where: str | Path) -> StoreError | None:
    """A StoreError naming `where` for a write the store cannot do (full, read-only, no permission); None
    for other errors."""
    if not isinstance(exc, OSError) or exc.errno not in WRITE_ERRNOS:
        return None
    why = {errno.ENOSPC: "the disk is full", errno.EROFS: "the file system is read-only",
           getattr(errno, "EDQUOT", errno.ENOSPC): "the disk quota is used up",
           errno.EFBIG: "the file is too large for the file system",
           errno.ENOTDIR: "a folder on the way is a file"}.get(exc.errno, "no permission to write")
    return StoreError(f"{where}: cannot write ({why}: {exc.strerror or exc})")
