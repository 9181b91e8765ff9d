"""Execution: run a RunSpec into its directory of the store, step by step, with checkpoints and resume.

``execute(spec)`` returns the stored result when ``result.json`` exists (no work at all), resumes
from ``checkpoint.npz`` when an earlier attempt was interrupted, and otherwise runs from step 0.
Layout of ``ROOT/<solver>-<scene>-<key16>/``::

    config.json        the spec and its identity (everything hashed into the key)
    log.txt            start, resume, checkpoints, adaptive capacity full, instability, finish (appended)
    timings.csv        phase,total_ms,count,mean_ms (wall time per phase after the warm-up steps)
    stats.parquet      one row per diagnostic step: cloudpbf.statistics diagnostics (+ solver stats())
    profiles.parquet   vertical profiles per diagnostic step (long format), when the statistics give them
    steps.csv          solver stats() after every step (record_steps runs, e.g. dam_break's front x_max)
    snapshots/step_NNNNNN.npz   a few full states (particles) or fields (grid), the final one included
    checkpoint.npz     the latest good checkpoint, with progress.json beside it
    partial/           rows gathered so far by an unfinished run (discarded up to its checkpoint on resume)
    result.json        written last, atomically: marks the run complete (stable or not); holds the
                       manifest (bytes, sha256) of the other files and its own checksum

A stored result is served only when it passes :func:`verify_run`; a run that fails it (or an unfinished
attempt whose checkpoint, progress.json or partial/ is unusable or belongs to another run) is moved to
``ROOT/quarantine/`` (kept, logged) and computed again.  A run that cannot start (no such backend, too
large for the memory) is refused before its directory is made.

An unstable run (NaN/Inf, velocity or density-error bound, particles escaping through a wall) is
complete too: ``result.json`` holds ``stable: false`` with the reason, the step and the particle
ids, the last good checkpoint stays, and no diagnostics of the failing state are stored.  Every
file is written through cloudpbf_io.files.atomic_path: a temporary name, fsync, ``os.replace``, fsync
of the folder.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
import time
from pathlib import Path
from typing import Callable

import numpy as np

from cloudpbf.environment import device_description
from cloudpbf.solvers import ADAPTERS, nonfinite_fields, nonfinite_ids, scene_params
from cloudpbf.store.files import save_frame, save_npz, sha256_file
from cloudpbf.store.identity import RUN_FORMAT, RunSpec, effective_seed
from cloudpbf.store.lock import locked
from cloudpbf.store.manifest import (finished_files, info_checksum, manifest, now, quarantine, quarantine_entry,
                                  verify_run)
from cloudpbf.store.result import RunResult
from cloudpbf.store.safe import StoreError, append_line, entry_kind, read_json, store_error
from cloudpbf_io.files import atomic_write_json, remove_stale_temps
from cloudpbf_io.progress import progress_bar as tqdm
from pbf_cuda.protocol import InstabilityError

__all__ = ["execute", "execute_summary", "cached_result", "StoreError"]

PARTIAL = ("stats", "profiles", "steps")      # partial/NAME.json: the rows gathered up to the checkpoint
MAX_PROGRESS_BYTES = 16 << 20                  # progress.json (timings, checksums)
# What a run directory holds, by kind; anything else under these names (a link, a folder for a file, a
# device) is moved to the quarantine before an attempt starts, never followed.
RUN_FILES = {"config.json", "log.txt", "timings.csv", "stats.parquet", "profiles.parquet", "steps.csv",
             "checkpoint.npz", "progress.json", "result.json"}
RUN_FOLDERS = {"snapshots", "partial"}


def merge_timings(base: dict, extra: dict) -> dict:
    out = {k: dict(v) for k, v in base.items()}
    for phase, t in extra.items():
        cur = out.setdefault(phase, {"total_ms": 0.0, "count": 0})
        cur["total_ms"] += float(t["total_ms"])
        cur["count"] += int(t["count"])
    for t in out.values():
        t["mean_ms"] = t["total_ms"] / t["count"] if t["count"] else float("nan")
    return out


class _Run:
    """One attempt at a spec inside its (locked) directory."""

    def __init__(self, spec: RunSpec, identity: dict, key: str, directory: Path, quiet: bool,
                 on_step: Callable[[int], None] | None):
        self.spec, self.identity, self.identity_key, self.dir = spec, identity, key, directory
        self.adapter = ADAPTERS[spec.solver]
        self.quiet, self.on_step = quiet, on_step
        self.partial = directory / "partial"
        self.rejects_logged = 0      # split_capacity_rejects at the last capacity warning
        self.rejects = 0             # split_capacity_rejects after the latest step
        self.refused = False         # True while the simulation is being created (nothing made yet)

    def log(self, message: str) -> None:
        append_line(self.dir / "log.txt", f"{now()} {message}")

    # -- progress bookkeeping ------------------------------------------------------------------
    def _resume(self):
        """(sim, progress) from checkpoint.npz + progress.json when they belong to this run and agree,
        else (None, fresh); whatever fails a check is moved to the quarantine folder (and logged)."""
        fresh = {"step": 0, "timings": {}, "step_wall_s": 0.0, "timed_wall_s": 0.0, "max_particles": 0}
        ckpt, prog = self.dir / "checkpoint.npz", self.dir / "progress.json"
        attempt = ["checkpoint.npz", "progress.json", "partial"]
        present = {name: entry_kind(self.dir / name) for name in attempt}
        if not self.adapter.can_checkpoint or not any(present.values()):
            return None, fresh
        if not (present["checkpoint.npz"] == "file" and present["progress.json"] == "file"):
            quarantine(self.dir, attempt, "checkpoint.npz and progress.json are not both present")
            return None, fresh
        try:
            progress = read_json(prog, limit=MAX_PROGRESS_BYTES)
            if not isinstance(progress, dict):
                raise ValueError("not a JSON object")
            step = progress["step"]
            for name in ("step_wall_s", "timed_wall_s", "max_particles"):
                float(progress[name])
            if (not isinstance(progress["timings"], dict) or not isinstance(step, int) or isinstance(step, bool)
                    or not 0 < step < self.spec.total_steps or not isinstance(progress.get("partial"), dict)):
                raise ValueError("bad timings, step or partial checksums")
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            quarantine(self.dir, attempt, f"progress.json unreadable: {type(exc).__name__}: {str(exc)[:80]}")
            return None, fresh
        if progress.get("key") != self.identity_key:
            quarantine(self.dir, attempt, "progress.json belongs to another run (key "
                                          f"{str(progress.get('key'))[:16]}, this run {self.identity_key[:16]})")
            return None, fresh
        try:
            if progress.get("checkpoint_sha256") != sha256_file(ckpt):
                raise ValueError("checkpoint.npz does not match the sha256 in progress.json")
            rows = {name: self._partial_rows(name, step, progress["partial"]) for name in PARTIAL}
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            quarantine(self.dir, attempt, f"{type(exc).__name__}: {str(exc)[:120]}")
            return None, fresh
        try:
            sim = self.adapter.load(ckpt, self.spec)
        except Exception as exc:  # a damaged checkpoint: start over, say so
            quarantine(self.dir, attempt, f"checkpoint unreadable ({type(exc).__name__}: {str(exc)[:80]})")
            return None, fresh
        expected = self.adapter.expected_scene(self.spec)
        if expected is not None and scene_params(sim.scene) != scene_params(expected):
            quarantine(self.dir, attempt, "the checkpoint's scene differs from the run's")
            return None, fresh
        if sim.step_count != step:
            quarantine(self.dir, attempt, f"checkpoint step {sim.step_count} != progress step {step}")
            return None, fresh
        self.resumed_rows = rows
        return sim, progress

    def _partial_rows(self, name: str, upto: int, checksums: dict) -> list[dict]:
        """The rows of partial/NAME.json, checked against the sha256 progress.json holds for it (a file of
        another attempt or run, or one that progress.json does not vouch for, is refused: ValueError)."""
        path = self.partial / f"{name}.json"
        expected = checksums.get(name)
        if entry_kind(path) is None and expected is None:
            return []
        if expected is None or sha256_file(path) != expected:
            raise ValueError(f"partial/{name}.json does not match the sha256 in progress.json")
        rows = read_json(path)
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise ValueError(f"partial/{name}.json: expected a list of rows")
        for r in rows:
            step = r.get("step")
            if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step <= upto:
                raise ValueError(f"partial/{name}.json: a row of step {str(step)[:20]} (expected 0 to {upto})")
        return rows

    def _checkpoint(self, sim, progress: dict) -> None:
        checksums = {}
        for name, rows in zip(PARTIAL, (self.rows, self.profile_rows, self.step_rows)):
            path = atomic_write_json(self.partial / f"{name}.json", rows, sort_keys=False)  # keeps column order
            checksums[name] = sha256_file(path)
        self.adapter.save(sim, self.dir / "checkpoint.npz")
        progress = {**progress, "key": self.identity_key, "partial": checksums,
                    "checkpoint_sha256": sha256_file(self.dir / "checkpoint.npz")}
        atomic_write_json(self.dir / "progress.json", progress)
        self.log(f"checkpoint at step {progress['step']}")

    # -- one diagnostics row -------------------------------------------------------------------
    def _record(self, sim, stats_row: dict | None, snapshot: bool) -> None:
        step = sim.step_count
        state = self.adapter.state(sim)
        bad = nonfinite_fields(state)
        if bad:
            ids = nonfinite_ids(state) if "id" in state else []
            raise InstabilityError(step, f"NaN/Inf in {', '.join(bad)}", ids, step - 1)
        if snapshot:
            save_npz(self.dir / "snapshots" / f"step_{step:06d}.npz",
                      {**state, "step": np.int64(step), "time_s": np.float64(sim.time)})
        if not self.spec.diagnostics:
            return
        import pandas as pd  # harness extra (pandas)
        row, profiles = self.adapter.diagnostics(sim, self.spec, state)
        when = {"step": step, "time_s": float(sim.time)}
        # The shared statistics keep their names; a solver's own value of the same name (e.g. its exact
        # total_water, where the shared one is deposited on the grid) is kept as solver_<name>.
        extra = {(k if k not in row else f"solver_{k}"): v for k, v in (stats_row or {}).items()}
        self.rows.append({**when, **row, **extra})
        if profiles is not None:
            for prof in pd.DataFrame(profiles).to_dict("records"):
                self.profile_rows.append({**when, **prof})

    # -- the loop --------------------------------------------------------------------------------
    def run(self) -> RunResult:
        spec = self.spec
        started = time.perf_counter()
        self.resumed_rows = {}
        sim, progress = self._resume()
        resumed_from = progress["step"] if sim is not None else None
        self.rows = self.resumed_rows.get("stats", [])
        self.profile_rows = self.resumed_rows.get("profiles", [])
        self.step_rows = self.resumed_rows.get("steps", [])
        self.device_bytes_before = None
        if sim is None:
            self.refused = True            # a failure before the simulation exists leaves nothing behind
            self.device_bytes_before = self.adapter.device_bytes_in_use(spec)
            sim = self.adapter.create(spec)
            self.refused = False
            self.log(f"start {spec.solver} {spec.scene.name}: {spec.total_steps} steps, "
                     f"seed {effective_seed(self.identity)}, "
                     f"backend {getattr(sim, 'backend', spec.backend)}")
        else:
            self.log(f"resume from checkpoint at step {resumed_from}")
        atomic_write_json(self.dir / "config.json", {
            "identity": self.identity, "key": self.identity_key,
            "checkpoint_every": spec.checkpoint_interval, "diagnostic_steps": spec.diagnostic_steps(),
            "snapshot_steps": spec.snapshot_steps(), "created": now()})
        base_timings = progress["timings"]
        step_wall = float(progress["step_wall_s"])
        timed_wall = float(progress["timed_wall_s"])      # wall time of the steps after the warm-up
        max_particles = max(int(progress["max_particles"]), self.adapter.size(sim))
        diag_steps = set(spec.diagnostic_steps())
        snap_steps = set(spec.snapshot_steps())
        total = spec.total_steps
        times_left = [t for t in spec.diagnostic_times if t > float(sim.time) * (1.0 + 1e-9)] if spec.diagnostics else []
        controlled = float(getattr(spec.scene.time, "cfl", 0.0) or 0.0) > 0.0
        chunk = 1 if spec.record_steps else 10
        failure = None
        bar = tqdm(total=total, initial=sim.step_count, desc=f"{spec.solver} {spec.scene.name}", unit="step",
                   disable=True if self.quiet else None, leave=False, dynamic_ncols=True)
        try:
            if sim.step_count == 0 and (0 in diag_steps or 0 in snap_steps):
                self._record(sim, self.adapter.step_row(sim), 0 in snap_steps)
            while sim.step_count < total and not self._reached_end(sim):
                s0 = sim.step_count
                targets = [total, s0 + chunk] + [s for s in diag_steps | snap_steps if s > s0]
                if self.adapter.can_checkpoint:
                    targets.append((s0 // spec.checkpoint_interval + 1) * spec.checkpoint_interval)
                if s0 < spec.warmup_steps:
                    targets.append(spec.warmup_steps)
                n = min(targets) - s0
                if spec.end_time is not None:
                    n = min(n, _steps_toward(spec.end_time - float(sim.time), sim))
                if times_left:      # a controlled step stops before each time too, so its last step before it has a row
                    remaining = times_left[0] - float(sim.time)
                    n = min(n, _steps_below(remaining, sim) if controlled else _steps_toward(remaining, sim))
                t0 = time.perf_counter()
                try:
                    sim.step(n)
                finally:                       # a failing step's time counts too
                    elapsed = time.perf_counter() - t0
                    step_wall += elapsed
                    if s0 >= spec.warmup_steps:
                        timed_wall += elapsed
                s = sim.step_count
                row = self.adapter.step_row(sim)
                self.adapter.check(sim, spec, row)
                max_particles = max(max_particles, self.adapter.size(sim))
                self._note_capacity(sim, row)
                if spec.record_steps:   # with each step's wall time, ms (Table 1's median and spread)
                    self.step_rows.append({**row, "wall_ms": 1e3 * elapsed / max(n, 1)})
                if s == spec.warmup_steps:
                    sim.reset_timings()
                    base_timings = {}
                last = s >= total or self._reached_end(sim)     # a run with an end time: its final step too
                bracket = _brackets_a_time(times_left, float(sim.time), sim, controlled)
                if s in diag_steps or s in snap_steps or (last and spec.end_time is not None) or bracket:
                    self._record(sim, row, s in snap_steps or (last and total in snap_steps))
                if self.adapter.can_checkpoint and s % spec.checkpoint_interval == 0 and not last:
                    self._checkpoint(sim, {"step": s, "timings": merge_timings(base_timings, sim.timings()),
                                           "step_wall_s": step_wall, "timed_wall_s": timed_wall,
                                           "max_particles": max_particles})
                bar.update(n)
                if self.on_step is not None:
                    self.on_step(s)
            if spec.end_time is not None and not self._reached_end(sim):
                self.log(f"end_time {spec.end_time:g} s not reached in {total} steps (t = {float(sim.time):g} s)")
        except InstabilityError as exc:
            failure = exc
            self.log(f"UNSTABLE: {exc}")
        except BaseException as exc:
            self.log(f"interrupted at step {sim.step_count}: {exc!r}"[:2000])
            raise
        finally:
            bar.close()
        timings = merge_timings(base_timings, sim.timings())
        return self._finish(sim, failure, timings, step_wall, timed_wall, max_particles, resumed_from,
                            time.perf_counter() - started)

    def _reached_end(self, sim) -> bool:
        end = self.spec.end_time
        return end is not None and float(sim.time) >= end * (1.0 - 1e-9)

    def _device_bytes(self) -> int | None:
        """Device memory the run holds at its end over what was in use before it made its simulation: with
        grow-only arrays and cached temporary storage, its peak (None on the CPU and for resumed runs)."""
        if self.device_bytes_before is None:
            return None
        now = self.adapter.device_bytes_in_use(self.spec)
        return None if now is None else max(0, now - self.device_bytes_before)

    def _note_capacity(self, sim, row: dict) -> None:
        """Log (and print) when the adaptive capacity first turns splits away, then each tenfold growth."""
        rejects = int(row.get("split_capacity_rejects", 0) or 0)
        logged = self.rejects_logged
        if rejects > 0 and (logged == 0 or rejects >= 10 * logged):
            message = (f"adaptive capacity full at step {sim.step_count}: {rejects} split(s) turned away so far "
                       f"({sim.capacity} particle slots, adaptive.capacity = "
                       f"{sim.scene.adaptive.capacity}); the run goes on without them")
            self.log(message)
            if not self.quiet:
                tqdm.write(f"warning: {message}")
            self.rejects_logged = rejects
        self.rejects = rejects

    def _finish(self, sim, failure, timings, step_wall, timed_wall, max_particles, resumed_from,
                wall) -> RunResult:
        import pandas as pd  # harness extra (pandas)
        spec = self.spec
        save_frame(pd.DataFrame([{"phase": k, **v} for k, v in sorted(timings.items())],
                               columns=["phase", "total_ms", "count", "mean_ms"]), self.dir / "timings.csv")
        if self.rows:
            save_frame(pd.DataFrame(self.rows), self.dir / "stats.parquet")
        if self.profile_rows:
            save_frame(pd.DataFrame(self.profile_rows), self.dir / "profiles.parquet")
        if self.step_rows:
            save_frame(pd.DataFrame(self.step_rows), self.dir / "steps.csv")
        backend = getattr(sim, "backend", None) or self.identity["backend"]
        info = {
            "format": RUN_FORMAT, "key": self.identity_key, "solver": spec.solver, "scene": spec.scene.name,
            "seed": spec.seed, "steps_requested": spec.total_steps,
            "stable": failure is None,
            "reason": None if failure is None else failure.reason,
            "step": sim.step_count if failure is None else failure.step,
            "particles": [] if failure is None else list(getattr(failure, "particles", []))[:16],
            "last_good_step": sim.step_count if failure is None else failure.last_good_step,
            "time_s": float(sim.time) if failure is None else None,
            **self.adapter.result_fields(max_particles, self.rejects),
            "step_wall_s": step_wall, "wall_s": wall, "resumed_from": resumed_from,
            "timed_steps": max(0, sim.step_count - spec.warmup_steps) if failure is None else None,
            "step_ms": 1e3 * timed_wall / max(1, sim.step_count - spec.warmup_steps) if failure is None else None,
            "backend": backend, "device": device_description(backend),
            "device_bytes": self._device_bytes(),
            "code": self.identity["code"], "finished": now(),
        }
        if failure is None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.dir / "progress.json")
        info["manifest"] = manifest(self.dir)          # checked whenever the result is served
        info["checksum"] = info_checksum(info)
        atomic_write_json(self.dir / "result.json", info)
        info = {k: v for k, v in info.items() if k not in ("manifest", "checksum")}
        self.log("finished " + ("stable" if failure is None else f"UNSTABLE at step {failure.step}")
                 + f" ({step_wall:.2f} s in steps)")
        return RunResult(self.dir, info, cached=False)


def _brackets_a_time(times_left: list, t: float, sim, controlled: bool) -> bool:
    """Whether the state at simulated time t gets a row for RunSpec.diagnostic_times: it is the first to reach the
    next of `times_left` (which then leaves the list), or, in a CFL-controlled run, the last before it (its next
    step, sim.time_step, reaches it)."""
    reached = False
    while times_left and t >= times_left[0] * (1.0 - 1e-9):
        times_left.pop(0)
        reached = True
    dt = float(getattr(sim, "time_step", 0.0) or 0.0)
    before = controlled and bool(times_left) and t + dt >= times_left[0] * (1.0 - 1e-9)
    return reached or before


def _steps_below(remaining: float, sim) -> int:
    """How many CFL-controlled steps surely stay short of `remaining` more seconds even if each grew by the control's
    largest factor (1.25): one fewer than reach it (_steps_toward); at least 1."""
    return max(1, _steps_toward(remaining, sim) - 1)


def _steps_toward(remaining: float, sim) -> int:
    """How many steps can be taken at once without passing the first step that reaches `remaining` more seconds:
    with the solver's step in use dt, all of them at dt; where the step is CFL-controlled (time.cfl > 0), the
    fewest steps that reach it if every step grew by the control's largest factor (1.25).  1 where the
    solver has no time_step."""
    dt = float(getattr(sim, "time_step", 0.0) or 0.0)
    if not dt > 0.0 or not remaining > 0.0:
        return 1
    if not getattr(sim.scene.time, "cfl", 0.0) > 0.0:
        return max(1, math.ceil(remaining / dt * (1.0 - 1e-9)))
    n, covered = 0, 0.0
    while covered < remaining and n < 10**6:
        covered += dt * 1.25 ** n
        n += 1
    return max(1, n)


def _odd_entries(directory: Path) -> list[str]:
    """Entries of a run directory of the wrong kind: a known file that is not a regular file, a known folder
    that is not a folder, anything but regular files inside snapshots/ and partial/."""
    odd = []
    for name in sorted(RUN_FILES | RUN_FOLDERS):
        kind = entry_kind(directory / name)
        if kind is not None and kind != ("dir" if name in RUN_FOLDERS else "file"):
            odd.append(name)
        elif kind == "dir":
            odd.extend(f"{name}/{p.name}" for p in sorted((directory / name).iterdir()) if entry_kind(p) != "file")
    return odd


def _served(directory: Path, key: str) -> RunResult | None:
    """The stored result when the directory holds a finished run that passes verify_run, else None."""
    if entry_kind(directory) == "dir" and entry_kind(directory / "result.json") == "file" \
            and not verify_run(directory, key):
        try:
            return RunResult.load(directory, cached=True)
        except (OSError, ValueError):            # changed between the check and the read: not served
            return None
    return None


def execute(spec: RunSpec, root: str | Path | None = None, *, quiet: bool = False,
            on_step: Callable[[int], None] | None = None) -> RunResult:
    """Run `spec` (or return its stored result without any work).  See the module docstring.

    A stored result is served only when it passes verify_run (a read-only cache serves the runs it holds);
    otherwise its files go to the quarantine folder (logged) and the run is computed again.  A run that
    cannot start (no such backend, too large for the memory) raises before its directory is made.  A cache
    that cannot be written (read-only, full, no permission) raises StoreError naming the run directory,
    with no temporary file left.

    on_step(step) is called after every chunk of steps (tests use it to simulate a crash)."""
    identity = spec.identity()
    key = spec.key(identity)
    directory = spec.directory(root, key)
    served = _served(directory, key)
    if served is not None:
        return served
    ADAPTERS[spec.solver].preflight(spec)
    try:
        kind = entry_kind(directory)
        if kind not in (None, "dir"):
            quarantine_entry(directory, f"a {kind} stood where the run directory belongs")
        created = entry_kind(directory) is None
        directory.mkdir(parents=True, exist_ok=True)
        if not os.access(directory, os.W_OK | os.X_OK):
            raise StoreError(f"{directory}: cannot write (no permission, or a read-only file system); the run "
                             "is not stored there finished; pass a writable --runs-root")
        with locked(directory):
            remove_stale_temps(directory, owned=True)       # we hold the lock: no writer is in here
            odd = _odd_entries(directory)
            if odd:
                quarantine(directory, odd, "not the kind of file a run directory holds (links are not followed)")
            if entry_kind(directory / "result.json") is not None:
                problems = verify_run(directory, key)
                if not problems:
                    return RunResult.load(directory, cached=True)
                quarantine(directory, finished_files(directory), "; ".join(problems[:3]))
            attempt = _Run(spec, identity, key, directory, quiet, on_step)
            try:
                return attempt.run()
            except BaseException:
                if attempt.refused and created:
                    shutil.rmtree(directory, ignore_errors=True)
                raise
    except OSError as exc:
        error = store_error(exc, directory)
        if error is None:
            raise
        raise error from None


def execute_summary(spec: RunSpec, root: str | Path | None = None) -> dict:
    """execute() for a worker process: quiet, returns the small summary dict."""
    return execute(spec, root, quiet=True).summary()


def cached_result(spec: RunSpec, root: str | Path | None = None) -> RunResult | None:
    """The stored result of `spec` when it is complete and passes verify_run, else None (execute then
    moves a damaged one aside and recomputes it)."""
    identity = spec.identity()
    key = spec.key(identity)
    return _served(spec.directory(root, key), key)
