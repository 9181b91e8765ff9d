"""The runs a cache holds, as ``cloudpbf runs`` shows them: listing, finding one by a prefix, pruning.

A run is found by its folder path, or by a prefix of its folder name (``particles-growing-3f2a``) or of
its key (the sha256 the folder name ends in; ``3f2a9c``).  A prefix that fits several runs is refused
with the candidates listed (:class:`RunLookupError`).  Everything here reads through cloudpbf.store.safe
(bounded, links never followed); nothing is verified in full (``cloudpbf runs show`` does that).
"""
from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

from cloudpbf.store.identity import effective_seed
from cloudpbf.store.manifest import QUARANTINE, quarantine_folders, read_result, remove_entry
from cloudpbf.store.safe import entry_kind, read_json

__all__ = ["RunEntry", "RunLookupError", "list_runs", "find_run", "folder_bytes", "run_entry", "prune_runs"]

RUN_NAME = re.compile(r"^(particles|grid)-(.+)-([0-9a-f]{16})$")
MAX_CONFIG_BYTES = 16 << 20


class RunLookupError(LookupError):
    """No run, or several, fit what was given. One line (the candidates listed when several)."""


@dataclass
class RunEntry:
    """One run folder of a cache, as listed.  status: 'stable', 'unstable', 'unfinished' (no result.json;
    `step` is its last checkpoint's) or 'damaged' (config.json or result.json unreadable)."""
    path: Path
    key: str
    solver: str
    scene: str
    backend: str
    seed: int | None
    steps: int | None           # steps requested
    step: int | None            # steps done (finished runs), the last checkpoint's step (unfinished ones)
    status: str
    modified: float             # s since the epoch (the folder's newest entry)
    bytes: int
    result: dict | None = None
    identity: dict | None = None

    @property
    def age_s(self) -> float:
        return max(0.0, time.time() - self.modified)


def folder_bytes(path: Path) -> int:
    """Bytes of the regular files under `path` (links not followed)."""
    total = 0
    for base, dirs, files in os.walk(path, followlinks=False):
        for name in files:
            try:
                st = os.lstat(os.path.join(base, name))
            except OSError:
                continue
            total += st.st_size
    return total


def _newest(path: Path) -> float:
    newest = 0.0
    try:
        with os.scandir(path) as it:
            for e in it:
                try:
                    newest = max(newest, e.stat(follow_symlinks=False).st_mtime)
                except OSError:
                    continue
        newest = max(newest, os.lstat(path).st_mtime)
    except OSError:
        pass
    return newest


def run_entry(path: Path) -> RunEntry:
    """What a run folder holds (read, not verified)."""
    m = RUN_NAME.match(path.name)
    solver, scene, key = (m.group(1), m.group(2), m.group(3)) if m else ("?", "?", "")
    identity, result, status, step = None, None, "damaged", None
    try:
        config = read_json(path / "config.json", limit=MAX_CONFIG_BYTES)
        identity = config["identity"]
        key = config.get("key", key) if isinstance(config.get("key"), str) else key
        solver = str(identity.get("solver", solver))
        scene = str(((identity.get("scene") or {}).get("scene") or {}).get("name", scene))
        status = "unfinished"
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    if entry_kind(path / "result.json") is not None:
        try:
            result = read_result(path)
            status = "stable" if result.get("stable") else "unstable"
            step = result.get("step")
        except (OSError, ValueError, AttributeError):
            status = "damaged"
    elif identity is not None:
        try:
            step = read_json(path / "progress.json", limit=1 << 24).get("step")
        except (OSError, ValueError, AttributeError):
            step = 0
    seed = None
    if isinstance(identity, dict):
        seed = effective_seed(identity)
        seed = None if seed < 0 else seed
    backend = str((result or {}).get("backend") or (identity or {}).get("backend") or "?")
    steps = (identity or {}).get("steps")
    return RunEntry(path=path, key=key, solver=solver, scene=scene, backend=backend,
                    seed=seed if isinstance(seed, int) else None, steps=steps if isinstance(steps, int) else None,
                    step=step if isinstance(step, int) else None, status=status, modified=_newest(path),
                    bytes=folder_bytes(path), result=result, identity=identity)


