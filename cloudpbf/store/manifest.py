"""Verification of a finished run (result.json's checksum and the manifest of its files) and the
quarantine that keeps whatever fails it (``ROOT/quarantine/``, logged) while the run is computed again.

Every read here goes through cloudpbf.store.safe: links are never followed, only regular files are read, and
a manifest's byte count bounds the read of its file (a device or FIFO in place of a snapshot cannot hang
the reader).  The quarantine keeps the newest :data:`QUARANTINE_KEEP` folders (``$CLOUDPBF_QUARANTINE_KEEP``)
and removes older ones; ``cloudpbf runs`` lists them and ``cloudpbf runs prune`` removes them."""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Iterable

from cloudpbf.store.safe import (StoreError, UnsafeFileError, append_line, entry_kind, read_json, sha256_file,
                              store_error)
from cloudpbf_io.files import fsync_dir, is_temp, json_default

__all__ = ["QUARANTINE", "QUARANTINE_KEEP", "manifest", "info_checksum", "verify_run", "quarantine",
           "quarantine_entry", "quarantine_folders", "prune_quarantine", "finished_files", "now", "read_result",
           "MAX_RESULT_BYTES"]

QUARANTINE = "quarantine"    # ROOT/quarantine/: run files that failed verification, kept for inspection
MAX_RESULT_BYTES = 16 << 20  # result.json (its manifest lists a few dozen files)
log = logging.getLogger("cloudpbf.runs")


def _keep() -> int:
    try:
        return max(1, int(os.environ.get("CLOUDPBF_QUARANTINE_KEEP", "20")))
    except ValueError:
        return 20


QUARANTINE_KEEP = _keep()    # quarantine folders kept (the newest); older ones are removed


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


# Files of a finished run that the manifest in result.json covers (all but the log, the lock and what
# only an unfinished attempt reads: progress.json, partial/).
_UNVERIFIED = {"log.txt", ".lock", "result.json", "progress.json"}


def manifest(directory: Path) -> dict:
    """{relative path: {"bytes": n, "sha256": hex}} of the run's files."""
    out = {}
    for p in sorted(directory.rglob("*")):
        rel = p.relative_to(directory).as_posix()
        if (entry_kind(p) != "file" or rel in _UNVERIFIED or rel.startswith(("partial/", "export/"))
                or is_temp(p)):
            continue
        out[rel] = {"bytes": os.lstat(p).st_size, "sha256": sha256_file(p)}
    return out


def read_result(directory: Path) -> dict:
    """result.json of a run directory, bounded (cloudpbf.store.safe.read_json); FileNotFoundError, ValueError."""
    return read_json(Path(directory) / "result.json", limit=MAX_RESULT_BYTES)


def info_checksum(info: dict) -> str:
    body = {k: v for k, v in info.items() if k != "checksum"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=json_default).encode()).hexdigest()


_VERIFIED: dict = {}     # result.json (path, mtime_ns, size) -> True: verified once in this process


def verify_run(directory: str | Path, key: str | None = None, memo: bool = True) -> list[str]:
    """Problems of a finished run directory (empty: it may be served). Checks result.json (JSON, its own
    checksum, the run key) and every file of its manifest (present, size, sha256).  With `memo`, a run
    verified before in this process (result.json unchanged) is not read again."""
    directory = Path(directory)
    path = directory / "result.json"
    try:
        st = os.lstat(path)
        seen = (str(path), st.st_mtime_ns, st.st_size, st.st_ino, key)
        if memo and seen in _VERIFIED:
            return []
        info = read_result(directory)
    except (FileNotFoundError, NotADirectoryError):
        return ["result.json is missing"]
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return [f"result.json is unreadable ({type(exc).__name__}: {str(exc)[:80]})"]
    if not isinstance(info, dict) or not isinstance(info.get("manifest"), dict):
        return ["result.json has no manifest (written by an older harness, or damaged)"]
    if info.get("checksum") != info_checksum(info):
        return ["result.json does not match its checksum"]
    if key is not None and info.get("key") != key:
        return [f"result.json belongs to run {str(info.get('key'))[:16]}, not {key[:16]}"]
    problems = []
    for rel, entry in info["manifest"].items():
        p = directory / rel
        if (not isinstance(entry, dict) or ".." in Path(rel).parts or Path(rel).is_absolute()
                or not isinstance(entry.get("bytes"), int) or isinstance(entry.get("bytes"), bool)
                or entry["bytes"] < 0):
            problems.append(f"manifest entry {rel[:80]!r} is malformed")
            continue
        parent = directory
        kinds = []
        for part in Path(rel).parts:            # no link or odd file anywhere on the way
            parent = parent / part
            kinds.append(entry_kind(parent))
        if kinds[-1] is None or any(k != "dir" for k in kinds[:-1]):
            problems.append(f"{rel} is missing")
            continue
        if kinds[-1] != "file":
            problems.append(f"{rel} is a {kinds[-1]}, not a regular file (not followed)")
            continue
        try:
            size = os.lstat(p).st_size
            if size != entry["bytes"]:
                problems.append(f"{rel} has {size} bytes, the manifest says {entry['bytes']}")
            elif sha256_file(p, limit=entry["bytes"]) != entry.get("sha256"):
                problems.append(f"{rel} does not match its sha256")
        except (OSError, UnsafeFileError) as exc:
            problems.append(f"{rel} is unreadable ({getattr(exc, 'strerror', None) or exc})")
    if not problems:
        _VERIFIED[seen] = True
    return problems


