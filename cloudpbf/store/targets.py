"""Where an export goes, and how it gets there without destroying anything: cloudpbf.export's file handling.

An export is one *target*: a file (NetCDF) or a folder (zarr store, VTK series, .bgeo frames).  It is
built under a temporary name beside the target (``.NAME.PID.RANDOM.export-tmp``) and moved into place
with one rename, so a reader sees no target or the whole one, and a failure (full disk, read-only folder,
an interrupted process) leaves the folder as it was: the temporary copy is removed.  An existing target
is only ever replaced when it is an earlier export of the same run (its marker says so) and the caller
asks (``force``); the replacement is one rename too (a folder is exchanged with renameat2 where the
system has it, else moved aside, replaced and removed).
"""
from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import re
import shutil
import uuid
from pathlib import Path

from cloudpbf.store.safe import UnsafeFileError, entry_kind, read_json
from cloudpbf_io.files import atomic_write_json, fsync_dir

__all__ = ["ExportError", "MARKER", "marker_of", "staged", "disk_error", "check_free_space", "foreign_entries"]

MARKER = ".cloudpbf-export.json"     # in a folder target: which run and format it holds, and its files
MAX_MARKER_BYTES = 16 << 20
_STAGE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[0-9a-f]{12}\.export-(?:tmp|old)$")
NETCDF_ATTR = "cloudpbf_export"      # in a NetCDF target: the same record, as a global attribute (JSON)


class ExportError(RuntimeError):
    """An export that cannot be written as asked (the target exists, the disk is full or read-only, the run
    is unfinished or damaged, it needs more memory than there is). One line naming the path or option."""


def disk_error(exc: OSError, where: Path) -> ExportError:
    reason = {errno.ENOSPC: "the disk is full", errno.EROFS: "the file system is read-only",
              errno.EACCES: "no permission to write", errno.EPERM: "no permission to write",
              getattr(errno, "EDQUOT", errno.ENOSPC): "the disk quota is used up"}.get(
        exc.errno, exc.strerror or type(exc).__name__)
    return ExportError(f"{where}: cannot write ({reason}); nothing was written")


def check_free_space(folder: Path, need: int) -> None:
    """ExportError when the file system of `folder` has less than `need` bytes free."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < need:
        raise ExportError(f"{folder}: the export needs about {_size(need)}, the disk has {_size(free)} free; "
                          "nothing was written")


def _size(n: float) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{int(n)} bytes"


def marker_of(target: Path) -> dict | None:
    """The export record of an existing target ({"run", "key", "format"}), None when it holds none (it was
    not written by an export, or is unreadable).  Links are never followed."""
    kind = entry_kind(target)
    try:
        if kind == "dir":
            if entry_kind(target / MARKER) != "file":
                return None
            record = read_json(target / MARKER, limit=MAX_MARKER_BYTES)
        elif kind == "file":
            record = _netcdf_marker(target)
        else:
            return None
    except (OSError, ValueError, UnsafeFileError):
        return None
    return record if isinstance(record, dict) else None


def _netcdf_marker(path: Path) -> dict | None:
    with open(path, "rb") as fh:                       # an HDF5 file (NetCDF-4) starts with this signature
        if fh.read(8) != b"\x89HDF\r\n\x1a\n":
            return None
    import h5py  # io extra (h5py)
    with h5py.File(path, "r") as f:
        raw = f.attrs.get(NETCDF_ATTR)
    if raw is None:
        return None
    raw = raw.decode() if isinstance(raw, bytes) else str(raw)
    return json.loads(raw) if len(raw) < 1 << 16 else None


def _files(folder: Path) -> list[str]:
    """Every entry under `folder` (relative paths; links and odd files listed, never followed)."""
    out = []
    for base, dirs, files in os.walk(folder, followlinks=False):
        rel = Path(base).relative_to(folder)
        out.extend((rel / n).as_posix() for n in dirs + files)
    return sorted(out)


def foreign_entries(target: Path, marker: dict) -> list[str]:
    """Entries of a folder export that its marker does not list (files someone else put there)."""
    if entry_kind(target) != "dir":
        return []
    listed = set(marker.get("files") or []) | {MARKER}
    return [rel for rel in _files(target) if rel not in listed]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def remove_stale_stages(target: Path) -> None:
    """Temporary copies of `target` left by an export that was killed (its process is gone)."""
    try:
        entries = list(target.parent.iterdir())
    except OSError:
        return
    for p in entries:
        m = _STAGE.match(p.name)
        if m and m.group("name") == target.name and int(m.group("pid")) != os.getpid() \
                and not _alive(int(m.group("pid"))):
            _remove(p)


def _renameat2(src: Path, dst: Path, flags: int) -> bool:
    """Linux renameat2 (1: RENAME_NOREPLACE, 2: RENAME_EXCHANGE); False where the system lacks it."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        call = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    if call(at_fdcwd, os.fsencode(src), at_fdcwd, os.fsencode(dst), flags) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP if hasattr(errno, "ENOTSUP") else errno.EINVAL):
        return False
    raise OSError(code, os.strerror(code), str(dst))


def _remove(path: Path) -> None:
    kind = entry_kind(path)
    if kind == "dir":
        shutil.rmtree(path, ignore_errors=True)
    elif kind is not None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)


def _move_into_place(stage: Path, target: Path, replace: bool) -> None:
    if not replace:
        if _renameat2(stage, target, 1):               # RENAME_NOREPLACE: never over something new
            return
        if entry_kind(target) is not None:
            raise ExportError(f"{target}: appeared while the export was written; nothing was replaced")
        os.rename(stage, target)
        return
    if entry_kind(stage) == "file":
        os.replace(stage, target)                     # a file replaces a file in one step
        return
    if _renameat2(stage, target, 2):                   # RENAME_EXCHANGE: the old folder is now at `stage`
        _remove(stage)
        return
    aside = target.with_name(f".{target.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.export-old")
    os.rename(target, aside)
    try:
        os.rename(stage, target)
    except BaseException:
        os.rename(aside, target)
        raise
    _remove(aside)


@contextlib.contextmanager
def staged(target: Path, record: dict, folder: bool, replace: bool):
    """Yield a temporary path beside `target` to write the export into (a folder when `folder`, made here;
    else a file name); on success the record is added (a marker file in a folder; a NetCDF file carries it
    itself) and the stage moved over `target`.  On any failure the stage is removed; an OSError becomes an
    ExportError naming `target`.  Stages of this target left by killed exports are removed first."""
    remove_stale_stages(target)
    stage = target.parent / f".{target.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.export-tmp"
    try:
        if folder:
            stage.mkdir()
        yield stage
        if folder:
            atomic_write_json(stage / MARKER, {**record, "files": _files(stage)})
        fsync_dir(stage if folder else target.parent)
        _move_into_place(stage, target, replace)
        fsync_dir(target.parent)
    except OSError as exc:
        _remove(stage)
        raise disk_error(exc, target) from None
    except BaseException:
        _remove(stage)
        raise