def _run_folders(root: Path) -> list[Path]:
    if entry_kind(root) != "dir":
        return []
    return sorted(p for p in root.iterdir()
                  if p.name != QUARANTINE and entry_kind(p) == "dir"
                  and (RUN_NAME.match(p.name) or entry_kind(p / "config.json") == "file"))


def list_runs(root: Path) -> list[RunEntry]:
    """Every run folder of the cache at `root`, newest first."""
    return sorted((run_entry(p) for p in _run_folders(Path(root))), key=lambda e: e.modified, reverse=True)


def find_run(text: str, root: Path) -> Path:
    """The run folder `text` names: a path to a run folder, or a unique prefix of a folder name or key in
    the cache at `root`.  RunLookupError when none or several fit."""
    path = Path(text)
    if entry_kind(path) == "dir" and (entry_kind(path / "config.json") == "file" or RUN_NAME.match(path.name)):
        return path
    if not text or "/" in text or "\0" in text:
        raise RunLookupError(f"'{_short(text)}': no run folder there and not a run id (a prefix of a run's "
                             "folder name or key); `cloudpbf runs` lists the runs")
    folders = _run_folders(Path(root))
    hits = [p for p in folders if p.name.startswith(text)]
    if not hits:
        for p in folders:
            m = RUN_NAME.match(p.name)
            if m and (m.group(3).startswith(text[:16]) and (len(text) <= 16 or _key_of(p).startswith(text))):
                hits.append(p)
    if len(hits) == 1:
        return hits[0]
    if not hits:
        raise RunLookupError(f"'{_short(text)}': no run in {root} has a folder name or key starting so; "
                             "`cloudpbf runs` lists the runs")
    names = ", ".join(p.name for p in hits[:8]) + (f", ... ({len(hits)} in all)" if len(hits) > 8 else "")
    raise RunLookupError(f"'{_short(text)}' fits {len(hits)} runs: {names}; give more characters")


def _key_of(path: Path) -> str:
    try:
        key = read_json(path / "config.json", limit=MAX_CONFIG_BYTES).get("key")
        return key if isinstance(key, str) else ""
    except (OSError, ValueError, AttributeError):
        return ""


def _short(text: str, limit: int = 60) -> str:
    text = text.replace("\n", "\\n")
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _locked(path: Path) -> bool:
    """True when a process holds the run's lock (it is being written)."""
    if entry_kind(path / ".lock") != "file":
        return False
    try:
        from filelock import FileLock, Timeout  # harness extra (filelock)
    except ImportError:
        return False
    lock = FileLock(str(path / ".lock"), timeout=0)
    try:
        lock.acquire()
    except Timeout:
        return True
    except OSError:
        return False
    lock.release()
    return False


def prune_runs(root: Path, statuses: set[str], older_than_s: float | None, quarantine: bool,
               dry_run: bool = True) -> tuple[list[tuple[Path, int, str]], list[str]]:
    """What `cloudpbf runs prune` removes: runs whose status is in `statuses` (and older than `older_than_s`
    when given), and every quarantine folder when `quarantine`.  Runs being written (locked) are skipped.
    Returns ([(path, bytes, why)], [skipped lines]); removes them unless `dry_run` (then a folder that cannot
    be removed is a skipped line, the others are removed)."""
    chosen, skipped = [], []
    for entry in list_runs(root):
        if entry.status not in statuses or (older_than_s is not None and entry.age_s < older_than_s):
            continue
        if _locked(entry.path):
            skipped.append(f"{entry.path.name} is being written (locked)")
            continue
        chosen.append((entry.path, entry.bytes, entry.status))
    if quarantine:
        chosen.extend((p, folder_bytes(p) if entry_kind(p) == "dir" else 0, "quarantine")
                      for p in quarantine_folders(root))
    if not dry_run:
        removed = []
        for item in chosen:
            try:
                remove_entry(item[0])
                removed.append(item)
            except OSError as exc:
                skipped.append(f"{item[0]}: could not be removed ({exc.strerror or exc})")
        chosen = removed
    return chosen, skipped
