"""Python API of the grid baseline (mirrors pbf_cuda.Simulation where it can).

    >>> from grid_baseline import GridSimulation
    >>> sim = GridSimulation("growing", resolution=(32, 32, 32))      # or cells_per_spacing=...
    >>> sim.step(100)
    >>> sim.fields()["cloud"].shape           # (nx, ny, nz) cell-centred numpy arrays
    >>> sim.state()["position"].shape         # the particle solver's format, one sample per cell
    >>> sim.stats(), sim.timings()

Precision: float64 on the CPU by default, float32 on a GPU by default (``dtype``
overrides either).  float64 needs jax's global ``jax_enable_x64`` flag: creating
a float64 simulation switches it on for the whole process (jax offers no
per-computation switch), and it stays on.  Every array of a float32 simulation
is created with an explicit float32 dtype, so float32 runs are unaffected by
the flag; other jax code in the same process will, however, default to 64-bit
types once a float64 simulation has been created.

Timing: in the default ``timing="fused"`` mode the whole step is one jitted
function (XLA fuses advection, physics and projection, so per-phase times do
not exist); ``timings()`` reports ``step`` (ms per step, measured over each
``step(n)`` call with ``block_until_ready`` at its end).  With
``timing="phases"`` the three phases are separate jitted functions, each
followed by ``block_until_ready``, and ``timings()`` reports ``advection``,
``projection``, ``physics`` and ``step`` (slightly slower: no cross-phase
fusion, one device sync per phase).
"""
from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np

import jax
import jax.numpy as jnp

from cloudpbf_io.export import fields_to_xarray
from cloudpbf_io.files import atomic_savez
from pbf_cuda.noise import noise_offset_for_seed
from pbf_cuda.protocol import InstabilityError
from pbf_cuda.scene import Scene, SceneError, load_scene, scene_from_dict

from .model import (BUDGET_TERMS, STATE_KEYS, advect, budget_terms, cell_centers, initial_state, make_aux,
                    params_from_scene, physics, pressure_project, step_with_budget)
from . import model
from .projection import _lower_face, relative_divergence

__all__ = ["GridSimulation", "InstabilityError", "grid_shape", "PHASES"]

PHASES = ("advection", "physics", "projection")
SNAPSHOT_VERSION = 1


def grid_shape(scene, cells_per_spacing: float = 1.0, resolution=None) -> tuple:
    """Cells per axis: round(L / (spacing / cells_per_spacing)) (>= 2), or `resolution` as given."""
    if resolution is not None:
        shape = tuple(int(n) for n in resolution)
        if len(shape) != 3 or min(shape) < 2:
            raise ValueError(f"resolution = {resolution!r}: expected three cell counts >= 2")
        return shape
    if not cells_per_spacing > 0:
        raise ValueError(f"cells_per_spacing = {cells_per_spacing!r}: must be > 0")
    h = scene.particles.spacing / float(cells_per_spacing)
    return tuple(max(2, int(round(L / h))) for L in scene.domain.size)


def _resolve_device(device):
    if device is None:
        return jax.devices()[0]
    if isinstance(device, str):
        name = {"cuda": "gpu"}.get(device, device)
        return jax.devices(name)[0]
    return device


def _resolve_dtype(dtype, device):
    if dtype is None:
        return jnp.float64 if device.platform == "cpu" else jnp.float32
    dt = jnp.dtype(dtype)
    if dt == jnp.float64:
        return jnp.float64
    if dt == jnp.float32:
        return jnp.float32
    raise ValueError(f"dtype = {dtype!r}: allowed float32, float64")


