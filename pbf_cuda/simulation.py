"""Python API of the particle solver.

    >>> from pbf_cuda import Simulation
    >>> sim = Simulation("dam_break", backend="auto")
    >>> sim.step(100)
    >>> sim.state()["position"].shape
    (12000, 3)
    >>> sim.timings()["pbf"]["mean_ms"]

State arrays are structure-of-arrays on the backend's device; :meth:`state`
copies them to numpy, :meth:`device_arrays` gives zero-copy DLPack views.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from cloudpbf_io.files import atomic_savez, read_meta

from . import initial_state
from .kernels import reference_gradient_norm2
from .noise import noise_offset_for_seed
from .protocol import InstabilityError
from .memory import check_memory, particle_slots
from .scene import Scene, load_scene, scene_from_dict

__all__ = ["Simulation", "InstabilityError", "available_backends"]

CHECKPOINT_VERSION = 1
# The running sums of stats() a checkpoint carries, in the solver's order (StepBudget::totals).
BUDGET_TOTALS = ("heat_source", "heat_latent", "heat_adiabatic", "heat_smoothing", "heat_relaxation",
                 "water_relaxation", "water_rain", "heat_subsidence", "heat_radiation", "water_subsidence",
                 "water_tendency")


def _core():
    """The compiled module, refused (StaleBuildError) when built from other sources than pbf_cuda/csrc."""
    from .buildinfo import checked_core
    return checked_core()


def seeded_scene(scene: Scene, seed: int | None) -> Scene:
    """The scene a Simulation with `seed` runs: particles.seed and the noise offset follow the seed."""
    if seed is None:
        return scene
    return scene.replace(**{"particles.seed": int(seed),
                            **({"atmosphere.noise_offset": noise_offset_for_seed(seed)}
                               if scene.thermodynamics else {})})


def available_backends() -> list[str]:
    """Backends usable on this machine: 'cpu' always, 'cuda' when built, a device exists and the build
    carries kernels for its compute capability (see :mod:`pbf_cuda.cuda_arch`)."""
    from .cuda_arch import cuda_problem
    out = ["cpu"]
    if cuda_problem() is None:
        out.append("cuda")
    return out


def _resolve_backend(backend: str) -> str:
    backends = available_backends()
    if backend == "auto":
        return "cuda" if "cuda" in backends else "cpu"
    if backend not in ("cpu", "cuda"):
        raise ValueError(f"backend = {backend!r}: allowed 'auto', 'cpu', 'cuda'")
    if backend not in backends:
        from .cuda_arch import cuda_problem
        raise RuntimeError(f"backend 'cuda' is not available: {cuda_problem()}")
    return backend


# The solver parameters computed from the scene, and the scene fields each one reads. Every other
# parameter is copied unchanged from the scene field declared beside it in csrc/params.h (PBF_PARAMS).
DERIVED = {
    "periodic": ("domain.boundary",),
    "spacing": ("domain.size", "particles.spacing"),
    "h0": ("particles.spacing", "particles.kernel_ratio"),
    "mass0": ("domain.size", "particles.spacing", "particles.kernel_ratio", "particles.rest_density"),
    "relaxation": ("pbf.relaxation", "domain.size", "particles.spacing", "particles.kernel_ratio",
                   "particles.rest_density"),
    "lambda_ref": ("domain.size", "particles.spacing", "particles.kernel_ratio", "particles.rest_density"),
    "velocity_projection": ("pbf.projection",),
    "thermodynamics": ("atmosphere",),
    "large_scale_forcing": ("atmosphere", "forcing"),
    "saturation": ("atmosphere.saturation_a", "atmosphere.saturation_b", "atmosphere.saturation_c"),
    "heating_layer": ("domain.size", "particles.spacing"),
    "vapor_relative": ("atmosphere.vapor_profile",),
    "kappa": ("atmosphere", "smoothing.kappa", "smoothing.fields"),
    "smoothing_beta": ("atmosphere", "smoothing.kappa", "smoothing.fields", "smoothing.epsilon", "domain.size",
                       "particles.spacing", "particles.kernel_ratio", "particles.rest_density"),
    "smooth_fields": ("smoothing.fields",),
    "max_level": ("adaptive.enabled", "adaptive.max_level"),
    "pair_kernel_mean_radius": ("adaptive.pair_kernel",),
    "lookahead_height": ("adaptive.criterion", "adaptive.lookahead_height"),
    "refine_warm_air": ("adaptive.criterion",),
    "heating_time": ("adaptive.criterion", "adaptive.heating_time"),
    "capacity": (),            # of the particle count, not of the scene alone: memory.particle_slots
}

# The scene fields that no solver parameter reads, and what reads them instead.
OUTSIDE_SOLVER = {
    "particles.fill_min": "initial_state: the filled box",
    "particles.fill_max": "initial_state: the filled box",
    "particles.max_speed": "initial_state: initial velocities",
    "particles.seed": "initial_state: initial velocities",
    "time.steps": "the harness: run length",
    "time.snapshot_every": "the harness: snapshots",
    "wave.amplitude": "initial_state: the initial gravity wave",
    "wave.modes_x": "initial_state: the initial gravity wave",
    "wave.modes_y": "initial_state: the initial gravity wave",
    "adaptive.capacity": "Simulation: the capacity parameter, adaptive.capacity times the particle count",
}


def derived_params(scene: Scene, capacity: int, core=None) -> dict:
    """The values of the DERIVED solver parameters for `scene` (SI units, as csrc/params.h states them)."""
    core = core or _core()
    out = {}
    h0 = scene.kernel_radius
    rho0 = scene.particles.rest_density
    # m0 such that a full lattice neighbourhood has density exactly rho0 (eq. 1).
    m0 = initial_state.lattice_mass(scene)
    d = float(np.prod(initial_state.lattice_spacings(scene)) ** (1.0 / 3.0))   # mean lattice spacing
    out["periodic"] = [b == "periodic" for b in scene.domain.boundary]
    out["spacing"] = d
    out["h0"] = h0
    out["mass0"] = m0
    grad2 = reference_gradient_norm2(h0, d, m0, rho0)   # sum_k |grad_k C_i|^2 / m_k of a full lattice
    out["relaxation"] = scene.pbf.relaxation * grad2
    out["lambda_ref"] = 1.0 / grad2                     # lambda of a unit constraint violation
    out["velocity_projection"] = scene.pbf.projection == "velocity"
    out["thermodynamics"] = scene.thermodynamics
    out["large_scale_forcing"] = scene.large_scale_forcing
    if scene.thermodynamics:
        a = scene.atmosphere
        out["saturation"] = [a.saturation_a, a.saturation_b, a.saturation_c]
        # Ground heating (eq. 5) weighs each particle by the part of its layer below heating_depth, so the
        # column's heat input S_e * heating_depth does not depend on the particle spacing (thermodynamics.h).
        out["heating_layer"] = float(initial_state.lattice_spacings(scene)[1])
        out["vapor_relative"] = a.vapor_profile == "relative"
        sm = scene.smoothing
        kappa = sm.kappa if scene.smoothing_active else 0.0
        out["kappa"] = kappa
        # kappa as the solver holds it (float32) times beta_0 of a full lattice (eq. 17)
        out["smoothing_beta"] = float(np.float32(kappa)) * core.reference_smoothing_beta(h0, d, m0, rho0, sm.epsilon)
        out["smooth_fields"] = [f in sm.fields for f in ("temperature", "vapor", "cloud")]
    ad = scene.adaptive
    out["max_level"] = ad.max_level if ad.enabled else 0
    out["pair_kernel_mean_radius"] = ad.pair_kernel == "mean_radius"
    out["lookahead_height"] = ad.lookahead_height if ad.criterion == "lookahead" else 0.0
    out["refine_warm_air"] = ad.criterion in ("thermal", "heated")
    out["heating_time"] = ad.heating_time if ad.criterion == "heated" else 0.0
    out["capacity"] = capacity
    return out


def build_params(scene: Scene, capacity: int):
    """Flatten a Scene into the solver's parameter struct: the scene fields csrc/params.h names are copied,
    the DERIVED parameters computed (without an [atmosphere] the thermodynamic ones keep their defaults,
    which the solver never reads)."""
    core = _core()
    p = core.Params()
    for name, _type, length, source in core.declared_params():
        if not source:
            continue
        section, key = source.split(".")
        values = getattr(scene, section)
        if values is not None:              # an optional section ([atmosphere]) the scene leaves out
            value = getattr(values, key)
            setattr(p, name, list(value) if length else value)
    for name, value in derived_params(scene, capacity, core).items():
        setattr(p, name, value)
    return p


class DeviceArray:
    """A zero-copy view of one solver array (the solver must outlive it)."""

    def __init__(self, solver, name: str):
        self._solver = solver
        self.name = name
        ptr, n, cols, typestr, on_device = solver.view_info(name)
        self.shape = (n, cols) if cols > 1 else (n,)
        self.on_device = bool(on_device)
        interface = {"shape": self.shape, "typestr": typestr, "data": (ptr, False), "version": 3,
                     "strides": None}
        if self.on_device:
            self.__cuda_array_interface__ = dict(interface, stream=None)
        else:
            self.__array_interface__ = interface

    def __dlpack__(self, stream=None, **kwargs):
        return self._solver.view(self.name)

    def __dlpack_device__(self):
        return (2, 0) if self.on_device else (1, 0)   # kDLCUDA / kDLCPU, device 0


class Simulation:
    """One particle simulation of a scene on one backend ('cpu' or 'cuda')."""

    def __init__(self, scene: Scene | str | Path, backend: str = "auto", seed: int | None = None,
                 _state: dict | None = None):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        scene = seeded_scene(scene, seed)
        self.scene = scene
        self.backend = _resolve_backend(backend)
        # Refuse what cannot fit before anything is allocated (SceneError naming count and memory).
        check_memory(scene, self.backend, fluid=len(_state["fluid"]["id"]) if _state else None,
                     boundary=len(_state["boundary"]["position"]) if _state else None)
        fluid = _state["fluid"] if _state else initial_state.fluid_particles(scene)
        boundary = _state["boundary"] if _state else initial_state.boundary_particles(scene)
        capacity = particle_slots(scene, len(fluid["id"]))
        self.capacity = capacity
        self._params = build_params(scene, capacity)
        core = _core()
        try:
            self._solver = core.Solver(self._params, self.backend)
        except MemoryError as exc:
            raise MemoryError(f"{self.backend}: not enough memory for {capacity} particle slots "
                              f"({scene.name}); lower the particle count or adaptive.capacity") from exc
        self._solver.set_boundary(boundary["position"], boundary["temperature"], boundary["vapor"])
        self._solver.set_fluid(fluid["position"], fluid["velocity"], fluid["temperature"], fluid["vapor"],
                               fluid["cloud"], fluid["mass"], fluid["id"])
        if _state:
            self._solver.set_clock(int(_state["step"]), float(_state["time"]), int(_state["next_id"]))
            if _state.get("dt") is not None:   # the CFL-controlled step in use when the checkpoint was written
                self._solver.set_time_step(float(_state["dt"]))
            if _state.get("neighbor_row_width"):
                self._solver.set_neighbor_row_width(int(_state["neighbor_row_width"]))
            if _state.get("budget_totals") is not None:
                self._solver.set_budget_totals([float(x) for x in _state["budget_totals"]])
            impulse = _state["fluid"].get("projection_impulse")
            if impulse is not None and scene.pbf.projection == "velocity":
                self._solver.set_projection_impulse(np.ascontiguousarray(impulse, np.float32))

    # ---- stepping ----------------------------------------------------------------------
    def step(self, n: int = 1, progress=None) -> None:
        """Advance n steps. Raises InstabilityError (the state then holds the failing step).

        ``progress``: None (silent), ``True`` (a progress bar on stderr, plain periodic lines when
        stderr is not a terminal) or a callable ``progress(done, total)`` called after every chunk of
        steps (about 1% of ``n``, at least one step).  With a progress report the steps run in
        chunks; the result is the same bits as one call."""
        if n < 0:
            raise ValueError(f"n = {n}: must be >= 0")
        n = int(n)
        if progress is None or progress is False or n == 0:
            self._step_chunk(n)
            return
        report = progress
        reporter = None
        if progress is True:
            from cloudpbf_io.progress import Progress
            reporter = Progress(total=n, desc=f"{self.scene.name} ({self.backend})", unit="step")
            report = lambda done, total: reporter.update_to(done)   # noqa: E731
        elif not callable(progress):
            raise TypeError(f"progress = {progress!r}: expected None, True or a callable(done, total)")
        chunk = max(1, n // 100)
        done = 0
        try:
            while done < n:
                k = min(chunk, n - done)
                self._step_chunk(k)
                done += k
                report(done, n)
        finally:
            if reporter is not None:
                reporter.close()

    def _step_chunk(self, n: int) -> None:
        try:
            self._solver.step(int(n))
        except RuntimeError as exc:
            msg = str(exc)
            if msg.startswith("unstable|"):
                _, step, last_good, reason, ids = msg.split("|", 4)
                raise InstabilityError(int(step), reason, [int(i) for i in ids.split(",") if i],
                                       int(last_good)) from None
            raise

    def to_pyvista(self, kind: str = "polydata"):
        """The particles as a pyvista dataset of points (``"polydata"`` for .vtp, ``"unstructured"``
        for .vtu): every array of :meth:`state` as point data, units in the field data
        (``<name>_unit``), the simulated time as ``TimeValue`` (s).  ``mesh.save("particles.vtp")``
        writes a file ParaView opens.  Needs pyvista (``pip install "cloudpbf[viz]"``)."""
        from cloudpbf_io.export import state_to_pyvista
        return state_to_pyvista(self.state(), kind, time=self.time, step=self.step_count,
                                scene_name=self.scene.name)

    def adapt(self) -> None:
        """Run only the split/merge phase (section 5.2) on the current state."""
        self._solver.adapt_now()

    @classmethod
    def from_arrays(cls, scene: Scene | str, fluid: dict, boundary: dict | None = None,
                    backend: str = "auto") -> "Simulation":
        """A simulation from given particle arrays (keys as `state()`: position, velocity, mass, id,
        temperature, vapor, cloud; optionally projection_impulse, the velocity projection's last impulse
        mu per particle, kg m^2/s, which warm-starts the next projection); boundary particles from the scene
        unless given."""
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        n = len(fluid["position"])
        zeros = np.zeros(n, np.float32)
        arrays = {
            "position": np.ascontiguousarray(fluid["position"], np.float32),
            "velocity": np.ascontiguousarray(fluid["velocity"], np.float32),
            "mass": np.ascontiguousarray(fluid["mass"], np.float32),
            "id": np.ascontiguousarray(fluid.get("id", np.arange(n)), np.uint32),
        }
        for key in ("temperature", "vapor", "cloud"):
            arrays[key] = np.ascontiguousarray(fluid.get(key, zeros), np.float32)
        if fluid.get("projection_impulse") is not None:
            if scene.pbf.projection != "velocity":
                raise ValueError(f"from_arrays: fluid['projection_impulse'] is the velocity projection's; scene "
                                 f"'{scene.name}' has pbf.projection = '{scene.pbf.projection}' (allowed with "
                                 f"'velocity' only)")
            arrays["projection_impulse"] = np.ascontiguousarray(fluid["projection_impulse"], np.float32)
        for key, arr in arrays.items():
            if len(arr) != n:
                raise ValueError(f"from_arrays: fluid['{key}'] has {len(arr)} rows, position has {n}")
        mass = arrays["mass"]
        if n and not (np.all(np.isfinite(mass)) and mass.min() > 0.0):
            raise ValueError("from_arrays: fluid['mass'] must be finite and > 0 kg for every particle")
        if "id" in fluid and n:
            ids = np.asarray(fluid["id"])
            if ids.dtype.kind not in "ui" or ids.min() < 0 or ids.max() > np.iinfo(np.uint32).max - 1:
                raise ValueError(f"from_arrays: fluid['id'] must be integers in [0, {np.iinfo(np.uint32).max - 1}]")
            unique, counts = np.unique(arrays["id"], return_counts=True)
            if len(unique) != n:
                dup = unique[counts > 1]
                raise ValueError(f"from_arrays: fluid['id'] holds {len(dup)} duplicated id(s) "
                                 f"({', '.join(map(str, dup[:8]))}{', ...' if len(dup) > 8 else ''}); ids must be unique")
        boundary = boundary if boundary is not None else initial_state.boundary_particles(scene)
        state = {"fluid": arrays, "boundary": boundary, "step": 0, "time": 0.0, "next_id": int(arrays["id"].max()) + 1 if n else 0}
        return cls(scene, backend=backend, _state=state)

    @property
    def step_count(self) -> int:
        return self._solver.step_count()

    @property
    def time(self) -> float:
        """Simulated time in s."""
        return self._solver.time()

    @property
    def time_step(self) -> float:
        """The step in use, s: the scene's time.dt, or the CFL-controlled step (time.cfl > 0)."""
        return self._solver.time_step()

    @property
    def n_particles(self) -> int:
        return self._solver.size()

    @property
    def size(self) -> int:
        """Particles (the simulation protocol's size)."""
        return self.n_particles

    # ---- state -------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """Host copies: position (N,3) m, velocity (N,3) m/s, temperature K, vapor and cloud kg/kg,
        mass kg, level, kernel_radius m, id. Empty thermodynamic arrays in plain-fluid scenes."""
        s = self._solver
        pos4 = s.get_float4("position")
        vel4 = s.get_float4("velocity")
        out = {
            "position": pos4[:, :3].copy(),
            "mass": pos4[:, 3].copy(),
            "velocity": vel4[:, :3].copy(),
            "id": s.get_uint("id"),
        }
        if self.scene.thermodynamics:
            out["temperature"] = s.get_float("temperature")
            out["vapor"] = s.get_float("vapor")
            out["cloud"] = s.get_float("cloud")
        m0 = self._params.mass0
        level = np.rint(-np.log2(out["mass"] / m0)).astype(np.int32) if len(out["mass"]) else np.zeros(0, np.int32)
        out["level"] = level
        out["kernel_radius"] = (self._params.h0 * 2.0 ** (-level / 3.0)).astype(np.float32)
        return out

    def boundary_state(self) -> dict[str, np.ndarray]:
        pos4 = self._solver.get_float4("boundary_position")
        out = {"position": pos4[:, :3].copy(), "mass": pos4[:, 3].copy()}
        if self.scene.thermodynamics:
            out["temperature"] = self._solver.get_float("boundary_temperature")
        return out

    def device_arrays(self) -> dict:
        """Zero-copy views of the solver's arrays: objects with __dlpack__ (np.from_dlpack,
        cupy.from_dlpack, torch.from_dlpack, jax.dlpack) and __cuda_array_interface__ on the GPU or
        __array_interface__ on the CPU. position and velocity are (N, 4): x, y, z and mass (position)
        or 0 (velocity). Valid until the next step() (which re-sorts the particles)."""
        names = ["position", "velocity", "id"]
        if self.scene.thermodynamics:
            names += ["temperature", "vapor", "cloud"]
        return {n: DeviceArray(self._solver, n) for n in names}

    def timings(self) -> dict[str, dict]:
        """Per-phase wall time on the device (CUDA events) or host (steady clock), in ms.
        Only phases that ran appear."""
        out = {}
        for name, total, count in self._solver.timings():
            if count > 0:
                out[name] = {"total_ms": total, "count": count, "mean_ms": total / count}
        return out

    def reset_timings(self) -> None:
        self._solver.reset_timings()

    def stats(self) -> dict:
        """Diagnostics of the last step: density error, extents, speed, adaptive counts."""
        st = dict(self._solver.stats())
        st["backend"] = self.backend
        return st

    # ---- checkpoints -------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write a checkpoint (npz) atomically; `Simulation.load` restores it bit-exactly."""
        path = Path(path)
        st = self.state()
        bd = self.boundary_state()
        s = self._solver
        arrays = {f"fluid_{k}": v for k, v in st.items() if k not in ("level", "kernel_radius")}
        arrays.update({f"boundary_{k}": v for k, v in bd.items()})
        if self.scene.thermodynamics:
            arrays["boundary_vapor"] = s.get_float("boundary_vapor")
        if self.scene.pbf.projection == "velocity":
            arrays["fluid_projection_impulse"] = s.get_float("projection_impulse")
        stats = s.stats()
        meta = {"version": CHECKPOINT_VERSION, "scene": self.scene.to_dict(), "step": self.step_count,
                "time": self.time, "dt": s.time_step(), "neighbor_row_width": int(stats["neighbor_row_width"]),
                "next_id": s.next_id(), "backend": self.backend,
                "budget_totals": [stats.get(f"{k}_total", 0.0) for k in BUDGET_TOTALS]}
        return atomic_savez(path, meta, **arrays)

    @classmethod
    def load(cls, path: str | Path, backend: str | None = None) -> "Simulation":
        with np.load(Path(path)) as z:
            meta = read_meta(z)
            if meta.get("version") != CHECKPOINT_VERSION:
                raise ValueError(f"{path}: checkpoint version {meta.get('version')} != {CHECKPOINT_VERSION}")
            scene = scene_from_dict(meta["scene"], source=str(path))
            thermo = scene.thermodynamics
            n = len(z["fluid_id"])
            zeros = np.zeros(n, np.float32)
            fluid = {
                "position": z["fluid_position"], "velocity": z["fluid_velocity"], "mass": z["fluid_mass"],
                "id": z["fluid_id"],
                "temperature": z["fluid_temperature"] if thermo else zeros,
                "vapor": z["fluid_vapor"] if thermo else zeros,
                "cloud": z["fluid_cloud"] if thermo else zeros,
            }
            if "fluid_projection_impulse" in z.files:
                fluid["projection_impulse"] = z["fluid_projection_impulse"]
            nb = len(z["boundary_position"])
            boundary = {
                "position": z["boundary_position"],
                "temperature": z["boundary_temperature"] if thermo else np.zeros(nb, np.float32),
                "vapor": z["boundary_vapor"] if thermo else np.zeros(nb, np.float32),
            }
        state = {"fluid": fluid, "boundary": boundary, "step": meta["step"], "time": meta["time"],
                 "dt": meta.get("dt"), "neighbor_row_width": meta.get("neighbor_row_width"),
                 "next_id": meta["next_id"], "budget_totals": meta.get("budget_totals")}
        return cls(scene, backend=backend or meta["backend"], _state=state)
