"""Run identity: what a run is (RunSpec), the key that names its directory, and the code version.

A :class:`RunSpec` says what to run (solver, scene, backend, steps, seed, options).  Its key is the
sha256 of the scene's parameters (its description aside), the solver, the resolved backend, the
step count, the seed, the run options and the *code version*: a hash of the source files the run
executes (see :func:`code_sources`: the modules its solver adapter drives and all they import), so
editing the solver, the grid baseline or the statistics invalidates earlier runs of that solver.  The
compiled module carries the hash of the csrc sources it was built from and is refused when they differ
(pbf_cuda.buildinfo), so a stale build never runs.

The default root is ``$CLOUDPBF_RUNS``, else ``runs/`` in a source checkout, else the user cache folder
(:func:`default_root`).
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from cloudpbf.solvers import ADAPTERS, SOLVERS
from cloudpbf_io.files import json_default
from pbf_cuda.scene import Scene

__all__ = ["RunSpec", "effective_seed", "code_version", "code_sources", "default_root", "is_checkout", "REPO_ROOT", "RUN_FORMAT"]

REPO_ROOT = Path(__file__).resolve().parent.parent.parent
RUN_FORMAT = 2          # bump when the run directory layout or the loop's semantics change
MAX_STEPS = 10**7
SOURCE_SUFFIXES = (".py", ".h", ".hpp", ".cuh", ".cu", ".cpp", ".cc", ".c", ".inl")
FIRST_PARTY = ("cloudpbf_io", "pbf_cuda", "grid_baseline", "cloudpbf")   # the packages whose sources a code version reads
# Compiled modules and the source files (relative to the repository) they are built from.
NATIVE_SOURCES = {"pbf_cuda._core": ("pbf_cuda/csrc", "CMakeLists.txt")}


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
    import platformdirs  # harness extra (platformdirs)
    return Path(platformdirs.user_cache_dir("cloudpbf", appauthor=False)) / "runs"



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


def effective_seed(identity: dict) -> int:
    """The seed a run ran with (from its identity): its own, else the scene's particles.seed (-1: unknown)."""
    seed = identity.get("seed")
    if seed is None:
        seed = ((identity.get("scene") or {}).get("particles") or {}).get("seed", 0)
    try:
        return int(seed)
    except (TypeError, ValueError):
        return -1


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
    diagnostics: compute cloudpbf.statistics diagnostics (off for pure timing runs)
    warmup_steps: timings are reset after this many steps (first-step allocations left out)
    cells_per_spacing, resolution, dtype: grid options (see grid_baseline.GridSimulation)
    diagnostics_resolution: deposit grid (nx, ny, nz) for particle diagnostics (None: the statistics' default)
    end_time: simulated time, s, at which the run ends (the first step that reaches it is its last, with a
      diagnostics row and the final snapshot); `steps` is then an upper bound.  For runs whose step varies
      (time.cfl > 0), so that every setting covers the same simulated time.  None: the run is `steps` long
    diagnostic_times: simulated times, s, each bracketed by diagnostics rows: one at the first step that reaches
      it and, where the step is CFL-controlled (time.cfl > 0) and so cannot be planned to land on it, one at
      the last step before it; a series interpolated onto these times is then off by less than one step's
      change.  Empty: rows by step counts only
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
    end_time: float | None = None
    diagnostic_times: tuple = ()

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
        if self.end_time is not None and (isinstance(self.end_time, bool) or not isinstance(self.end_time, (int, float))
                                          or not 0.0 < float(self.end_time) < 1e12):
            raise ValueError(f"end_time = {self.end_time!r}: expected a positive number of seconds")
        times = tuple(self.diagnostic_times)
        if any(isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 < float(t) < 1e12 for t in times) \
                or any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError(f"diagnostic_times = {self.diagnostic_times!r}: expected increasing positive seconds")
        object.__setattr__(self, "diagnostic_times", tuple(float(t) for t in times))

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
        if self.end_time is not None:       # only when set: the keys of runs without it stay as they were
            out["end_time"] = float(self.end_time)
        if self.diagnostic_times:           # likewise
            out["diagnostic_times"] = list(self.diagnostic_times)
        return {**out, **ADAPTERS[self.solver].options(self)}

    def identity(self) -> dict:
        """All that is hashed into the key (the checkpoint interval is not: it does not change results)."""
        scene = self.scene.to_dict()
        scene["scene"] = {"name": self.scene.name}
        return {"format": RUN_FORMAT, "solver": self.solver, "scene": scene,
                "backend": ADAPTERS[self.solver].resolve_backend(self.backend),
                "steps": self.total_steps, "seed": self.seed, "options": self.options(),
                "code": code_version(self.solver)}

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
