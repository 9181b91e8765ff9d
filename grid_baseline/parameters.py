"""The grid's parameters, derived from the scene schema (pbf_cuda/scene.py), and what the grid does with
every scene field.

Each scene field is declared once, in the scene schema (default, range, unit, meaning).  The grid
takes the fields its step uses as they are (:data:`COPIED`: :class:`Params` holds each under the
scene's own name and type, a list as a tuple), derives a few settings of its own from others
(:data:`DERIVED`) and leaves the particle solver's own settings alone, each with its reason
(:data:`IGNORED`).  tests/test_grid_parameters.py checks that the three tables name every scene field
exactly once, so a new scene field fails it until someone decides what the grid does with it.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from pbf_cuda.environment import EnvironmentProfile
from pbf_cuda.scene import SECTIONS

__all__ = ["Params", "params_from_scene", "COPIED", "DERIVED", "IGNORED"]

# Scene fields the grid's step reads as they are, per section; Params holds each under the same name.
COPIED = {
    "atmosphere": ("dry_lapse_rate", "buoyancy", "cloud_gravity", "latent_heat", "phase_rate",
                   "saturation_a", "saturation_b", "saturation_c", "heating_rate", "heating_depth",
                   "noise_frequency", "noise_amplitude", "noise_offset", "heating_patch_radius",
                   "initial_vapor_ratio", "vapor_ratio_above", "vapor_profile", "diurnal_period",
                   "relaxation_time", "autoconversion_rate", "autoconversion_threshold"),
    "pbf": ("vorticity", "gravity"),
    "particles": ("rest_density",),   # a cell's mass is rest_density * cell volume (budgets)
    # the BOMEX forcing (model.py, L1-L3); a scene without [forcing] takes the defaults (no forcing)
    "forcing": ("subsidence_heights", "subsidence_values", "radiative_heights", "radiative_values",
                "moisture_heights", "moisture_values"),
}

_ENVIRONMENT = "Params.environment: T0(y) (pbf_cuda/environment.py, EnvironmentProfile.of)"
# Scene fields the grid reads to derive a setting of its own: "section.field" -> what it becomes.
# Those whose text starts with "Params." shape the step's parameters; the others GridSimulation reads.
DERIVED = {
    "domain.size": "Params.size (m); with particles.spacing, the cell count per axis (grid_shape)",
    "domain.boundary": "Params.periodic: periodic or wall per axis",
    "time.dt": "Params.dt: the grid's step (s), also where the particle solver's step is CFL-controlled",
    "atmosphere.ground_temperature": _ENVIRONMENT,
    "atmosphere.lapse_rate": _ENVIRONMENT,
    "atmosphere.inversion_height": _ENVIRONMENT,
    "atmosphere.inversion_depth": _ENVIRONMENT,
    "atmosphere.inversion_strength": _ENVIRONMENT,
    "atmosphere.lapse_rate_above": _ENVIRONMENT,
    "time.cfl": "GridSimulation: the Courant sum advection's sub-steps keep, where > 0 (else 0.8)",
    "particles.spacing": "GridSimulation: the cell size spacing / cells_per_spacing (grid_shape)",
    "particles.kernel_ratio": "GridSimulation.particles: the kernel radius of the cells seen as particles",
    "time.steps": "GridSimulation.run: the default number of steps",
    "time.snapshot_every": "GridSimulation.run: the default steps between snapshots",
    "time.check_every": "GridSimulation: steps between the NaN and speed checks",
    "pbf.max_velocity": "GridSimulation: a cell faster than this stops the run as unstable",
    "wave.amplitude": "GridSimulation: the initial velocity mode (model.wave_velocity)",
    "wave.modes_x": "GridSimulation: the initial velocity mode (model.wave_velocity)",
    "wave.modes_y": "GridSimulation: the initial velocity mode (model.wave_velocity)",
}

_PBF = "a setting of the particles' density constraint; the grid projects pressure exactly (projection.py)"
_PROJECTION = "a setting of the particles' velocity projection; the grid's projection is exact"
_ADAPTIVE = "particle splitting and merging (section 5.2); the grid's resolution is fixed"
_STEP_CONTROL = "the particles' CFL step control; the grid keeps time.dt and sub-steps advection"
# Scene fields the grid leaves alone on purpose: "section.field" -> why.
IGNORED = {
    "particles.fill_min": "the particles' filled region; the grid's air fills the whole domain",
    "particles.fill_max": "the particles' filled region; the grid's air fills the whole domain",
    "particles.max_speed": "random initial particle velocities; the grid starts at rest (or with the wave)",
    "particles.seed": "random initial particle velocities; GridSimulation(seed=) sets the noise offset",
    "time.reference_dt": _STEP_CONTROL,
    "time.dt_min": _STEP_CONTROL,
    "time.dt_max": _STEP_CONTROL,
    "time.max_cfl": _STEP_CONTROL,
    "pbf.iterations": _PBF,
    "pbf.relaxation": _PBF,
    "pbf.projection": _PBF,
    "pbf.unilateral": _PBF,
    "pbf.neighbor_list": "how the particles find their neighbours; cells have fixed neighbours",
    "pbf.scorr_k": "the particles' tensile correction s_corr; a grid has no particle clumping",
    "pbf.scorr_n": "the particles' tensile correction s_corr; a grid has no particle clumping",
    "pbf.scorr_dq": "the particles' tensile correction s_corr; a grid has no particle clumping",
    "pbf.scorr_fine": "the particles' tensile correction s_corr; a grid has no particle clumping",
    "pbf.scorr_dt_power": "the particles' tensile correction s_corr; a grid has no particle clumping",
    "pbf.divergence_iterations": _PROJECTION,
    "pbf.divergence_tolerance": _PROJECTION,
    "pbf.gradient_correction": _PROJECTION,
    "pbf.remove_column_drift": _PROJECTION,
    "pbf.remove_shift_drift": _PROJECTION,
    "pbf.shift_keeps_anomaly": _PROJECTION,
    "pbf.xsph": "XSPH smooths particle velocities; the grid's advection scheme diffuses numerically",
    "pbf.viscosity": "the particles' SPH viscosity; the grid's advection scheme diffuses numerically",
    "pbf.max_density_error": "the particles' density check; the grid's projection conserves volume",
    "smoothing.kappa": "temperature smoothing (section 4.1) is a particle concept; the grid's numerical "
                       "diffusion plays that role",
    "smoothing.fields": "temperature smoothing (section 4.1) is a particle concept",
    "smoothing.epsilon": "temperature smoothing (section 4.1) is a particle concept",
    **{f"adaptive.{f.name}": _ADAPTIVE for f in dataclasses.fields(SECTIONS["adaptive"])},
}

# the type a copied field has in Params, by the scene field's annotation (lists become hashable tuples)
_GRID_TYPES = {"float": float, "int": int, "str": str, "bool": bool, "list": tuple}


def _scene_field(section: str, name: str) -> dataclasses.Field:
    return {f.name: f for f in dataclasses.fields(SECTIONS[section])}[name]


def _grid_value(value, kind):
    """A scene value as a Python number, text or tuple of floats (static under jit, hashable)."""
    return tuple(float(v) for v in value) if kind is tuple else kind(value)


# (section, name, type in Params) of every copied field
_COPIED_FIELDS = [(section, name, _GRID_TYPES[_scene_field(section, name).type])
                  for section, names in COPIED.items() for name in names]


def _section(scene, section):
    """The scene's section, or the schema's defaults for an optional section the scene leaves out ([forcing])."""
    values = getattr(scene, section)
    return values if values is not None else SECTIONS[section]()


def _steps(self) -> tuple:
    """Cell size per axis (m)."""
    return tuple(L / n for L, n in zip(self.size, self.shape))


def _cell_volume(self) -> float:
    """Volume of one cell (m^3)."""
    return float(np.prod(self.steps))


Params = dataclasses.make_dataclass(
    "Params",
    [("shape", tuple), ("size", tuple), ("periodic", tuple), ("dt", float),
     ("environment", EnvironmentProfile)]
    + [(name, kind) for _, name, kind in _COPIED_FIELDS]
    + [("cfl_target", float, dataclasses.field(default=0.8)),
       ("max_substeps", int, dataclasses.field(default=16))],
    frozen=True,
    namespace={"steps": property(_steps), "cell_volume": property(_cell_volume),
               "__doc__": "Everything the step needs, as Python numbers (static under jit): the grid's "
                          "shape (cells) and size (m), which axes are periodic, the step dt (s), the "
                          "environment profile T0(y), every scene field of COPIED under its own name "
                          "(unit as in the scene), and advection's sub-stepping (cfl_target, max_substeps)."})
Params.__module__ = __name__   # where pickle finds it (make_dataclass's module= needs Python 3.12)


def params_from_scene(scene, shape, cfl_target=0.8, max_substeps=16) -> Params:
    """The step's parameters for a cloud scene on a grid of `shape` cells (nx, ny, nz)."""
    copied = {name: _grid_value(getattr(_section(scene, section), name), kind)
              for section, name, kind in _COPIED_FIELDS}
    return Params(
        shape=tuple(int(n) for n in shape), size=tuple(float(s) for s in scene.domain.size),
        periodic=tuple(b == "periodic" for b in scene.domain.boundary), dt=float(scene.time.dt),
        environment=EnvironmentProfile.of(scene.atmosphere), **copied,
        cfl_target=float(cfl_target), max_substeps=int(max_substeps))
