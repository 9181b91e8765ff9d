"""The solvers behind the run loop.  Both solvers speak pbf_cuda.protocol.SimulationProtocol (step, state,
stats, timings, save, size; one InstabilityError); an adapter holds what still differs: how a run is
made and restored, what its memory check and its diagnostics are.  ADAPTERS is the table bench.execution
looks them up in."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pbf_cuda.protocol import InstabilityError

__all__ = ["ADAPTERS", "SOLVERS", "SolverAdapter", "ParticleAdapter", "GridAdapter", "InstabilityError", "flatten"]

STATS_VECTOR_AXES = "xyz"
GRID_BYTES_PER_CELL = 800    # fields, auxiliaries and jit buffers of the grid baseline in float64


def flatten(values: dict) -> dict:
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


def scene_params(scene) -> dict:
    """A scene's parameters without its name and description (what a checkpoint must match)."""
    data = scene.to_dict()
    data.pop("scene", None)
    return json.loads(json.dumps(data, sort_keys=True, default=float))


def nonfinite_fields(arrays: dict) -> list[str]:
    return [name for name, arr in arrays.items()
            if isinstance(arr, np.ndarray) and arr.dtype.kind == "f" and not np.all(np.isfinite(arr))]


class SolverAdapter:
    """What the run loop does the same way for every solver (through the simulation protocol)."""
    solver = ""
    can_checkpoint = True
    modules: tuple = ()          # the modules whose sources (and imports) decide a result (code_version)

    @staticmethod
    def options(spec) -> dict:
        """The spec's options that only this solver reads (they enter the run's key)."""
        return {}

    @staticmethod
    def expected_scene(spec):
        """The scene a checkpoint of this spec must hold (None: not checked)."""
        return None

    @staticmethod
    def save(sim, path: Path) -> None:
        sim.save(path)

    @staticmethod
    def state(sim) -> dict:
        return sim.state()

    @staticmethod
    def size(sim) -> int:
        return int(sim.size)

    @staticmethod
    def step_row(sim) -> dict:
        return flatten(sim.stats())

    @staticmethod
    def check(sim, spec, row: dict | None) -> None:
        """Checks of the harness beyond the solver's own (which raise InstabilityError from step())."""

    @staticmethod
    def result_fields(largest: int, rejects: int) -> dict:
        """The size fields of result.json: the largest size the run reached, and splits turned away."""
        return {}


class ParticleAdapter(SolverAdapter):
    """pbf_cuda.Simulation behind the run loop."""
    solver = "particles"
    modules = ("pbf_cuda.simulation", "bench.statistics")

    @staticmethod
    def resolve_backend(backend: str) -> str:
        if backend != "auto":
            return backend
        from pbf_cuda.simulation import available_backends
        return "cuda" if "cuda" in available_backends() else "cpu"

    @staticmethod
    def preflight(spec) -> None:
        """Refuse before anything is made: the backend must exist (RuntimeError), the run must fit in
        memory (pbf_cuda.SceneError naming the particle count and the memory needed)."""
        from pbf_cuda.memory import check_memory
        from pbf_cuda.simulation import _resolve_backend, seeded_scene
        check_memory(seeded_scene(spec.scene, spec.seed), _resolve_backend(spec.backend))

    @staticmethod
    def expected_scene(spec):
        """The scene a checkpoint of this spec must hold."""
        from pbf_cuda.simulation import seeded_scene
        return seeded_scene(spec.scene, spec.seed)

    @staticmethod
    def create(spec):
        from pbf_cuda.simulation import Simulation
        return Simulation(spec.scene, backend=spec.backend, seed=spec.seed)

    @staticmethod
    def load(path: Path, spec):
        from pbf_cuda.simulation import Simulation
        return Simulation.load(path, backend=ParticleAdapter.resolve_backend(spec.backend))

    @staticmethod
    def result_fields(largest: int, rejects: int) -> dict:
        return {"max_particles": largest, "split_capacity_rejects": rejects, "cells": None}

    @staticmethod
    def check(sim, spec, row: dict | None) -> None:
        """Raise InstabilityError for NaN in stats() or particles outside a wall axis (by more than h0)."""
        row = row if row is not None else flatten(sim.stats())
        step = sim.step_count
        bad = [k for k, v in row.items() if isinstance(v, float) and not math.isfinite(v)]
        if bad:
            raise InstabilityError(step, f"NaN/Inf in solver statistics ({', '.join(bad)})",
                                 nonfinite_ids(sim.state()), step - 1)
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
            raise InstabilityError(step, f"particles escaping the domain: {name} in [{lo:.6g}, {hi:.6g}] m, "
                                       f"outside the walls [0, {size:g}] m", ids[:16], step - 1)

    @staticmethod
    def diagnostics(sim, spec, state: dict):
        """(diagnostics row, vertical profiles) of a particle state, deposited once on the statistics grid.
        Plain-fluid scenes have no cloud statistics: their rows hold the solver's stats() only."""
        from bench import statistics
        scene = sim.scene
        if not scene.thermodynamics:
            return {}, None
        grid = statistics.deposit_state(state, scene, spec.diagnostics_resolution)
        periodic = tuple(b == "periodic" for b in scene.domain.boundary)
        return statistics.diagnostics(grid, periodic=periodic), statistics.vertical_profiles(grid)


