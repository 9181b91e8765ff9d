"""The solvers behind the run loop.  Both solvers speak pbf_cuda.protocol.SimulationProtocol (step, state,
stats, timings, save, size; one InstabilityError); an adapter holds what still differs: how a run is
made and restored, what its memory check and its diagnostics are, and how a stored snapshot becomes
points (ParaView series) and a gridded Dataset (NetCDF / zarr).  ADAPTERS is the table cloudpbf.execution
and cloudpbf.export look them up in."""
from __future__ import annotations

import gc
import json
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from cloudpbf_io.export import fields_to_xarray
from pbf_cuda.memory import available_memory, check_memory, cuda_memory_in_use
from pbf_cuda.protocol import InstabilityError
from pbf_cuda.scene import SceneError
from pbf_cuda.simulation import Simulation, _resolve_backend, available_backends, seeded_scene

__all__ = ["ADAPTERS", "SOLVERS", "SolverAdapter", "ParticleAdapter", "GridAdapter", "InstabilityError", "flatten",
           "particles_to_xarray"]

STATS_VECTOR_AXES = "xyz"
GRID_BYTES_PER_CELL = 800    # fields, auxiliaries and jit buffers of the grid baseline in float64
DEPOSITED = ("temperature", "vapor", "cloud")   # particle fields deposited for a gridded export


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

    @staticmethod
    def device_bytes_in_use(spec) -> int | None:
        """Bytes in use on the run's accelerator now (context included), or None where there is none."""
        return None

    @staticmethod
    def snapshot_points(snap: dict) -> dict:
        """A stored snapshot as points with per-point fields (position (N, 3) m, ...), as
        cloudpbf_io.export.write_particle_series takes them; particles already are."""
        return snap

    @staticmethod
    def snapshot_dataset(snap: dict, scene, resolution=None, like=None):
        """A stored snapshot as an xarray.Dataset on cell centres (x, y, z), CF attributes on every field."""
        raise NotImplementedError


class ParticleAdapter(SolverAdapter):
    """pbf_cuda.Simulation behind the run loop."""
    solver = "particles"
    modules = ("pbf_cuda.simulation", "cloudpbf.statistics")

    @staticmethod
    def resolve_backend(backend: str) -> str:
        if backend != "auto":
            return backend
        return "cuda" if "cuda" in available_backends() else "cpu"

    @staticmethod
    def preflight(spec) -> None:
        """Refuse before anything is made: the backend must exist (RuntimeError), the run must fit in
        memory (pbf_cuda.SceneError naming the particle count and the memory needed)."""
        check_memory(seeded_scene(spec.scene, spec.seed), _resolve_backend(spec.backend))

    @staticmethod
    def expected_scene(spec):
        """The scene a checkpoint of this spec must hold."""
        return seeded_scene(spec.scene, spec.seed)

    @staticmethod
    def create(spec):
        return Simulation(spec.scene, backend=spec.backend, seed=spec.seed)

    @staticmethod
    def load(path: Path, spec):
        return Simulation.load(path, backend=ParticleAdapter.resolve_backend(spec.backend))

    @staticmethod
    def result_fields(largest: int, rejects: int) -> dict:
        return {"max_particles": largest, "split_capacity_rejects": rejects, "cells": None}

    @staticmethod
    def device_bytes_in_use(spec) -> int | None:
        """CUDA runs: total - free memory of the device (cudaMemGetInfo). The solver's arrays only grow and
        its temporary storage is cached, so after the run this is its peak."""
        if ParticleAdapter.resolve_backend(spec.backend) != "cuda":
            return None
        gc.collect()                   # a previous run's arrays are freed now, not during this run
        return cuda_memory_in_use()

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
        from cloudpbf import statistics  # harness extra (pandas, scipy)
        scene = sim.scene
        if not scene.thermodynamics:
            return {}, None
        grid = statistics.deposit_state(state, scene, spec.diagnostics_resolution)
        periodic = tuple(b == "periodic" for b in scene.domain.boundary)
        return statistics.diagnostics(grid, periodic=periodic), statistics.vertical_profiles(grid)

    @staticmethod
    def snapshot_dataset(snap: dict, scene, resolution=None, like=None):
        """The particles deposited with the poly6 kernel (see particles_to_xarray); needs an [atmosphere]."""
        if not scene.thermodynamics:
            raise ValueError(f"{scene.name}: NetCDF/zarr export deposits cloud fields and needs a scene with an "
                             "[atmosphere] section; use --format vtu or vtp for plain-fluid runs")
        return particles_to_xarray(snap, scene, resolution=resolution, like=like,
                                   time=float(snap.get("time_s", 0.0)), step=int(snap.get("step", 0)))


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
    modules = ("grid_baseline.simulation", "cloudpbf.statistics")

    @staticmethod
    def resolve_backend(backend: str) -> str:
        if backend != "auto":
            return backend
        import jax  # grid extra (jax)
        return "cuda" if jax.default_backend() == "gpu" else "cpu"

    @staticmethod
    def preflight(spec) -> None:
        """Refuse a grid that cannot fit in host memory (CPU runs) before anything is allocated."""
        from grid_baseline.simulation import grid_shape  # grid extra (jax)
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
        from grid_baseline import GridSimulation  # grid extra (jax)
        sim = GridSimulation(spec.scene, seed=spec.seed, cells_per_spacing=spec.cells_per_spacing,
                             resolution=spec.resolution, dtype=spec.dtype, device=GridAdapter._device(spec))
        sim.warmup()
        return sim

    @staticmethod
    def _device(spec):
        return {"auto": None, "cpu": "cpu", "cuda": "gpu"}[spec.backend]

    @staticmethod
    def load(path: Path, spec):
        from grid_baseline import GridSimulation  # grid extra (jax)
        sim = GridSimulation.load(path, device=GridAdapter._device(spec), dtype=spec.dtype)
        sim.warmup()
        return sim

    @staticmethod
    def state(sim) -> dict:
        """fields() plus cell_size (3,) m and origin (3,) m (what cloudpbf.statistics reads)."""
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
        from cloudpbf import statistics  # harness extra (pandas, scipy)
        return statistics.grid_diagnostics(state, sim.scene), statistics.grid_profiles(state, sim.scene)

    @staticmethod
    def snapshot_points(snap: dict) -> dict:
        """A grid snapshot as 'particles' at its cell centres (for .vtp/.vtu point series)."""
        x, y, z = (np.asarray(snap[k]) for k in "xyz")
        X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
        out = {"position": np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1),
               "step": snap.get("step", 0), "time_s": snap.get("time_s", 0.0)}
        for k, v in snap.items():
            arr = np.asarray(v)
            if arr.ndim == 3:
                out[k] = arr.ravel()
            elif arr.ndim == 4 and k == "velocity":
                out[k] = arr.reshape(-1, 3)
        return out

    @staticmethod
    def snapshot_dataset(snap: dict, scene, resolution=None, like=None):
        """The grid's own fields (resolution and like do not apply: the cells are the grid's)."""
        fields = {k: v for k, v in snap.items() if k not in ("step", "time_s", "origin")}
        return fields_to_xarray(fields, time=float(snap.get("time_s", 0.0)), step=int(snap.get("step", 0)), attrs={
            "source": "cloudpbf grid_baseline (Eulerian, jax-cfd)", "solver": "grid", "scene": scene.name})