def _quarantine_root(root: Path) -> Path:
    """ROOT/quarantine, made when missing; StoreError when something else than a folder is there."""
    folder = root / QUARANTINE
    kind = entry_kind(folder)
    if kind is None:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise (store_error(exc, folder) or exc) from None
        kind = entry_kind(folder)
    if kind != "dir":
        raise StoreError(f"{folder}: is a {kind}, not a folder; the run cache keeps damaged runs there "
                         "(move it away)")
    return folder


def _move_aside(root: Path, label: str, moves: list[tuple[Path, str]]) -> Path:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    target = _quarantine_root(root) / f"{label}-{stamp}-{os.getpid()}-{os.urandom(3).hex()}"
    try:
        target.mkdir()
        for src, name in moves:
            dest = target / name
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dest)
    except OSError as exc:
        raise (store_error(exc, src if moves else target) or exc) from None
    fsync_dir(target)
    prune_quarantine(root, keep=QUARANTINE_KEEP)
    return target


def quarantine(directory: Path, names: Iterable[str], reason: str) -> Path | None:
    """Move the named files/folders of a run directory aside to ROOT/quarantine/<dir>-<time>/ (kept for
    inspection; the newest QUARANTINE_KEEP folders are kept) and log why.  Links and odd files are moved as
    they are (never followed).  Returns the quarantine folder (None: nothing to move).  StoreError when
    the cache cannot be written."""
    present = [n for n in names if entry_kind(directory / n) is not None]
    if not present:
        return None
    target = _move_aside(directory.parent, directory.name, [(directory / n, n) for n in present])
    fsync_dir(directory)
    message = f"quarantined {', '.join(present)} of {directory.name} to {target} ({reason}); recomputing"
    append_line(directory / "log.txt", f"{now()} {message}")
    log.warning(message)
    return target


def quarantine_entry(path: Path, reason: str) -> Path:
    """Move one entry (a file, link or folder standing where a run directory or one of its files belongs)
    to ROOT/quarantine/<name>-<time>/, where ROOT is its folder; logged.  Returns the quarantine folder."""
    target = _move_aside(path.parent, path.name, [(path, path.name)])
    log.warning(f"quarantined {path} to {target} ({reason})")
    return target


def quarantine_folders(root: Path) -> list[Path]:
    """The folders of ROOT/quarantine, newest first (by modification time)."""
    folder = Path(root) / QUARANTINE
    if entry_kind(folder) != "dir":
        return []
    entries = []
    for p in folder.iterdir():
        try:
            entries.append((os.lstat(p).st_mtime, p.name, p))
        except FileNotFoundError:
            continue
    return [p for _, _, p in sorted(entries, reverse=True)]


def remove_entry(path: Path) -> None:
    """Remove a file, link or folder tree (links inside are removed, never followed)."""
    if entry_kind(path) == "dir":
        shutil.rmtree(path)
    else:
        os.unlink(path)


def prune_quarantine(root: Path, keep: int) -> list[Path]:
    """Remove all but the newest `keep` quarantine folders; returns those removed."""
    removed = []
    for p in quarantine_folders(root)[keep:]:
        try:
            remove_entry(p)
            removed.append(p)
        except FileNotFoundError:
            continue
        except OSError as exc:
            log.warning(f"could not remove {p} from the quarantine: {exc}")
    if removed:
        log.info(f"removed {len(removed)} old quarantine folder(s) of {root}")
    return removed


def finished_files(directory: Path) -> list[str]:
    """Everything in a run directory but its log, its lock and the user's exports (what a failed verification
    moves aside)."""
    return sorted(p.name for p in directory.iterdir() if p.name not in ("log.txt", ".lock", "export"))
