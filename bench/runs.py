"""The run cache: one simulation run is one directory, named by a hash of what decides its result.

A :class:`RunSpec` says what to run (solver, scene, backend, steps, seed, options).  Its key is the
sha256 of the scene's parameters (its description aside), the solver, the resolved backend, the
step count, the seed, the run options and the *code version*: a hash of the source files the result
executes (see :func:`code_sources`: the modules its solver adapter drives and all they import), so editing the solver, the grid baseline or the statistics
invalidates earlier runs of that solver.  The compiled module carries the hash of the csrc sources it
was built from and is refused when they differ (pbf_cuda.buildinfo), so a stale build never runs.

``execute(spec)`` returns the stored result when ``result.json`` exists (no work at all), resumes
from ``checkpoint.npz`` when an earlier attempt was interrupted, and otherwise runs from step 0.
Layout of ``ROOT/<solver>-<scene>-<key16>/``::

    config.json        the spec and its identity (everything hashed into the key)
    log.txt            start, resume, checkpoints, adaptive capacity full, instability, finish (appended)
    timings.csv        phase,total_ms,count,mean_ms (wall time per phase after the warm-up steps)
    stats.parquet      one row per diagnostic step: bench.statistics diagnostics (+ solver stats())
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
file is written through pbf_cuda.files.atomic_path: a temporary name, fsync, ``os.replace``, fsync
of the folder.

The default root is ``$CLOUDPBF_RUNS``, else ``runs/`` in a source checkout, else the user cache folder
(:func:`default_root`).
"""
from __future__ import annotations

import ast
import contextlib
import dataclasses
import datetime as _dt
import functools
import hashlib
import json
import logging
import math
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from pbf_cuda.scene import Scene

__all__ = [
    "RunSpec", "RunResult", "RunInstability", "execute", "execute_summary", "default_root", "code_version",
    "atomic_path", "atomic_write_text", "atomic_write_json", "write_csv", "write_parquet", "ADAPTERS",
    "REPO_ROOT", "SOLVERS", "verify_run", "cached_result", "QUARANTINE",
]

REPO_ROOT = Path(__file__).resolve().parent.parent
QUARANTINE = "quarantine"    # ROOT/quarantine/: run files that failed verification, kept for inspection
log = logging.getLogger("bench.runs")
RUN_FORMAT = 2          # bump when the run directory layout or the loop's semantics change
SOLVERS = ("particles", "grid")
MAX_STEPS = 10**7
SOURCE_SUFFIXES = (".py", ".h", ".hpp", ".cuh", ".cu", ".cpp", ".cc", ".c", ".inl")
FIRST_PARTY = ("pbf_cuda", "grid_baseline", "bench")   # the packages whose sources a code version reads
# Compiled modules and the source files (relative to the repository) they are built from.
NATIVE_SOURCES = {"pbf_cuda._core": ("pbf_cuda/csrc", "CMakeLists.txt")}
STATS_VECTOR_AXES = "xyz"
GRID_BYTES_PER_CELL = 800    # fields, auxiliaries and jit buffers of the grid baseline in float64


def is_checkout(root: Path = REPO_ROOT) -> bool:
    """True when the code runs from a source checkout (editable install or PYTHONPATH), not from an
    installed wheel: the folder above the packages holds pyproject.toml and is no site-packages."""
    return (root / "pyproject.toml").is_file() and not {"site-packages", "dist-packages"} & set(root.parts)


def default_root() -> Path:
    """Where runs live: $CLOUDPBF_RUNS; else runs/ in the checkout (gitignored) when running from one;
    else the user cache folder (platformdirs: ~/.cache/cloudpbf/runs on Linux, ~/Library/Caches/cloudpbf/runs
    on macOS, %LOCALAPPDATA%\\cloudpbf\\Cache\\runs on Windows), never inside site-packages."""
    env = os.environ.get("CLOUDPBF_RUNS")
    if env:
        return Path(env)
    if is_checkout():
        return REPO_ROOT / "runs"
    import platformdirs
    return Path(platformdirs.user_cache_dir("cloudpbf", appauthor=False)) / "runs"


# ---- atomic writes (pbf_cuda.files: one helper, one file mode, fsync of file and folder) ---------
from pbf_cuda.files import (FILE_MODE, json_default, atomic_path, atomic_write_json, atomic_write_text,  # noqa: E402,F401
                            remove_stale_temps)


def write_csv(frame, path: str | Path) -> Path:
    """Write a pandas DataFrame as CSV atomically (no index)."""
    with atomic_path(path) as tmp:
        frame.to_csv(tmp, index=False)
    return Path(path)


def write_parquet(frame, path: str | Path) -> Path:
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)
    return Path(path)


def _save_npz(path: Path, arrays: dict) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def sha256_file(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ---- code version ----------------------------------------------------------------------------
def _source_files(entry: str) -> list[Path]:
    path = REPO_ROOT / entry
    if path.is_file():
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.rglob("*")
                  if p.is_file() and (p.suffix in SOURCE_SUFFIXES or p.name == "CMakeLists.txt")
                  and "__pycache__" not in p.parts)