def particles_to_xarray(state: Mapping[str, np.ndarray], scene, resolution=None, like=None,
                        time: float | None = None, step: int | None = None, attrs: Mapping | None = None):
    """Particles deposited on a grid as an ``xarray.Dataset`` (the grid baseline's layout).

    The grid: ``like`` (a Dataset whose ``x``, ``y``, ``z`` are cell centres of a regular grid from
    the origin, e.g. ``GridSimulation.to_xarray()``), else ``cloudpbf.statistics.grid_for_scene(scene,
    resolution)`` (default: one cell per particle spacing, the grid baseline's default).  Variables:
    ``density`` (kg/m^3) and the Shepard averages of temperature, vapor, cloud and velocity_x/y/z,
    with the CF attributes of :data:`cloudpbf_io.export.FIELD_ATTRS`."""
    from cloudpbf import statistics  # harness extra (pandas, scipy)
    origin = np.zeros(3)
    if like is not None:
        shape = tuple(int(like.sizes[k]) for k in "xyz")
        centres = [np.asarray(like[k].values, dtype=np.float64) for k in "xyz"]
        cell_size = np.array([c[1] - c[0] if len(c) > 1 else 2 * c[0] for c in centres])
        origin = np.array([c[0] for c in centres]) - cell_size / 2
        for k, c, d in zip("xyz", centres, cell_size):
            if not np.allclose(np.diff(c), d, rtol=1e-9, atol=0):
                raise ValueError(f"like: coordinate {k} is not a regular grid of cell centres")
    else:
        shape, cell_size = statistics.grid_for_scene(scene, resolution)
    fields = {k: state[k] for k in DEPOSITED if k in state}
    vel = np.asarray(state["velocity"], dtype=np.float64)
    for a, axis in enumerate("xyz"):
        fields[f"velocity_{axis}"] = vel[:, a]
    periodic = tuple(b == "periodic" for b in scene.domain.boundary)
    grid = statistics.deposit(state["position"], state["mass"], state["kernel_radius"], fields, shape, cell_size,
                              periodic=periodic, origin=origin)
    org = grid.pop("origin")
    size = grid.pop("cell_size")
    return fields_to_xarray(grid, cell_size=size, origin=org, time=time, step=step, attrs={
        "source": "cloudpbf particles (PBF) deposited with the poly6 kernel", "solver": "particles",
        "scene": scene.name, **dict(attrs or {})})


ADAPTERS = {"particles": ParticleAdapter, "grid": GridAdapter}
SOLVERS = tuple(ADAPTERS)