def nonfinite_ids(state: dict) -> list[int]:
    mask = np.zeros(len(state["id"]), dtype=bool)
    for name, arr in state.items():
        if name != "id" and isinstance(arr, np.ndarray) and arr.dtype.kind == "f" and len(arr) == len(mask):
            mask |= ~np.isfinite(arr.reshape(len(mask), -1)).all(axis=1)
    return [int(i) for i in state["id"][mask][:16]]


class GridAdapter(SolverAdapter):
    """grid_baseline.GridSimulation behind the run loop.

    The grid checks itself for NaN/Inf and speed every time.check_every steps (InstabilityError);
    its step functions are compiled before the clock starts (GridSimulation.warmup)."""
    solver = "grid"
    modules = ("grid_baseline.simulation", "bench.statistics")

    @staticmethod
    def resolve_backend(backend: str) -> str:
        if backend != "auto":
            return backend
        import jax
        return "cuda" if jax.default_backend() == "gpu" else "cpu"

    @staticmethod
    def preflight(spec) -> None:
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
    def options(spec) -> dict:
        return {"cells_per_spacing": float(spec.cells_per_spacing),
                "resolution": list(spec.resolution) if spec.resolution else None, "dtype": spec.dtype}

    @staticmethod
    def create(spec):
        from grid_baseline import GridSimulation
        sim = GridSimulation(spec.scene, seed=spec.seed, cells_per_spacing=spec.cells_per_spacing,
                             resolution=spec.resolution, dtype=spec.dtype, device=GridAdapter._device(spec))
        sim.warmup()
        return sim

    @staticmethod
    def _device(spec):
        return {"auto": None, "cpu": "cpu", "cuda": "gpu"}[spec.backend]

    @staticmethod
    def load(path: Path, spec):
        from grid_baseline import GridSimulation
        sim = GridSimulation.load(path, device=GridAdapter._device(spec), dtype=spec.dtype)
        sim.warmup()
        return sim

    @staticmethod
    def state(sim) -> dict:
        """fields() plus cell_size (3,) m and origin (3,) m (what bench.statistics reads)."""
        fields = {k: np.asarray(v) for k, v in sim.fields().items()}
        fields["cell_size"] = np.asarray(sim.cell_size, dtype=np.float64)
        fields["origin"] = np.zeros(3)
        return fields

    @staticmethod
    def result_fields(largest: int, rejects: int) -> dict:
        return {"max_particles": None, "split_capacity_rejects": None, "cells": largest}

    @staticmethod
    def diagnostics(sim, spec, state: dict):
        """(diagnostics row, vertical profiles) of the grid's fields."""
        from bench import statistics
        return statistics.grid_diagnostics(state, sim.scene), statistics.grid_profiles(state, sim.scene)


ADAPTERS = {"particles": ParticleAdapter, "grid": GridAdapter}
SOLVERS = tuple(ADAPTERS)