def _module_file(module: str) -> Path | None:
    base = REPO_ROOT.joinpath(*module.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _imported_modules(path: Path, module: str) -> set[str]:
    """First-party modules that a source file imports, anywhere in it (imports inside functions too).
    ``from package import name`` names the submodule when there is one, else the package."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_bytes(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            parts = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
            base = ".".join(parts + ([node.module] if node.module else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if sub in NATIVE_SOURCES or _module_file(sub) is not None else base)
    return {name for name in found if name.split(".")[0] in FIRST_PARTY}


def code_sources(modules: Iterable[str]) -> list[Path]:
    """The source files that `modules` run: their files, those of every first-party module they import
    (followed to any depth), the __init__.py of each package on the way (a package's face: read, its
    re-exports not followed), and the native sources of the compiled modules among them."""
    files, todo, seen = set(), list(modules), set()
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        seen.add(module)
        parts = module.split(".")
        files.update(f for f in (_module_file(".".join(parts[:i])) for i in range(1, len(parts))) if f)
        for entry in NATIVE_SOURCES.get(module, ()):
            files.update(_source_files(entry))
        path = _module_file(module)
        if path is not None:
            files.add(path)
            todo.extend(_imported_modules(path, module))
    return sorted(files)


@functools.lru_cache(maxsize=None)
def code_version(solver: str) -> str:
    """sha256 (16 hex) of the source files a `solver` run executes (code_sources of the modules its adapter
    drives), names and contents."""
    digest = hashlib.sha256()
    for path in code_sources(ADAPTERS[solver].modules):
        digest.update(str(path.relative_to(REPO_ROOT)).encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


# ---- the spec ----------------------------------------------------------------------------------
class RunInstability(RuntimeError):
    """An instability found by the harness (particles escaping, NaN in fields or statistics).

    Same fields as pbf_cuda.InstabilityError: step, reason, particles (ids), last_good_step."""

    def __init__(self, step: int, reason: str, particles: Iterable[int] = (), last_good_step: int = -1):
        self.step = int(step)
        self.reason = reason
        self.particles = [int(p) for p in particles]
        self.last_good_step = int(last_good_step)
        ids = ", ".join(map(str, self.particles[:16])) or "none identified"
        super().__init__(f"unstable at step {self.step}: {reason}; particles (ids): {ids}")


def _check_int(name: str, value, lo: int, hi: int, allow_none: bool = False):
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= int(value) <= hi:
        raise ValueError(f"{name} = {value!r}: expected an integer in [{lo}, {hi}]")


@dataclass(frozen=True)
class RunSpec:
    """What to run.  Steps, snapshot and checkpoint intervals default to the scene's `time` section.

    solver: 'particles' (pbf_cuda.Simulation) or 'grid' (grid_baseline.GridSimulation)
    backend: particles 'auto' | 'cpu' | 'cuda'; the grid runs on jax's default device ('auto')
    seed: noise/initial-velocity seed (None: the scene's own)
    snapshot_every: steps between diagnostics rows (stats.parquet); the final step always has one
    keep_snapshots: how many full states to store as npz (evenly spaced diagnostic steps, final included)
    checkpoint_every: steps between checkpoints (default: snapshot_every)
    record_steps: store solver stats() after every step in steps.csv
    diagnostics: compute bench.statistics diagnostics (off for pure timing runs)
    warmup_steps: timings are reset after this many steps (first-step allocations left out)
    cells_per_spacing, resolution, dtype: grid options (see grid_baseline.GridSimulation)
    diagnostics_resolution: deposit grid (nx, ny, nz) for particle diagnostics (None: the statistics' default)
    """
    solver: str
    scene: Scene
    backend: str = "auto"
    steps: int | None = None
    seed: int | None = None
    snapshot_every: int | None = None
    keep_snapshots: int = 3
    checkpoint_every: int | None = None
    record_steps: bool = False
    diagnostics: bool = True
    warmup_steps: int = 0
    cells_per_spacing: float = 1.0
    resolution: tuple | None = None
    dtype: str | None = None
    diagnostics_resolution: tuple | None = None

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ValueError(f"solver = {self.solver!r}: allowed {', '.join(SOLVERS)}")
        if not isinstance(self.scene, Scene):
            raise ValueError(f"scene = {self.scene!r}: expected a pbf_cuda.scene.Scene")
        if self.backend not in ("auto", "cpu", "cuda"):
            raise ValueError(f"backend = {self.backend!r}: allowed auto, cpu, cuda")
        _check_int("steps", self.steps, 1, MAX_STEPS, allow_none=True)
        _check_int("seed", self.seed, 0, 2**31 - 1, allow_none=True)
        _check_int("snapshot_every", self.snapshot_every, 1, MAX_STEPS, allow_none=True)
        _check_int("checkpoint_every", self.checkpoint_every, 1, MAX_STEPS, allow_none=True)
        _check_int("keep_snapshots", self.keep_snapshots, 0, 10_000)
        _check_int("warmup_steps", self.warmup_steps, 0, MAX_STEPS)
        if self.warmup_steps >= self.total_steps:
            raise ValueError(f"warmup_steps = {self.warmup_steps}: must be below steps = {self.total_steps}")
        if not (isinstance(self.cells_per_spacing, (int, float)) and 0.05 <= self.cells_per_spacing <= 64):
            raise ValueError(f"cells_per_spacing = {self.cells_per_spacing!r}: expected a number in [0.05, 64]")
        for name in ("resolution", "diagnostics_resolution"):
            value = getattr(self, name)
            if value is not None:
                if len(value) != 3 or any(not isinstance(v, (int, np.integer)) or v < 1 for v in value):
                    raise ValueError(f"{name} = {value!r}: expected three positive integers (nx, ny, nz)")
                object.__setattr__(self, name, tuple(int(v) for v in value))
        if self.dtype not in (None, "float32", "float64"):
            raise ValueError(f"dtype = {self.dtype!r}: allowed float32, float64")

    # ---- derived -----------------------------------------------------------------------------
    @property
    def total_steps(self) -> int:
        return int(self.steps if self.steps is not None else self.scene.time.steps)

    @property
    def diagnostic_every(self) -> int:
        return int(self.snapshot_every if self.snapshot_every is not None else self.scene.time.snapshot_every)

    @property
    def checkpoint_interval(self) -> int:
        return int(self.checkpoint_every if self.checkpoint_every is not None else self.diagnostic_every)

    def diagnostic_steps(self) -> list[int]:
        """Steps that get a diagnostics row: 0, every `snapshot_every`, and the last step."""
        if not self.diagnostics:
            return []
        n, every = self.total_steps, self.diagnostic_every
        return sorted({0, n, *range(every, n, every)})

    def snapshot_steps(self) -> list[int]:
        """Steps whose full state is stored: `keep_snapshots` diagnostic steps, evenly spaced, last included."""
        candidates = self.diagnostic_steps() or [self.total_steps]
        k = min(self.keep_snapshots, len(candidates))
        if k <= 0:
            return []
        picks = np.unique(np.rint(np.linspace(len(candidates) - 1, 0, k)).astype(int))
        return sorted(candidates[i] for i in picks)

    def options(self) -> dict:
        """Everything but the scene, solver, backend, steps and seed that enters the key."""
        out = {"snapshot_every": self.diagnostic_every, "keep_snapshots": self.keep_snapshots,
               "record_steps": self.record_steps, "diagnostics": self.diagnostics,
               "warmup_steps": self.warmup_steps,
               "diagnostics_resolution": list(self.diagnostics_resolution) if self.diagnostics_resolution else None}
        if self.solver == "grid":
            out.update(cells_per_spacing=float(self.cells_per_spacing),
                       resolution=list(self.resolution) if self.resolution else None, dtype=self.dtype)
        return out

    def identity(self) -> dict:
        """All that is hashed into the key (the checkpoint interval is not: it does not change results)."""
        scene = self.scene.to_dict()
        scene["scene"] = {"name": self.scene.name}
        return {"format": RUN_FORMAT, "solver": self.solver, "scene": scene,
                "backend": ADAPTERS[self.solver].resolve_backend(self.backend),
                "steps": self.total_steps, "seed": self.seed, "options": self.options(),
                "code": ADAPTERS[self.solver].code_version()}

    def key(self, identity: dict | None = None) -> str:
        """sha256 (hex) of identity()."""
        blob = json.dumps(identity or self.identity(), sort_keys=True, default=json_default).encode()
        return hashlib.sha256(blob).hexdigest()

    def directory(self, root: str | Path | None = None, key: str | None = None) -> Path:
        """ROOT/<solver>-<scene>-<key16>."""
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", self.scene.name)[:60] or "scene"
        return Path(root or default_root()) / f"{self.solver}-{name}-{(key or self.key())[:16]}"

    def replace(self, **changes) -> "RunSpec":
        return dataclasses.replace(self, **changes)


# ---- solver adapters ---------------------------------------------------------------------------
def _flatten(values: dict) -> dict:
    """Solver stats() as flat scalars: min_position -> min_position_x/_y/_z, level_counts -> level_0..,
    time -> time_s (s); strings (the backend's name) dropped."""
    out = {}
    for name, value in values.items():
        if isinstance(value, str):
            continue
        if name == "time":
            name = "time_s"
        if name == "level_counts":
            for level, count in enumerate(value):
                out[f"level_{level}"] = int(count)
        elif isinstance(value, (list, tuple, np.ndarray)):
            arr = np.asarray(value).ravel()
            labels = STATS_VECTOR_AXES if len(arr) == 3 else [str(i) for i in range(len(arr))]
            for label, v in zip(labels, arr):
                out[f"{name}_{label}"] = v.item()
        else:
            out[name] = value.item() if isinstance(value, np.generic) else value
    return out


def _scene_params(scene) -> dict:
    """A scene's parameters without its name and description (what a checkpoint must match)."""
    data = scene.to_dict()
    data.pop("scene", None)
    return json.loads(json.dumps(data, sort_keys=True, default=float))


def _nonfinite_fields(arrays: dict) -> list[str]:
    return [name for name, arr in arrays.items()
            if isinstance(arr, np.ndarray) and arr.dtype.kind == "f" and not np.all(np.isfinite(arr))]


class ParticleAdapter:
    """pbf_cuda.Simulation behind the run loop."""
    solver = "particles"
    can_checkpoint = True
    modules = ("pbf_cuda.simulation", "bench.statistics")    # what decides a result (see code_version)

    @staticmethod
    def resolve_backend(backend: str) -> str:
        if backend != "auto":
            return backend
        from pbf_cuda.simulation import available_backends
        return "cuda" if "cuda" in available_backends() else "cpu"

    @staticmethod
    def code_version() -> str:
        return code_version("particles")

    @staticmethod
    def instability_errors() -> tuple:
        from pbf_cuda.simulation import InstabilityError
        return (InstabilityError, RunInstability)

    @staticmethod
    def preflight(spec: RunSpec) -> None:
        """Refuse before anything is made: the backend must exist (RuntimeError), the run must fit in
        memory (pbf_cuda.SceneError naming the particle count and the memory needed)."""
        from pbf_cuda.memory import check_memory
        from pbf_cuda.simulation import _resolve_backend, seeded_scene
        check_memory(seeded_scene(spec.scene, spec.seed), _resolve_backend(spec.backend))

    @staticmethod
    def expected_scene(spec: RunSpec):
        """The scene a checkpoint of this spec must hold."""
        from pbf_cuda.simulation import seeded_scene
        return seeded_scene(spec.scene, spec.seed)

    @staticmethod
    def create(spec: RunSpec):
        from pbf_cuda.simulation import Simulation
        return Simulation(spec.scene, backend=spec.backend, seed=spec.seed)

    @staticmethod
    def load(path: Path, spec: RunSpec):
        from pbf_cuda.simulation import Simulation
        return Simulation.load(path, backend=ParticleAdapter.resolve_backend(spec.backend))

    @staticmethod
    def save(sim, path: Path) -> None:
        sim.save(path)

    @staticmethod
    def state(sim) -> dict:
        return sim.state()

    @staticmethod
    def size(sim) -> int:
        return int(sim.n_particles)

    @staticmethod
    def step_row(sim) -> dict:
        return _flatten(sim.stats())

    @staticmethod
    def check(sim, spec: RunSpec, row: dict | None) -> None:
        """Raise RunInstability for NaN in stats() or particles outside a wall axis (by more than h0)."""
        row = row if row is not None else _flatten(sim.stats())
        step = sim.step_count
        bad = [k for k, v in row.items() if isinstance(v, float) and not math.isfinite(v)]
        if bad:
            raise RunInstability(step, f"NaN/Inf in solver statistics ({', '.join(bad)})",
                                 _nonfinite_ids(sim.state()), step - 1)
        scene = sim.scene
        tol = scene.kernel_radius
        for axis, name in enumerate(STATS_VECTOR_AXES):
            if scene.domain.boundary[axis] != "wall":
                continue
            lo, hi = row.get(f"min_position_{name}"), row.get(f"max_position_{name}")
            size = scene.domain.size[axis]
            if lo is None or hi is None or (lo >= -tol and hi <= size + tol):
                continue
            pos = sim.state()
            p = pos["position"][:, axis]
            ids = pos["id"][(p < -tol) | (p > size + tol)]
            raise RunInstability(step, f"particles escaping the domain: {name} in [{lo:.6g}, {hi:.6g}] m, "
                                       f"outside the walls [0, {size:g}] m", ids[:16], step - 1)

    @staticmethod
    def diagnostics(sim, spec: RunSpec, state: dict):
        """(diagnostics row, vertical profiles) of a particle state, deposited once on the statistics grid.
        Plain-fluid scenes have no cloud statistics: their rows hold the solver's stats() only."""
        from bench import statistics
        scene = sim.scene
        if not scene.thermodynamics:
            return {}, None
        grid = statistics.deposit_state(state, scene, spec.diagnostics_resolution)
        periodic = tuple(b == "periodic" for b in scene.domain.boundary)
        return statistics.diagnostics(grid, periodic=periodic), statistics.vertical_profiles(grid)


def _nonfinite_ids(state: dict) -> list[int]:
    mask = np.zeros(len(state["id"]), dtype=bool)
    for name, arr in state.items():
        if name != "id" and isinstance(arr, np.ndarray) and arr.dtype.kind == "f" and len(arr) == len(mask):
            mask |= ~np.isfinite(arr.reshape(len(mask), -1)).all(axis=1)
    return [int(i) for i in state["id"][mask][:16]]


class GridAdapter:
    """grid_baseline.GridSimulation behind the run loop.

    The grid checks itself for NaN/Inf and speed every time.check_every steps (GridInstabilityError);
    its step functions are compiled before the clock starts (GridSimulation.warmup)."""
    solver = "grid"
    can_checkpoint = True
    modules = ("grid_baseline.simulation", "bench.statistics")

    @staticmethod
    def resolve_backend(backend: str) -> str:
        if backend != "auto":
            return backend
        import jax
        return "cuda" if jax.default_backend() == "gpu" else "cpu"

    @staticmethod
    def code_version() -> str:
        return code_version("grid")

    @staticmethod
    def instability_errors() -> tuple:
        from grid_baseline import GridInstabilityError
        return (GridInstabilityError, RunInstability)

    @staticmethod
    def preflight(spec: RunSpec) -> None:
        """Refuse a grid that cannot fit in host memory (CPU runs) before anything is allocated."""
        from grid_baseline.simulation import grid_shape
        from pbf_cuda.memory import available_memory
        from pbf_cuda.scene import SceneError
        shape = grid_shape(spec.scene, spec.cells_per_spacing, spec.resolution)
        cells = math.prod(shape)
        need = cells * GRID_BYTES_PER_CELL
        if GridAdapter.resolve_backend(spec.backend) == "cpu":
            avail = available_memory("cpu")
            if avail is not None and need > 0.8 * avail:
                raise SceneError(f"{spec.scene.name}: a grid of {cells:,} cells ({shape[0]} x {shape[1]} x "
                                 f"{shape[2]}) needs about {need / 2**30:.2f} GiB, {avail / 2**30:.2f} GiB "
                                 f"available; raise particles.spacing or lower cells_per_spacing")

    @staticmethod
    def expected_scene(spec: RunSpec):
        return None

    @staticmethod
    def create(spec: RunSpec):
        from grid_baseline import GridSimulation
        sim = GridSimulation(spec.scene, seed=spec.seed, cells_per_spacing=spec.cells_per_spacing,
                             resolution=spec.resolution, dtype=spec.dtype, device=GridAdapter._device(spec))
        sim.warmup()
        return sim

    @staticmethod
    def _device(spec: RunSpec):
        return {"auto": None, "cpu": "cpu", "cuda": "gpu"}[spec.backend]

    @staticmethod
    def load(path: Path, spec: RunSpec):
        from grid_baseline import GridSimulation
        sim = GridSimulation.load_snapshot(path, device=GridAdapter._device(spec), dtype=spec.dtype)
        sim.warmup()
        return sim

    @staticmethod
    def save(sim, path: Path) -> None:
        sim.save_snapshot(path)

    @staticmethod
    def state(sim) -> dict:
        """fields() plus cell_size (3,) m and origin (3,) m (what bench.statistics reads)."""
        fields = {k: np.asarray(v) for k, v in sim.fields().items()}
        fields["cell_size"] = np.asarray(sim.cell_size, dtype=np.float64)
        fields["origin"] = np.zeros(3)
        return fields

    @staticmethod
    def size(sim) -> int:
        return int(sim.n_cells)

    @staticmethod
    def step_row(sim) -> dict:
        return _flatten(sim.stats())

    @staticmethod
    def check(sim, spec: RunSpec, row: dict | None) -> None:
        """Nothing more to check: GridSimulation.step checks NaN/Inf and speed itself."""

    @staticmethod
    def diagnostics(sim, spec: RunSpec, state: dict):
        """(diagnostics row, vertical profiles) of the grid's fields."""
        from bench import statistics
        return statistics.grid_diagnostics(state, sim.scene), statistics.grid_profiles(state, sim.scene)


ADAPTERS = {"particles": ParticleAdapter, "grid": GridAdapter}


# ---- results -----------------------------------------------------------------------------------
@dataclass
class RunResult:
    """A finished run (stable or not), read from its directory."""
    path: Path
    info: dict
    cached: bool = False

    @classmethod
    def load(cls, path: str | Path, cached: bool = False) -> "RunResult":
        """The result in `path` (not verified: see verify_run and cached_result)."""
        path = Path(path)
        info = json.loads((path / "result.json").read_text())
        info.pop("manifest", None)
        info.pop("checksum", None)
        return cls(path, info, cached)

    def __getattr__(self, name):
        info = self.__dict__.get("info", {})
        if name in info:
            return info[name]
        raise AttributeError(name)

    def stats(self):
        import pandas as pd
        p = self.path / "stats.parquet"
        return pd.read_parquet(p) if p.exists() else pd.DataFrame()

    def profiles(self):
        import pandas as pd
        p = self.path / "profiles.parquet"
        return pd.read_parquet(p) if p.exists() else pd.DataFrame()

    def steps_table(self):
        import pandas as pd
        p = self.path / "steps.csv"
        return pd.read_csv(p) if p.exists() else pd.DataFrame()

    def timings(self) -> dict[str, dict]:
        import pandas as pd
        p = self.path / "timings.csv"
        if not p.exists():
            return {}
        return {r["phase"]: {"total_ms": r["total_ms"], "count": int(r["count"]), "mean_ms": r["mean_ms"]}
                for r in pd.read_csv(p).to_dict("records")}

    def snapshot_paths(self) -> list[Path]:
        return sorted((self.path / "snapshots").glob("step_*.npz"))

    def snapshot(self, step: int | None = None) -> dict[str, np.ndarray]:
        """A stored state (the last one when step is None), as a dict of numpy arrays."""
        paths = self.snapshot_paths()
        if step is not None:
            paths = [p for p in paths if p.name == f"step_{step:06d}.npz"]
        if not paths:
            raise FileNotFoundError(f"{self.path}: no snapshot{'' if step is None else f' at step {step}'}")
        with np.load(paths[-1]) as z:
            return {k: z[k] for k in z.files}

    def summary(self) -> dict:
        """Small JSON-able dict (what a dask task returns)."""
        return {**self.info, "path": str(self.path), "cached": self.cached}


# ---- verification and quarantine -----------------------------------------------------------------
# Files of a finished run that the manifest in result.json covers (all but the log, the lock and what
# only an unfinished attempt reads: progress.json, partial/).
_UNVERIFIED = {"log.txt", ".lock", "result.json", "progress.json"}


def _manifest(directory: Path) -> dict:
    """{relative path: {"bytes": n, "sha256": hex}} of the run's files."""
    out = {}
    for p in sorted(directory.rglob("*")):
        rel = p.relative_to(directory).as_posix()
        if not p.is_file() or rel in _UNVERIFIED or rel.startswith("partial/") or _is_temp(p):
            continue
        out[rel] = {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
    return out


def _is_temp(path: Path) -> bool:
    from pbf_cuda.files import is_temp
    return is_temp(path)


def _info_checksum(info: dict) -> str:
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
    if info.get("checksum") != _info_checksum(info):
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
    from pbf_cuda.files import fsync_dir
    fsync_dir(directory)
    fsync_dir(target)
    message = f"quarantined {', '.join(present)} of {directory.name} to {target} ({reason}); recomputing"
    with open(directory / "log.txt", "a") as fh:
        fh.write(f"{_now()} {message}\n")
    log.warning(message)
    return target


def _finished_files(directory: Path) -> list[str]:
    """Everything in a run directory but its log and lock (what a failed verification moves aside)."""
    return sorted(p.name for p in directory.iterdir() if p.name not in ("log.txt", ".lock"))


# ---- the run loop --------------------------------------------------------------------------------
def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@contextlib.contextmanager
def _locked(directory: Path):
    """Exclusive lock on the run directory, so two processes never run the same spec at once."""
    try:
        from filelock import FileLock  # portable: fcntl on POSIX, msvcrt on Windows (the harness extra)
    except ImportError:                # a bare POSIX machine without it (e.g. a GPU node): plain flock
        import fcntl
        with open(directory / ".lock", "a+") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)
        return
    with FileLock(str(directory / ".lock")):
        yield


def _merge_timings(base: dict, extra: dict) -> dict:
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
        with open(self.dir / "log.txt", "a") as fh:
            fh.write(f"{_now()} {message}\n")

    # -- progress bookkeeping ------------------------------------------------------------------
    def _resume(self):
        """(sim, progress) from checkpoint.npz + progress.json when they belong to this run and agree,
        else (None, fresh); whatever fails a check is moved to the quarantine folder (and logged)."""
        fresh = {"step": 0, "timings": {}, "step_wall_s": 0.0, "timed_wall_s": 0.0, "max_particles": 0}
        ckpt, prog = self.dir / "checkpoint.npz", self.dir / "progress.json"
        attempt = ["checkpoint.npz", "progress.json", "partial"]
        if not self.adapter.can_checkpoint or not (ckpt.exists() or prog.exists() or self.partial.exists()):
            return None, fresh
        if not (ckpt.exists() and prog.exists()):
            quarantine(self.dir, attempt, "checkpoint.npz and progress.json are not both present")
            return None, fresh
        try:
            progress = json.loads(prog.read_text())
            if not isinstance(progress, dict):
                raise ValueError("not a JSON object")
            step = progress["step"]
            for name in ("step_wall_s", "timed_wall_s", "max_particles"):
                float(progress[name])
            if not isinstance(progress["timings"], dict) or not isinstance(step, int):
                raise ValueError("bad timings or step")
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            quarantine(self.dir, attempt, f"progress.json unreadable: {type(exc).__name__}: {str(exc)[:80]}")
            return None, fresh
        if progress.get("key") != self.identity_key:
            quarantine(self.dir, attempt, "progress.json belongs to another run (key "
                                          f"{str(progress.get('key'))[:16]}, this run {self.identity_key[:16]})")
            return None, fresh
        if progress.get("checkpoint_sha256") != sha256_file(ckpt):
            quarantine(self.dir, attempt, "checkpoint.npz does not match the sha256 in progress.json")
            return None, fresh
        try:
            sim = self.adapter.load(ckpt, self.spec)
        except Exception as exc:  # a damaged checkpoint: start over, say so
            quarantine(self.dir, attempt, f"checkpoint unreadable ({type(exc).__name__}: {str(exc)[:80]})")
            return None, fresh
        expected = self.adapter.expected_scene(self.spec)
        if expected is not None and _scene_params(sim.scene) != _scene_params(expected):
            quarantine(self.dir, attempt, "the checkpoint's scene differs from the run's")
            return None, fresh
        if sim.step_count != step:
            quarantine(self.dir, attempt, f"checkpoint step {sim.step_count} != progress step {step}")
            return None, fresh
        try:
            rows = {name: self._partial_rows(name, step) for name in ("stats", "profiles", "steps")}
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            quarantine(self.dir, attempt, f"partial diagnostics unreadable: {type(exc).__name__}: {str(exc)[:80]}")
            return None, fresh
        self.resumed_rows = rows
        return sim, progress

    def _partial_rows(self, name: str, upto: int) -> list[dict]:
        path = self.partial / f"{name}.json"
        if not path.exists():
            return []
        rows = json.loads(path.read_text())
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise ValueError(f"partial/{name}.json: expected a list of rows")
        return [r for r in rows if r["step"] <= upto]

    def _checkpoint(self, sim, progress: dict) -> None:
        for name, rows in (("stats", self.rows), ("profiles", self.profile_rows), ("steps", self.step_rows)):
            atomic_write_json(self.partial / f"{name}.json", rows, sort_keys=False)  # keeps column order
        self.adapter.save(sim, self.dir / "checkpoint.npz")
        progress = {**progress, "key": self.identity_key,
                    "checkpoint_sha256": sha256_file(self.dir / "checkpoint.npz")}
        atomic_write_json(self.dir / "progress.json", progress)
        self.log(f"checkpoint at step {progress['step']}")

    # -- one diagnostics row -------------------------------------------------------------------
    def _record(self, sim, stats_row: dict | None, snapshot: bool) -> None:
        step = sim.step_count
        state = self.adapter.state(sim)
        bad = _nonfinite_fields(state)
        if bad:
            ids = _nonfinite_ids(state) if "id" in state else []
            raise RunInstability(step, f"NaN/Inf in {', '.join(bad)}", ids, step - 1)
        if snapshot:
            _save_npz(self.dir / "snapshots" / f"step_{step:06d}.npz",
                      {**state, "step": np.int64(step), "time_s": np.float64(sim.time)})
        if not self.spec.diagnostics:
            return
        import pandas as pd
        row, profiles = self.adapter.diagnostics(sim, self.spec, state)
        when = {"step": step, "time_s": float(sim.time)}
        extra = {k: v for k, v in (stats_row or {}).items() if k not in row}  # the shared statistics win
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
        if sim is None:
            self.refused = True            # a failure before the simulation exists leaves nothing behind
            sim = self.adapter.create(spec)
            self.refused = False
            self.log(f"start {spec.solver} {spec.scene.name}: {spec.total_steps} steps, seed {spec.seed}, "
                     f"backend {getattr(sim, 'backend', spec.backend)}")
        else:
            self.log(f"resume from checkpoint at step {resumed_from}")
        atomic_write_json(self.dir / "config.json", {
            "identity": self.identity, "key": self.identity_key,
            "checkpoint_every": spec.checkpoint_interval, "diagnostic_steps": spec.diagnostic_steps(),
            "snapshot_steps": spec.snapshot_steps(), "created": _now()})
        base_timings = progress["timings"]
        step_wall = float(progress["step_wall_s"])
        timed_wall = float(progress["timed_wall_s"])      # wall time of the steps after the warm-up
        max_particles = max(int(progress["max_particles"]), self.adapter.size(sim))
        diag_steps = set(spec.diagnostic_steps())
        snap_steps = set(spec.snapshot_steps())
        total = spec.total_steps
        chunk = 1 if spec.record_steps else 10
        failure = None
        from pbf_cuda.progress import progress_bar as tqdm
        bar = tqdm(total=total, initial=sim.step_count, desc=f"{spec.solver} {spec.scene.name}", unit="step",
                   disable=True if self.quiet else None, leave=False, dynamic_ncols=True)
        try:
            if sim.step_count == 0 and (0 in diag_steps or 0 in snap_steps):
                self._record(sim, self.adapter.step_row(sim), 0 in snap_steps)
            while sim.step_count < total:
                s0 = sim.step_count
                targets = [total, s0 + chunk] + [s for s in diag_steps | snap_steps if s > s0]
                if self.adapter.can_checkpoint:
                    targets.append((s0 // spec.checkpoint_interval + 1) * spec.checkpoint_interval)
                if s0 < spec.warmup_steps:
                    targets.append(spec.warmup_steps)
                n = min(targets) - s0
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
                if spec.record_steps:
                    self.step_rows.append(row)
                if s == spec.warmup_steps:
                    sim.reset_timings()
                    base_timings = {}
                if s in diag_steps or s in snap_steps:
                    self._record(sim, row, s in snap_steps)
                if self.adapter.can_checkpoint and s % spec.checkpoint_interval == 0 and s < total:
                    self._checkpoint(sim, {"step": s, "timings": _merge_timings(base_timings, sim.timings()),
                                           "step_wall_s": step_wall, "timed_wall_s": timed_wall,
                                           "max_particles": max_particles})
                bar.update(n)
                if self.on_step is not None:
                    self.on_step(s)
        except self.adapter.instability_errors() as exc:
            failure = exc
            self.log(f"UNSTABLE: {exc}")
        except BaseException as exc:
            self.log(f"interrupted at step {sim.step_count}: {exc!r}")
            raise
        finally:
            bar.close()
        timings = _merge_timings(base_timings, sim.timings())
        return self._finish(sim, failure, timings, step_wall, timed_wall, max_particles, resumed_from,
                            time.perf_counter() - started)

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
                from pbf_cuda.progress import progress_bar as tqdm
                tqdm.write(f"warning: {message}")
            self.rejects_logged = rejects
        self.rejects = rejects

    def _finish(self, sim, failure, timings, step_wall, timed_wall, max_particles, resumed_from,
                wall) -> RunResult:
        import pandas as pd
        spec = self.spec
        write_csv(pd.DataFrame([{"phase": k, **v} for k, v in sorted(timings.items())],
                               columns=["phase", "total_ms", "count", "mean_ms"]), self.dir / "timings.csv")
        if self.rows:
            write_parquet(pd.DataFrame(self.rows), self.dir / "stats.parquet")
        if self.profile_rows:
            write_parquet(pd.DataFrame(self.profile_rows), self.dir / "profiles.parquet")
        if self.step_rows:
            write_csv(pd.DataFrame(self.step_rows), self.dir / "steps.csv")
        from bench.environment import device_description
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
            "max_particles": max_particles if spec.solver == "particles" else None,
            "split_capacity_rejects": self.rejects if spec.solver == "particles" else None,
            "cells": max_particles if spec.solver == "grid" else None,
            "step_wall_s": step_wall, "wall_s": wall, "resumed_from": resumed_from,
            "timed_steps": max(0, sim.step_count - spec.warmup_steps) if failure is None else None,
            "step_ms": 1e3 * timed_wall / max(1, sim.step_count - spec.warmup_steps) if failure is None else None,
            "backend": backend, "device": device_description(backend),
            "code": self.identity["code"], "finished": _now(),
        }
        if failure is None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.dir / "progress.json")
        info["manifest"] = _manifest(self.dir)          # checked whenever the result is served
        info["checksum"] = _info_checksum(info)
        atomic_write_json(self.dir / "result.json", info)
        info = {k: v for k, v in info.items() if k not in ("manifest", "checksum")}
        self.log("finished " + ("stable" if failure is None else f"UNSTABLE at step {failure.step}")
                 + f" ({step_wall:.2f} s in steps)")
        return RunResult(self.dir, info, cached=False)


def execute(spec: RunSpec, root: str | Path | None = None, *, quiet: bool = False,
            on_step: Callable[[int], None] | None = None) -> RunResult:
    """Run `spec` (or return its stored result without any work).  See the module docstring.

    A stored result is served only when it passes verify_run; otherwise its files go to the quarantine
    folder (logged) and the run is computed again.  A run that cannot start (no such backend, too large
    for the memory) raises before its directory is made.

    on_step(step) is called after every chunk of steps (tests use it to simulate a crash)."""
    identity = spec.identity()
    key = spec.key(identity)
    directory = spec.directory(root, key)
    if (directory / "result.json").exists() and not verify_run(directory, key):
        return RunResult.load(directory, cached=True)
    ADAPTERS[spec.solver].preflight(spec)
    created = not directory.exists()
    directory.mkdir(parents=True, exist_ok=True)
    with _locked(directory):
        remove_stale_temps(directory, owned=True)       # we hold the lock: no writer is in here
        if (directory / "result.json").exists():
            problems = verify_run(directory, key)
            if not problems:
                return RunResult.load(directory, cached=True)
            quarantine(directory, _finished_files(directory), "; ".join(problems[:3]))
        attempt = _Run(spec, identity, key, directory, quiet, on_step)
        try:
            return attempt.run()
        except BaseException:
            if attempt.refused and created:
                shutil.rmtree(directory, ignore_errors=True)
            raise


def execute_summary(spec: RunSpec, root: str | Path | None = None) -> dict:
    """execute() for a worker process: quiet, returns the small summary dict."""
    return execute(spec, root, quiet=True).summary()


def cached_result(spec: RunSpec, root: str | Path | None = None) -> RunResult | None:
    """The stored result of `spec` when it is complete and passes verify_run, else None (execute then
    moves a damaged one aside and recomputes it)."""
    identity = spec.identity()
    key = spec.key(identity)
    directory = spec.directory(root, key)
    if (directory / "result.json").exists() and not verify_run(directory, key):
        return RunResult.load(directory, cached=True)
    return None