class GridSimulation:
    """One grid run of a cloud scene (a scene with an [atmosphere] section).

    scene: Scene, scene name or path.  seed: replaces atmosphere.noise_offset with
    noise_offset_for_seed(seed) (as the particle solver does).  cells_per_spacing /
    resolution: grid size (see :func:`grid_shape`).  dtype: 'float32' / 'float64' /
    None (float64 on CPU, float32 on GPU).  device: None (jax's default), 'cpu', 'gpu'
    or a jax Device.  timing: 'fused' or 'phases'.  check_every: steps between
    NaN / speed checks (default: the scene's time.check_every; 0 disables).
    cfl_target, max_substeps: advection sub-stepping (cfl_target None: the scene's time.cfl where it is > 0,
    else 0.8). The grid's step stays time.dt: the sub-steps keep advection within its CFL number, and every
    other term (heating, buoyancy, the phase change, the projection) is stable at the scene's steps, so the
    scene's CFL control acts on the advection here.
    """

    def __init__(self, scene, seed: int | None = None, cells_per_spacing: float = 1.0, resolution=None,
                 dtype=None, device=None, timing: str = "fused", check_every: int | None = None,
                 cfl_target: float | None = None, max_substeps: int = 16):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        if scene.atmosphere is None:
            raise SceneError(f"{scene.name}: the grid baseline runs cloud scenes; this scene has no "
                             f"[atmosphere] section")
        if seed is not None:
            scene = scene.replace(**{"particles.seed": int(seed),
                                     "atmosphere.noise_offset": noise_offset_for_seed(seed)})
        if timing not in ("fused", "phases"):
            raise ValueError(f"timing = {timing!r}: allowed 'fused', 'phases'")
        self.scene = scene
        self.device = _resolve_device(device)
        self.dtype = _resolve_dtype(dtype, self.device)
        if self.dtype == jnp.float64:
            jax.config.update("jax_enable_x64", True)   # global, see the module docstring
        self.shape = grid_shape(scene, cells_per_spacing, resolution)
        if cfl_target is None:
            cfl_target = scene.time.cfl if scene.time.cfl > 0.0 else 0.8
        self.params = params_from_scene(scene, self.shape, cfl_target=cfl_target, max_substeps=max_substeps)
        self.timing_mode = timing
        self.check_every = scene.time.check_every if check_every is None else int(check_every)
        p = self.params
        self._aux = jax.device_put(make_aux(p, self.dtype), self.device)
        self._state = jax.device_put(initial_state(p, self.dtype, scene.wave), self.device)
        self._state = _jitted("projection", p)(self._state, self._aux)
        self._compiled = set()
        self.compile_seconds = 0.0
        self._diag_fn = _jitted("diagnostics", p)
        self._health_fn = _jitted("health", p)
        self._nsub = jnp.asarray(1, jnp.int32)
        # Budget (see model.BUDGET_TERMS): the last step's terms and their running sums since step 0, K.
        self._budget_fn = _jitted("budget", p)
        self._budget_last = np.zeros(len(BUDGET_TERMS))
        self._budget_totals = jnp.zeros(len(BUDGET_TERMS), self.dtype)
        self._budget_valid = False
        self._step = 0
        self._last_good = 0
        self._timers = {}

    # ---- stepping ----------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance n steps. Raises InstabilityError (the state then holds the failing step)."""
        if n < 0:
            raise ValueError(f"n = {n}: must be >= 0")
        if n == 0:
            return
        if self.timing_mode == "phases":
            for _ in range(n):
                self._phased_step()
            return
        done = 0
        while done < n:
            chunk = n - done
            if self.check_every > 0:
                chunk = min(chunk, self.check_every - (self._step % self.check_every))
            step_fn = self._fn("step")
            t0 = time.perf_counter()
            s, a, nsub, totals = self._state, self._aux, self._nsub, self._budget_totals
            for _ in range(chunk):
                s, nsub, terms = step_fn(s, a)
                totals = totals + terms
            jax.block_until_ready(s)
            self._add_time("step", (time.perf_counter() - t0) * 1e3, chunk)
            self._state, self._nsub, self._budget_totals = s, nsub, totals
            self._budget_last, self._budget_valid = terms, True
            self._step += chunk
            done += chunk
            self._maybe_check()

    def _fn(self, name):
        """The jitted function of a phase, compiled on first use (not timed)."""
        fn = _jitted(name, self.params)
        if name not in self._compiled:
            # Every phase maps a state to a state of the same structure, shapes and dtypes: one call
            # on the current state (result discarded) compiles it, or finds it in jax's cache when an
            # earlier simulation of this process had the same parameters, grid and dtype.
            t0 = time.perf_counter()
            jax.block_until_ready(fn(self._state, self._aux))
            self.compile_seconds += time.perf_counter() - t0
            self._compiled.add(name)
        return fn

    def _phased_step(self):
        s, a = self._state, self._aux
        adv, phys, proj = self._fn("advection"), self._fn("physics"), self._fn("projection")
        t_start = time.perf_counter()
        t0 = t_start
        s, nsub = adv(s, a)
        jax.block_until_ready(s)
        t1 = time.perf_counter()
        s = phys(s, a)
        jax.block_until_ready(s)
        t2 = time.perf_counter()
        s = proj(s, a)
        jax.block_until_ready(s)
        t3 = time.perf_counter()
        self._add_time("advection", (t1 - t0) * 1e3, 1)
        self._add_time("physics", (t2 - t1) * 1e3, 1)
        self._add_time("projection", (t3 - t2) * 1e3, 1)
        self._add_time("step", (t3 - t_start) * 1e3, 1)
        terms = self._budget_fn(self._state, s, a)
        self._budget_totals = self._budget_totals + terms
        self._budget_last, self._budget_valid = terms, True
        self._state, self._nsub = s, nsub
        self._step += 1
        self._maybe_check()

    def _maybe_check(self):
        if self.check_every > 0 and self._step % self.check_every == 0:
            self.check()

    def check(self) -> None:
        """Raise InstabilityError on NaN/Inf or a speed above pbf.max_velocity."""
        finite, vmax = (np.asarray(x) for x in self._health_fn(self._state))
        if not bool(finite):
            raise InstabilityError(self._step, "NaN or Inf in the state", (), self._last_good)
        limit = self.scene.pbf.max_velocity
        if float(vmax) > limit:
            raise InstabilityError(self._step, f"speed {float(vmax):.4g} m/s above pbf.max_velocity = {limit}",
                                   (), self._last_good)
        self._last_good = self._step

    def _add_time(self, name, ms, count):
        t = self._timers.setdefault(name, [0.0, 0])
        t[0] += ms
        t[1] += count

    def warmup(self) -> float:
        """Compile the step functions of the current mode (without advancing the state); returns the
        seconds spent compiling so far (also in ``compile_seconds``, which includes one untimed
        evaluation per function; never part of timings())."""
        names = PHASES if self.timing_mode == "phases" else ("step",)
        for name in names:
            self._fn(name)
        return self.compile_seconds

    @property
    def step_count(self) -> int:
        return self._step

    @property
    def time(self) -> float:
        """Simulated time in s."""
        return self._step * self.params.dt

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    @property
    def size(self) -> int:
        """Cells (the simulation protocol's size)."""
        return self.n_cells

    @property
    def cell_size(self) -> tuple:
        return self.params.steps

    # ---- state -------------------------------------------------------------------------
    def raw_state(self) -> dict:
        """The model's own arrays (device): face velocities ux, uy, uz; theta (theta'), vapor, cloud."""
        return dict(self._state)

    def fields(self) -> dict[str, np.ndarray]:
        """Cell-centred host arrays of shape (nx, ny, nz): temperature T (K), potential_temperature
        theta = T + Gamma_d y (K), vapor, cloud (kg/kg), velocity (nx, ny, nz, 3) (m/s, face values
        averaged to the centre); plus the cell-centre coordinates x, y, z (1-D, m)."""
        p = self.params
        st = {k: np.asarray(v, dtype=np.float64) for k, v in self._state.items()}
        xc, yc, zc = cell_centers(p)
        t0 = model.environment_temperature(p, yc)[None, :, None]
        T = t0 + st["theta"]
        vel = np.stack([_center_np(st[k], a, p.periodic[a]) for a, k in enumerate(("ux", "uy", "uz"))], axis=-1)
        return {"temperature": T, "potential_temperature": T + p.dry_lapse_rate * yc[None, :, None],
                "vapor": st["vapor"], "cloud": st["cloud"], "velocity": vel, "x": xc, "y": yc, "z": zc}

    def to_xarray(self):
        """fields() as an ``xarray.Dataset``: temperature, potential_temperature, vapor, cloud and
        velocity_x/_y/_z on the cell-centre coordinates x, y, z (m, y up) with CF attributes (units,
        standard_name, long_name, axis), and the scalar coordinates time (s) and step.  The same
        layout as particles deposited by ``cloudpbf.export.particles_to_xarray``, so the two solvers
        compare directly in xarray.  Needs xarray (``pip install "cloudpbf[io]"``)."""
        return fields_to_xarray(self.fields(), time=self.time, step=self._step, attrs={
            "source": "cloudpbf grid_baseline (Eulerian, jax-cfd)", "solver": "grid", "scene": self.scene.name,
            "dtype": jnp.dtype(self.dtype).name, "device": device_kind(self.device)})

    def state(self) -> dict[str, np.ndarray]:
        """The particle solver's state format, one sample per cell centre: position (N,3) m, velocity (N,3)
        m/s, temperature K, vapor and cloud kg/kg, mass kg (rest_density * cell volume), level (0),
        kernel_radius m (kernel_ratio * cell size, the largest edge), id.  float32 like the particle solver."""
        f = self.fields()
        X, Y, Z = np.meshgrid(f["x"], f["y"], f["z"], indexing="ij")
        n = self.n_cells
        h = max(self.cell_size)
        return {
            "position": np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1).astype(np.float32),
            "velocity": f["velocity"].reshape(n, 3).astype(np.float32),
            "temperature": f["temperature"].ravel().astype(np.float32),
            "vapor": f["vapor"].ravel().astype(np.float32),
            "cloud": f["cloud"].ravel().astype(np.float32),
            "mass": np.full(n, self.scene.particles.rest_density * self.params.cell_volume, np.float32),
            "level": np.zeros(n, np.int32),
            "kernel_radius": np.full(n, self.scene.particles.kernel_ratio * h, np.float32),
            "id": np.arange(n, dtype=np.uint32),
        }

    def timings(self) -> dict[str, dict]:
        """Per-phase wall time in ms ({name: {total_ms, count, mean_ms}}); only phases that ran appear.
        fused mode: 'step'; phases mode: 'advection', 'physics', 'projection', 'step'."""
        return {k: {"total_ms": t, "count": c, "mean_ms": t / c} for k, (t, c) in self._timers.items() if c > 0}

    def reset_timings(self) -> None:
        self._timers = {}

    def stats(self) -> dict:
        """Diagnostics of the current state (device reductions; one small transfer)."""
        d = {k: float(v) for k, v in self._diag_fn(self._state, self._aux).items()}
        d["cloud_cells"] = int(round(d["cloud_cells"]))
        p = self.params
        d.update({
            "step": self._step, "time": self.time, "substeps": int(self._nsub), "cells": self.n_cells,
            "nx": self.shape[0], "ny": self.shape[1], "nz": self.shape[2],
            "dtype": jnp.dtype(self.dtype).name, "device": device_kind(self.device),
            "backend": "grid-" + self.device.platform,
        })
        if d["cloud_cells"] == 0:
            d["cloud_base"] = d["cloud_top"] = float("nan")
        d["cloud_fraction_volume"] = d["cloud_cells"] / self.n_cells
        d["dt"] = p.dt
        # The particle solver's budget columns (same names, meanings and units; docs/physics.md, Budgets):
        # last step's warming per process and running totals (K), plus heat_numerical (model.BUDGET_TERMS).
        last = np.asarray(self._budget_last, dtype=np.float64) if self._budget_valid else np.zeros(len(BUDGET_TERMS))
        totals = np.asarray(self._budget_totals, dtype=np.float64)
        for k, name in enumerate(BUDGET_TERMS):
            d[name] = float(last[k])
            d[name + "_total"] = float(totals[k])
        return d

    def budget_totals(self) -> dict:
        """Running sums since step 0 of the budget terms (K), keyed like stats()' ``*_total`` columns."""
        totals = np.asarray(self._budget_totals, dtype=np.float64)
        return {name + "_total": float(totals[k]) for k, name in enumerate(BUDGET_TERMS)}

    # ---- runs and snapshots -------------------------------------------------------------
    def run(self, steps: int | None = None, out_dir: str | Path | None = None, snapshot_every: int | None = None,
            stats_every: int = 1, progress=None) -> list[dict]:
        """Advance `steps` (default time.steps), recording stats() every `stats_every` steps (and at step 0);
        with out_dir: snapshots every `snapshot_every` (default time.snapshot_every) steps as
        out_dir/snapshot_XXXXXX.npz, stats as out_dir/stats.csv, timings as out_dir/timings.json."""
        steps = self.scene.time.steps if steps is None else int(steps)
        snap = self.scene.time.snapshot_every if snapshot_every is None else int(snapshot_every)
        out = Path(out_dir) if out_dir is not None else None
        rows = [self.stats()]
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            self.save(out / f"snapshot_{self._step:06d}.npz")
        end = self._step + steps
        while self._step < end:
            marks = [end]
            if stats_every > 0:
                marks.append((self._step // stats_every + 1) * stats_every)
            if out is not None and snap > 0:
                marks.append((self._step // snap + 1) * snap)
            self.step(min(marks) - self._step)
            if stats_every > 0 and self._step % stats_every == 0 or self._step == end:
                rows.append(self.stats())
                if progress is not None:
                    progress(rows[-1])
            if out is not None and snap > 0 and self._step % snap == 0:
                self.save(out / f"snapshot_{self._step:06d}.npz")
        if out is not None:
            write_stats_csv(rows, out / "stats.csv")
            (out / "timings.json").write_text(json.dumps(self.timings(), indent=1))
        return rows

    def save(self, path: str | Path) -> Path:
        """Write fields() (float32) and the raw state (model dtype) with metadata to an npz, atomically."""
        path = Path(path)
        f = self.fields()
        arrays = {k: (v.astype(np.float32) if v.ndim >= 3 else v) for k, v in f.items()}
        arrays.update({f"raw_{k}": np.asarray(v) for k, v in self._state.items()})
        meta = {"version": SNAPSHOT_VERSION, "solver": "grid_baseline", "scene": self.scene.to_dict(),
                "step": self._step, "time": self.time, "shape": list(self.shape),
                "dtype": jnp.dtype(self.dtype).name, "device": device_kind(self.device),
                "cfl_target": self.params.cfl_target, "max_substeps": self.params.max_substeps,
                "budget_totals": [float(x) for x in np.asarray(self._budget_totals, dtype=np.float64)]}
        return atomic_savez(path, meta, **arrays)

    @classmethod
    def load(cls, path: str | Path, device=None, dtype=None, timing: str = "fused") -> "GridSimulation":
        """Restore a run from save() (bit-exact when dtype and device kind match)."""
        with np.load(Path(path)) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta.get("version") != SNAPSHOT_VERSION:
                raise ValueError(f"{path}: snapshot version {meta.get('version')} != {SNAPSHOT_VERSION}")
            # A snapshot from before the forcing's scalars existed: clock from the step, sums from 0.
            raw = {k: z[f"raw_{k}"] if f"raw_{k}" in z.files else
                   np.asarray(meta["time"] if k == "time" else 0.0) for k in STATE_KEYS}
        scene = scene_from_dict(meta["scene"], source=str(path))
        sim = cls(scene, resolution=meta["shape"], dtype=dtype or meta["dtype"], device=device, timing=timing,
                  cfl_target=meta["cfl_target"], max_substeps=meta["max_substeps"])
        sim._state = jax.device_put({k: jnp.asarray(v, dtype=sim.dtype) for k, v in raw.items()}, sim.device)
        sim._step = sim._last_good = int(meta["step"])
        if meta.get("budget_totals") is not None:
            sim._budget_totals = jnp.asarray(meta["budget_totals"], dtype=sim.dtype)
        return sim


_JIT_CACHE: dict = {}
_PHASE_FUNCS = {"step": step_with_budget, "advection": advect, "physics": physics, "projection": pressure_project}


def _jitted(name: str, p):
    """One jitted function per (phase, Params), shared by simulations of equal parameters so that jax's
    compilation cache serves them (Params is a frozen, hashable dataclass)."""
    key = (name, p)
    fn = _JIT_CACHE.get(key)
    if fn is None:
        if name in _PHASE_FUNCS:
            f = _PHASE_FUNCS[name]
            fn = jax.jit(lambda s, a: f(s, a, p))
        elif name == "diagnostics":
            fn = jax.jit(lambda s, a: _diagnostics(s, a, p))
        elif name == "health":
            fn = jax.jit(_health)
        elif name == "budget":
            fn = jax.jit(lambda before, after, a: budget_terms(before, after, a, p))
        else:
            raise KeyError(name)
        _JIT_CACHE[key] = fn
    return fn


def device_kind(device) -> str:
    return getattr(device, "device_kind", None) or device.platform


def _center_np(u, axis, periodic):
    lower = np.roll(u, 1, axis=axis)
    if not periodic:
        idx = [slice(None)] * 3
        idx[axis] = 0
        lower[tuple(idx)] = 0.0
    return 0.5 * (u + lower)


def _health(state):
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in state.values()]))
    vmax = jnp.max(jnp.stack([jnp.max(jnp.abs(state[k])) for k in ("ux", "uy", "uz")]))
    return finite, vmax


def _diagnostics(state, aux, p):
    vol = p.cell_volume
    steps = p.steps
    yc = (jnp.arange(p.shape[1], dtype=state["theta"].dtype) + 0.5) * steps[1]
    t0 = aux["t0"]
    theta = state["theta"]
    w = state["cloud"]
    v = state["vapor"]
    cloudy = w > 1e-6
    ycol = jnp.broadcast_to(yc[None, :, None], w.shape)
    big = jnp.asarray(1e30, w.dtype)
    vel = (state["ux"], state["uy"], state["uz"])
    speed = jnp.max(jnp.stack([jnp.max(jnp.abs(u)) for u in vel]))
    column_cloudy = jnp.any(cloudy, axis=1)
    rho = p.rest_density
    # available potential energy k_b theta'^2 / (2 T0 (Gamma_d - Gamma(y))) of the stable levels
    stable = model.stratification(p, (np.arange(p.shape[1]) + 0.5) * steps[1])
    ape_scale = jnp.asarray(np.where(stable > 0.0, 0.5 / np.where(stable > 0.0, stable, 1.0), 0.0)[None, :, None],
                            theta.dtype)
    ke = 0.5 * rho * vol * sum(jnp.sum(0.5 * (u * u + _lower_face(u, a, p.periodic[a]) ** 2))
                               for a, u in enumerate(vel))
    return {
        # budget columns of the particle solver (kg, m, J, K; see model.BUDGET_TERMS)
        "mass": jnp.asarray(rho * vol * w.size, w.dtype),
        "mass_centre_height": jnp.mean(ycol),
        "kinetic_energy": ke,
        "potential_energy": rho * vol * jnp.sum(p.buoyancy / t0 * theta * theta * ape_scale),
        "total_water": jnp.sum(v + w) * vol * rho,    # kg (rest density times kg/kg times m^3)
        "total_vapor": jnp.sum(v) * vol,
        "total_cloud": jnp.sum(w) * vol,
        "mean_temperature": jnp.mean(t0 + theta),
        "mean_theta_perturbation": jnp.mean(theta),
        "heat": jnp.sum(theta - p.latent_heat * w) * vol,   # sum of T + Gamma_d y - Q w minus the environment's theta
        # running sums of the large-scale forcing (docs/cycling.md C4): total_water(t) = total_water(0)
        # + water_relaxation_total - rain_total
        "rain_total": state["rain_total"],
        "water_relaxation_total": state["water_relaxation_total"],
        "heat_relaxation_total": state["heat_relaxation_total"],
        # the BOMEX forcing's running sums (model.py, L1-L3): K m^3 and kg/kg m^3
        "heat_subsidence_total": state["heat_subsidence_total"],
        "heat_radiation_total": state["heat_radiation_total"],
        "water_subsidence_total": state["water_subsidence_total"],
        "water_tendency_total": state["water_tendency_total"],
        "max_cloud": jnp.max(w),
        "cloud_cells": jnp.sum(cloudy.astype(w.dtype)),
        "cloud_cover": jnp.mean(column_cloudy.astype(w.dtype)),
        "cloud_base": jnp.min(jnp.where(cloudy, ycol, big)),
        "cloud_top": jnp.max(jnp.where(cloudy, ycol, -big)),
        "max_speed": speed,
        "max_w_up": jnp.max(state["uy"]),
        "cfl": _courant(vel, p),
        "divergence_rel": relative_divergence(vel, steps, p.periodic),
    }


def _courant(vel, p):
    from .model import courant_sum
    return courant_sum(vel, p, p.dt)


STATS_COLUMNS = ("step", "time", "total_water", "total_vapor", "total_cloud", "rain_total", "water_relaxation_total",
                 "heat_relaxation_total", "heat", "mean_temperature",
                 "mean_theta_perturbation", "max_cloud", "cloud_cells", "cloud_fraction_volume", "cloud_cover",
                 "cloud_base", "cloud_top", "max_speed", "max_w_up", "cfl", "substeps", "divergence_rel", "cells",
                 "nx", "ny", "nz", "dt", "dtype", "device", "backend",
                 "mass", "mass_centre_height", "kinetic_energy", "potential_energy",
                 *BUDGET_TERMS, *(t + "_total" for t in BUDGET_TERMS))


def write_stats_csv(rows, path) -> Path:
    path = Path(path)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(STATS_COLUMNS), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow(r)
    return path
