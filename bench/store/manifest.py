"""Verification of a finished run (result.json's checksum and the manifest of its files) and the
quarantine that keeps whatever fails it (``ROOT/quarantine/``, logged) while the run is computed again."""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Iterable

from bench.store.files import sha256_file
from pbf_cuda.files import fsync_dir, is_temp, json_default

__all__ = ["QUARANTINE", "manifest", "info_checksum", "verify_run", "quarantine", "finished_files", "now"]

QUARANTINE = "quarantine"    # ROOT/quarantine/: run files that failed verification, kept for inspection
log = logging.getLogger("bench.runs")


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
        if not p.is_file() or rel in _UNVERIFIED or rel.startswith("partial/") or is_temp(p):
            continue
        out[rel] = {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
    return out


def info_checksum(info: dict) -> str:
    body = {k: v for k, v in info.items() if k != "checksum"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=json_default).encode()).hexdigest()


_VERIFIED: dict = {}     # result.json (path, mtime_ns, size) -> True: verified once in this process


def verify_run(directory: str | Path, key: str | None = None) -> list[str]:
    """Problems of a finished run directory (empty: it may be served). Checks result.json (JSON, its own
    checksum, the run key) and every file of its manifest (present, size, sha256)."""
    directory = Path(directory)
    path = directory / "result.json"
    try:
        st = path.stat()
        memo = (str(path), st.st_mtime_ns, st.st_size, key)
        if memo in _VERIFIED:
            return []
        info = json.loads(path.read_text())
    except FileNotFoundError:
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
        if not isinstance(entry, dict) or ".." in Path(rel).parts or Path(rel).is_absolute():
            problems.append(f"manifest entry {rel[:80]!r} is malformed")
            continue
        try:
            size = p.stat().st_size
        except (FileNotFoundError, NotADirectoryError):
            problems.append(f"{rel} is missing")
            continue
        except OSError as exc:
            problems.append(f"{rel} is unreadable ({exc.strerror or exc})")
            continue
        if size != entry.get("bytes"):
            problems.append(f"{rel} has {size} bytes, the manifest says {entry.get('bytes')}")
            continue
        try:
            if sha256_file(p) != entry.get("sha256"):
                problems.append(f"{rel} does not match its sha256")
        except OSError as exc:
            problems.append(f"{rel} is unreadable ({exc.strerror or exc})")
    if not problems:
        _VERIFIED[memo] = True
    return problems


def quarantine(directory: Path, names: Iterable[str], reason: str) -> Path | None:
    """Move the named files/folders of a run directory aside to ROOT/quarantine/<dir>-<time>/ (kept for
    inspection, never deleted) and log why.  Returns the quarantine folder (None: nothing to move)."""
    present = [n for n in names if (directory / n).exists()]
    if not present:
        return None
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    target = directory.parent / QUARANTINE / f"{directory.name}-{stamp}-{os.getpid()}-{os.urandom(3).hex()}"
    target.mkdir(parents=True, exist_ok=True)
    for name in present:
        dest = target / name
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(directory / name, dest)
    fsync_dir(directory)
    fsync_dir(target)
    message = f"quarantined {', '.join(present)} of {directory.name} to {target} ({reason}); recomputing"
    with open(directory / "log.txt", "a") as fh:
        fh.write(f"{now()} {message}\n")
    log.warning(message)
    return target


def finished_files(directory: Path) -> list[str]:
    """Everything in a run directory but its log and lock (what a failed verification moves aside)."""
    return sorted(p.name for p in directory.iterdir() if p.name not in ("log.txt", ".lock"))
