"""Scene files: TOML in, validated parameters out.

Every parameter of a run is declared once here, with its unit and allowed
range.  A scene file names only what differs from the defaults.  Invalid input
raises :class:`SceneError` naming the field, the value and the allowed range (the checks of a
value against its declaration and between fields are in pbf_cuda/scene_checks.py).

Units are SI: metres, seconds, kelvin, kilograms, kg/kg for vapor and cloud
mixing ratios.  ``y`` is up (the paper's unit vector **j**).
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .scene_checks import SceneError, build_section, cross_checks, short, short_text

__all__ = [
    "SceneError",
    "Scene",
    "Domain",
    "Particles",
    "Time",
    "PBF",
    "Atmosphere",
    "Smoothing",
    "Adaptive",
    "Wave",
    "Forcing",
    "load_scene",
    "scene_from_dict",
    "SCENE_DIR",
    "list_scenes",
    "sanitize_name",
    "NAME_PATTERN",
]

SCENE_DIR = Path(__file__).resolve().parent / "scenes"        # the shipped scenes (package data)

BOUNDARY_KINDS = ("periodic", "wall")
SMOOTHABLE_FIELDS = ("temperature", "vapor", "cloud")
VAPOR_PROFILES = ("relative", "uniform")
PROJECTIONS = ("position", "velocity")
REFINEMENT_CRITERIA = ("paper", "lookahead", "thermal", "heated")
PAIR_KERNELS = ("mean_of_kernels", "mean_radius")


MAX_SCENE_BYTES = 1 << 20        # a scene file larger than this is refused (1 MiB)
MAX_EXTENDS_DEPTH = 16           # scene.extends chains longer than this are refused
MAX_NAME_CHARS = 64              # scene.name
NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")   # scene.name: letters, digits, _ . - (file names are made from it)
MAX_DESCRIPTION_CHARS = 10_000   # scene.description


def _spec(default, lo=None, hi=None, unit="", doc="", choices=None, length=None):
    """Declare a field: default, inclusive range [lo, hi], unit, meaning."""
    return field(
        default_factory=(lambda d=default: copy.deepcopy(d)),
        metadata=dict(lo=lo, hi=hi, unit=unit, doc=doc, choices=choices, length=length),
    )


@dataclass
class Domain:
    size: list = _spec([3200.0, 3200.0, 3200.0], 1e-3, 1e6, "m",
                       "box edge lengths along x, y (up), z", length=3)
    boundary: list = _spec(["periodic", "wall", "periodic"], unit="",
                           doc="per axis: 'periodic' (minimum image) or 'wall' (boundary particles, eq. 18)",
                           choices=BOUNDARY_KINDS, length=3)


@dataclass
class Particles:
    spacing: float = _spec(100.0, 1e-4, 1e5, "m", "initial lattice spacing d of level-0 particles")
    kernel_ratio: float = _spec(2.0, 1.2, 4.0, "", "kernel radius h0 / spacing d")
    rest_density: float = _spec(1.0, 1e-6, 1e5, "kg/m^3", "PBF rest density rho0")
    fill_min: list = _spec(None, -1e6, 1e6, "m", "lower corner of the filled region (default: domain)", length=3)
    fill_max: list = _spec(None, -1e6, 1e6, "m", "upper corner of the filled region (default: domain)", length=3)
    max_speed: float = _spec(0.0, 0.0, 1e3, "m/s", "initial speed, random direction (section 5)")
    seed: int = _spec(0, 0, 2**31 - 1, "", "random seed for initial velocities")


@dataclass
class Time:
    dt: float = _spec(2.0, 1e-6, 1e3, "s", "time step (the first step where cfl > 0)")
    reference_dt: float = _spec(2.0, 1e-6, 1e3, "s",
                                "the step at which the per-step coefficients smoothing.kappa and pbf.xsph are stated "
                                "(the paper's 2 s): at any dt they keep the same rate per simulated second, "
                                "c(dt) = 1 - (1 - c)^(dt / reference_dt), so the model converges as dt shrinks")
    cfl: float = _spec(0.0, 0.0, 2.0, "",
                       "0: every step is dt; > 0: each step is chosen so that max |v_i| dt / h_i (h_i the particle's "
                       "kernel radius) is this, within [dt_min, dt_max] and at most 1.25 times the step before")
    dt_min: float = _spec(1e-6, 1e-6, 1e3, "s", "smallest CFL-controlled step")
    dt_max: float = _spec(1e3, 1e-6, 1e3, "s", "largest CFL-controlled step")
    max_cfl: float = _spec(2.0, 1e-3, 1e3, "",
                           "a state whose CFL number max |v_i| dt / h_i is above this stops the run as unstable "
                           "(a particle crossing the diameter of its kernel support in one step)")
    steps: int = _spec(400, 1, 10**7, "", "default number of steps of a run")
    snapshot_every: int = _spec(50, 1, 10**7, "", "steps between saved snapshots")
    check_every: int = _spec(1, 1, 64, "",
                             "steps between NaN / instability checks (at most 64, so an instability is "
                             "reported within 64 steps of where it happened)")


@dataclass
class PBF:
    iterations: int = _spec(4, 1, 200, "", "constraint iterations per step")
    relaxation: float = _spec(1e-2, 0.0, 1e3, "",
                              "constraint relaxation epsilon relative to a full neighbourhood's sum |grad C|^2")
    projection: str = _spec("position", choices=PROJECTIONS,
                            doc="'position': Macklin & Mueller's PBF, velocity = (x* - x)/dt after the density "
                                "constraint (free surfaces); 'velocity': divergence-free velocity projection, the "
                                "density constraint moves positions only (closed domains: energy is not created)")
    divergence_iterations: int = _spec(4, 1, 64, "", "most conjugate-gradient iterations of the velocity projection")
    divergence_tolerance: float = _spec(0.0, 0.0, 1.0, "",
                                        "the velocity projection stops when RMS(div v) dt, the relative density "
                                        "change per step, is below this (0: always divergence_iterations)")
    gradient_correction: bool = _spec(False, doc="velocity projection: corrected kernel gradients L_i grad W_ij "
                                                 "(Bonet & Lok 1999) in its divergence, exact for every linear "
                                                 "velocity field on a disordered particle set, so the projection "
                                                 "removes compression only, not flow the plain SPH divergence misreads")
    remove_column_drift: bool = _spec(True, doc="velocity projection in a box closed at the floor and the lid: remove "
                                      "the fluid's net vertical momentum after the projection (incompressible air there has "
                                      "none; a few CG iterations do not stop a drift of the whole column, which rarefies "
                                      "heated air: docs/physics.md, Column drift)")
    remove_shift_drift: bool = _spec(False, doc="velocity projection in a box closed at the floor and the lid: remove "
                                     "the density solve's net vertical shift of the fluid after its iterations (the "
                                     "same rigid mode as the column drift, reached through positions; off by default, "
                                     "docs/physics.md, Shift drift)")
    shift_keeps_anomaly: bool = _spec(False, doc="velocity projection with an atmosphere: the density constraint's "
                                      "vertical shift of a particle moves its temperature along the environment's lapse "
                                      "rate, not the dry adiabat")
    neighbor_list: bool = _spec(True, doc="keep each particle's neighbour candidates in a list built once per step "
                                          "(about 200 bytes per particle) instead of searching the cells in every "
                                          "neighbour pass: the same sums, 2-3x fewer particles looked at; off for "
                                          "the largest sizes, where the lists would not fit in memory")
    unilateral: bool = _spec(True, doc="clamp C_i = max(rho_i/rho0 - 1, 0) (free surfaces only: a closed domain "
                                       "needs the bilateral constraint, or heated air leaves a rarefied layer)")
    scorr_k: float = _spec(0.01, 0.0, 10.0, "", "tensile s_corr strength k, relative to a unit constraint's lambda")
    scorr_n: int = _spec(4, 1, 8, "", "tensile s_corr exponent n")
    scorr_dq: float = _spec(0.2, 0.0, 0.99, "", "tensile s_corr reference distance dq / h")
    scorr_fine: float = _spec(1.0, 0.0, 1.0, "", "weight of s_corr on pairs with a particle finer than level 0 "
                                                "(adaptive runs; 0: s_corr acts between level-0 particles only)")
    scorr_dt_power: float = _spec(0.0, 0.0, 1.0, "",
                                  "s_corr's k scaled by (dt / time.reference_dt)^power, exactly k at the reference "
                                  "step: 0 keeps it per iteration; 0.5 keeps the random walk of its shifts per unit "
                                  "time (docs/design.md, The time step)")
    xsph: float = _spec(0.01, 0.0, 1.0, "", "XSPH viscosity c")
    viscosity: float = _spec(0.0, 0.0, 1e6, "m^2/s", "kinematic viscosity nu (pairwise SPH Laplacian, conserves "
                                                     "momentum); explicit: keep nu dt / spacing^2 below 0.1")
    vorticity: float = _spec(0.0, 0.0, 1e4, "m/s", "vorticity confinement epsilon")
    gravity: list = _spec([0.0, 0.0, 0.0], -1e3, 1e3, "m/s^2", "constant body acceleration", length=3)
    max_velocity: float = _spec(1e3, 1e-6, 1e9, "m/s", "a particle faster than this stops the run as unstable")
    max_density_error: float = _spec(10.0, 1e-6, 1e6, "", "mean |rho/rho0 - 1| above this stops the run as unstable")


@dataclass
class Atmosphere:
    """Cloud physics of section 4. Present in a scene file => thermodynamics on."""
    ground_temperature: float = _spec(300.0, 150.0, 400.0, "K", "environment temperature T0 at y = 0")
    lapse_rate: float = _spec(6.5e-3, -0.05, 0.05, "K/m", "environment lapse rate: T0(y) = T_ground - lapse_rate*y "
                                                          "(below the inversion, if there is one)")
    # A capping inversion (pbf_cuda/environment.py; off at inversion_height = 0, the paper's linear profile).
    inversion_height: float = _spec(0.0, 0.0, 1e5, "m", "base z_i of a capping inversion (0: none)")
    inversion_depth: float = _spec(200.0, 1.0, 1e5, "m", "thickness of the inversion layer, over which T0 rises "
                                                          "by inversion_strength")
    inversion_strength: float = _spec(0.0, 0.0, 100.0, "K", "warming of T0 across the inversion layer")
    lapse_rate_above: float = _spec(6.5e-3, -0.05, 0.05, "K/m", "environment lapse rate above the inversion layer")
    vapor_ratio_above: float = _spec(-1.0, -1.0, 2.0, "", "k_v above the inversion layer (the dry free troposphere), "
                                                          "blended linearly across it; -1: initial_vapor_ratio")
    initial_vapor_ratio: float = _spec(0.5, 0.0, 2.0, "", "k_v of section 5: v = k_v A exp(B/(T+C))")
    vapor_profile: str = _spec("relative", choices=VAPOR_PROFILES,
                               doc="'relative': k_v times saturation at T0(y); 'uniform': k_v times saturation at the ground")
    buoyancy: float = _spec(9.81, 0.0, 1e3, "m/s^2", "k_b of eq. 6")
    cloud_gravity: float = _spec(9.81, 0.0, 1e4, "m/s^2 per kg/kg", "k_g of eq. 6")
    dry_lapse_rate: float = _spec(9.8e-3, 0.0, 0.1, "K/m", "Gamma_d of eq. 7")
    latent_heat: float = _spec(2489.0, 0.0, 1e5, "K", "Q = L/c_p of eq. 11")
    phase_rate: float = _spec(0.5, 0.0, 1e6, "1/s", "alpha of eq. 9")
    saturation_a: float = _spec(1.795e5, 1e-12, 1e12, "kg/kg", "A of eq. 10")
    saturation_b: float = _spec(-4302.6, -1e6, 1e6, "K", "B of eq. 10")
    saturation_c: float = _spec(-29.65, -1e4, 1e4, "K", "C of eq. 10")
    heating_rate: float = _spec(0.05, 0.0, 100.0, "K/s", "S_e of eq. 5")
    heating_depth: float = _spec(100.0, 0.0, 1e5, "m", "air below this height is heated (each particle by the "
                                                        "part of its layer below it)")
    noise_frequency: float = _spec(1.0 / 800.0, 0.0, 1e3, "1/m", "spatial frequency of the simplex heating pattern")
    noise_amplitude: float = _spec(1.0, 0.0, 10.0, "", "S = S_e * max(0, 1 + amplitude * noise(x f, z f))")
    heating_patch_radius: float = _spec(0.0, 0.0, 1e6, "m",
                                        "0: the whole ground is heated; > 0: only a patch around the domain's "
                                        "horizontal centre, S times (1 - (r/R)^2)^2 for r < R (one isolated cloud)")
    noise_offset: list = _spec([0.0, 0.0], -1e6, 1e6, "", "shift of the noise pattern (noise units); seeds vary it",
                               length=2)
    # Large-scale forcing of the cycling example (docs/cycling.md, eq. C1-C3); every term is off at 0.
    diurnal_period: float = _spec(0.0, 0.0, 1e7, "s",
                                  "P of eq. C1: the ground heating is multiplied by max(0, sin(2 pi t / P)) "
                                  "(time of day; 0: constant heating)")
    relaxation_time: float = _spec(0.0, 0.0, 1e9, "s",
                                   "tau of eq. C2: T and vapor relax toward the initial profiles T0(y), v0(y) "
                                   "(large-scale forcing; 0: off)")
    autoconversion_rate: float = _spec(0.0, 0.0, 1e3, "1/s",
                                       "k_auto of eq. C3: cloud water above the threshold is removed as rain at "
                                       "this rate (0: off)")
    autoconversion_threshold: float = _spec(5e-4, 0.0, 1.0, "kg/kg", "q_c0 of eq. C3: cloud water kept by a parcel")


@dataclass
class Smoothing:
    kappa: float = _spec(0.1, 0.0, 1.0, "", "kappa of eq. 17b; 0 disables smoothing and its cost")
    fields: list = _spec(["temperature"], doc="scalar fields smoothed with eq. 12-17", choices=SMOOTHABLE_FIELDS)
    epsilon: float = _spec(0.01, 1e-8, 1.0, "", "epsilon of eq. 13 relative to h^2")


@dataclass
class Adaptive:
    enabled: bool = _spec(False, doc="split and merge particles (section 5.2)")
    max_level: int = _spec(3, 1, 12, "", "finest level; h_l = h0 2^(-l/3), m_l = m0 2^(-l)")
    k_p: float = _spec(1.0, 1e-9, 1e9, "", "k_p of eq. 20")
    k_c: float = _spec(2000.0, 0.0, 1e9, "1/(kg/kg)", "k_c of eq. 20")
    split_threshold: float = _spec(0.3, 0.0, 1e9, "", "split when E > this (alpha)")
    merge_threshold: float = _spec(0.05, 0.0, 1e9, "", "merge when E < this (beta)")
    criterion: str = _spec("paper", choices=REFINEMENT_CRITERIA,
                           doc="what E of eq. 20 measures: 'paper': the cloud water w; 'lookahead': the cloud water "
                               "the particle would hold after rising lookahead_height dry-adiabatically, "
                               "max(w, v + w - q_s(T - Gamma_d dz)), so thermals are refined before they condense; "
                               "'thermal': max(w, (T - T0(y)) / Q), the heat excess over the initial profile as the "
                               "cloud water that would release it, so heated air is refined from the ground up; "
                               "'heated': the thermal criterion and max(w*, S_e(x, z) tau / Q), the heat the ground "
                               "below gives in tau = heating_time, so the columns above heated ground are fine "
                               "before thermals rise in them")
    pair_kernel: str = _spec("mean_of_kernels", choices=PAIR_KERNELS,
                             doc="the kernel between particles of radii h_i != h_j: 'mean_of_kernels': eq. 19, "
                                 "(W(r, h_i) + W(r, h_j)) / 2, support max(h_i, h_j) (the paper's); 'mean_radius': "
                                 "W(r, (h_i + h_j) / 2), support (h_i + h_j) / 2, so a coarse particle next to fine "
                                 "ones has fewer neighbours (both symmetric in i and j; 'mean_radius' is the less "
                                 "tried: one of five seeds of the growing study blew up with it, docs/performance.md)")
    lookahead_height: float = _spec(300.0, 0.0, 5000.0, "m", "rise dz of the 'lookahead' criterion")
    heating_time: float = _spec(60.0, 0.0, 1e6, "s", "tau of the 'heated' criterion: with the defaults a column "
                                                     "is fine where S_e tau > 0.45 K")
    coarse_near_walls: bool = _spec(True, doc="particles within one level-0 kernel radius h0 of a wall stay at level 0 "
                                              "(never split; finer ones merge): the boundary particles sample a wall "
                                              "at level-0 spacing, which a finer kernel sees as lumps")
    every: int = _spec(1, 1, 1000, "steps", "split and merge every this many steps (1: every step, as the paper); "
                                             "between them the levels stay as they are")
    capacity: float = _spec(4.0, 1.0, 1e3, "", "preallocated slots as a multiple of the initial particle count")
    min_distance: float = _spec(0.35, 0.0, 0.5, "",
                                "no particle within this times the new particle's kernel radius of it; at most "
                                "0.5, so the check stays inside one cell block (see adaptivity.h)")


_KNOTS = "; piecewise linear through the 4 knots of the heights field, constant below the first and above the last"


@dataclass
class Forcing:
    """Large-scale forcing of the BOMEX case (Siebesma et al. 2003): subsidence, radiative cooling and a moisture
    tendency, each a profile of height y through 4 knots (pbf_cuda/csrc/thermodynamics.h, L1-L3). Needs an
    [atmosphere]; every value 0 (the default) is no forcing."""
    subsidence_heights: list = _spec([0.0, 1000.0, 2000.0, 3000.0], 0.0, 1e5, "m",
                                     "heights of the knots of w_s(y), non-decreasing", length=4)
    subsidence_values: list = _spec([0.0, 0.0, 0.0, 0.0], -1.0, 1.0, "m/s",
                                    "large-scale vertical velocity w_s at the knots (< 0: subsidence); T and vapor "
                                    "change at -w_s dtheta0/dy and -w_s dv0/dy of the environment profiles" + _KNOTS,
                                    length=4)
    radiative_heights: list = _spec([0.0, 1000.0, 2000.0, 3000.0], 0.0, 1e5, "m",
                                    "heights of the knots of the radiative rate, non-decreasing", length=4)
    radiative_values: list = _spec([0.0, 0.0, 0.0, 0.0], -1e-2, 1e-2, "K/s",
                                   "radiative heating rate of theta at the knots (< 0: cooling; BOMEX: -2 K/day = "
                                   "-2.3148e-5 K/s)" + _KNOTS, length=4)
    moisture_heights: list = _spec([0.0, 1000.0, 2000.0, 3000.0], 0.0, 1e5, "m",
                                   "heights of the knots of the moisture tendency, non-decreasing", length=4)
    moisture_values: list = _spec([0.0, 0.0, 0.0, 0.0], -1e-5, 1e-5, "1/s",
                                  "large-scale tendency of the vapor mixing ratio at the knots, kg/kg per s "
                                  "(BOMEX: -1.2e-8 below 300 m)" + _KNOTS, length=4)

    @property
    def active(self) -> bool:
        """Whether any profile is non-zero (else the solvers skip the forcing)."""
        return any(v != 0.0 for v in (*self.subsidence_values, *self.radiative_values, *self.moisture_values))

    def profiles(self) -> dict:
        """{"subsidence" | "radiative" | "moisture": (heights, values)} as tuples of floats."""
        return {k: (tuple(map(float, getattr(self, k + "_heights"))), tuple(map(float, getattr(self, k + "_values"))))
                for k in ("subsidence", "radiative", "moisture")}


@dataclass
class Wave:
    """Optional initial internal gravity wave (stream function psi = A sin(kx x) sin(ky y))."""
    amplitude: float = _spec(0.0, 0.0, 1e3, "m/s", "peak vertical velocity of the initial mode")
    modes_x: int = _spec(1, 1, 64, "", "horizontal wavenumber in wavelengths per domain width")
    modes_y: int = _spec(1, 1, 64, "", "vertical wavenumber in half-wavelengths per domain height")


SECTIONS = {
    "domain": Domain,
    "particles": Particles,
    "time": Time,
    "pbf": PBF,
    "atmosphere": Atmosphere,
    "smoothing": Smoothing,
    "adaptive": Adaptive,
    "wave": Wave,
    "forcing": Forcing,
}
OPTIONAL_SECTIONS = ("atmosphere", "wave", "forcing")


@dataclass
class Scene:
    name: str = "unnamed"
    description: str = ""
    domain: Domain = field(default_factory=Domain)
    particles: Particles = field(default_factory=Particles)
    time: Time = field(default_factory=Time)
    pbf: PBF = field(default_factory=PBF)
    atmosphere: Atmosphere | None = None
    smoothing: Smoothing = field(default_factory=Smoothing)
    adaptive: Adaptive = field(default_factory=Adaptive)
    wave: Wave | None = None
    forcing: Forcing | None = None

    # ---- derived quantities (all SI) -------------------------------------------------
    @property
    def kernel_radius(self) -> float:
        """h0 in m: kernel radius of level-0 particles (the largest)."""
        return self.particles.kernel_ratio * self.particles.spacing

    @property
    def thermodynamics(self) -> bool:
        return self.atmosphere is not None

    @property
    def large_scale_forcing(self) -> bool:
        """A [forcing] section with a non-zero profile (and an atmosphere for it to act on)."""
        return self.thermodynamics and self.forcing is not None and self.forcing.active

    @property
    def smoothing_active(self) -> bool:
        return self.thermodynamics and self.smoothing.kappa > 0.0 and len(self.smoothing.fields) > 0

    def fill_box(self) -> tuple[list, list]:
        lo = self.particles.fill_min if self.particles.fill_min is not None else [0.0, 0.0, 0.0]
        hi = self.particles.fill_max if self.particles.fill_max is not None else list(self.domain.size)
        return list(lo), list(hi)

    def lattice_shape(self) -> tuple[int, int, int]:
        """Particles per axis: lattice sites (i + 1/2) L/N, N = round(L / spacing), inside the fill box
        (the same lattice as pbf_cuda.initial_state)."""
        lo, hi = self.fill_box()
        shape = []
        for a in range(3):
            L = self.domain.size[a]
            n = max(1, int(round(L / self.particles.spacing)))
            d = L / n
            first = max(0, int(math.ceil((lo[a] - 1e-9) / d - 0.5)))
            last = min(n - 1, int(math.floor((hi[a] + 1e-9) / d - 0.5)))
            shape.append(max(0, last - first + 1))
        return tuple(shape)

    def estimated_particles(self) -> int:
        nx, ny, nz = self.lattice_shape()
        return nx * ny * nz

    def environment_temperature(self, y):
        """T0(y) in K (section 4; linear from the ground, or with a capping inversion: pbf_cuda/environment.py)."""
        from .environment import EnvironmentProfile
        return EnvironmentProfile.of(self.atmosphere).temperature(y)

    def saturation(self, temperature):
        """A exp(B/(T+C)) in kg/kg (eq. 10 without the total-water cap)."""
        import numpy as np
        a = self.atmosphere
        return a.saturation_a * np.exp(a.saturation_b / (np.asarray(temperature) + a.saturation_c))

    def lifting_condensation_level(self, surface_temperature, q):
        """The model's lifting condensation level in m of air with dry static temperature T_s = T + Gamma_d y
        (K) and total water q (kg/kg): it saturates where T_s - Gamma_d z reaches the dew point T_d, the
        temperature at which eq. 10 gives q, T_d = B / ln(q / A) - C; z = (T_s - T_d) / Gamma_d."""
        import numpy as np
        a = self.atmosphere
        dew_point = a.saturation_b / np.log(np.asarray(q, float) / a.saturation_a) - a.saturation_c
        return (np.asarray(surface_temperature, float) - dew_point) / a.dry_lapse_rate

    # ---- transformations ---------------------------------------------------------------
    def to_dict(self) -> dict:
        out = {"scene": {"name": self.name, "description": self.description}}
        for key in SECTIONS:
            value = getattr(self, key)
            if value is not None:
                out[key] = dataclasses.asdict(value)
        return out

    def config_hash(self) -> str:
        """Stable hash of every parameter (hex, 16 chars)."""
        blob = json.dumps(self.to_dict(), sort_keys=True, default=float).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def replace(self, **overrides) -> "Scene":
        """A copy with dotted overrides, e.g. replace(**{"pbf.iterations": 8}). Validated."""
        data = self.to_dict()
        for dotted, value in overrides.items():
            section, _, key = dotted.partition(".")
            if not key:
                raise SceneError(f"override '{dotted}': expected 'section.field'")
            data.setdefault(section, {})[key] = value
        return scene_from_dict(data, source=f"{self.name} (overridden)")

    def with_spacing(self, spacing: float) -> "Scene":
        return self.replace(**{"particles.spacing": float(spacing)})

    def with_particle_count(self, target: int) -> "Scene":
        """Rescale the lattice spacing so the initial particle count is about `target`."""
        lo, hi = self.fill_box()
        volume = float(abs((hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2])))
        spacing = (volume / max(int(target), 1)) ** (1.0 / 3.0)
        return self.with_spacing(spacing)


def scene_from_dict(data: dict, source: str = "scene") -> Scene:
    """Validate a nested dict (as read from TOML) into a Scene."""
    if not isinstance(data, dict):
        raise SceneError(f"{source}: expected a table at the top level")
    allowed = {"scene", *SECTIONS}
    unknown = sorted(map(str, set(data) - allowed))
    if unknown:
        raise SceneError(f"{source}: unknown section [{short_text(unknown[0])}]; "
                         f"known sections: {', '.join(sorted(allowed))}")
    head = data.get("scene", {})
    if not isinstance(head, dict):
        raise SceneError(f"{source}: [scene] = {short(head)} must be a table (name, description, extends)")
    extra = sorted(map(str, set(head) - {"name", "description", "extends"}))
    if extra:
        raise SceneError(f"{source}: unknown field scene.{short_text(extra[0])}; known fields: name, description, extends")
    name = head.get("name", _default_name(source))
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name) or name in (".", ".."):
        raise SceneError(f"{source}: scene.name = {short(name)}: expected 1 to {MAX_NAME_CHARS} characters, "
                         "each a letter, a digit or one of _ . - (no spaces, slashes or other symbols)")
    description = head.get("description", "")
    if not isinstance(description, str) or len(description) > MAX_DESCRIPTION_CHARS:
        raise SceneError(f"{source}: scene.description = {short(description)}: expected a text of at most "
                         f"{MAX_DESCRIPTION_CHARS} characters")
    scene = Scene(name=name, description=description)
    for key, cls in SECTIONS.items():
        if key in data:
            setattr(scene, key, build_section(key, cls, data[key], source))
    cross_checks(scene, source)
    return scene


def _default_name(source: str) -> str:
    """A scene without scene.name is named after its file (the source's stem), every character outside
    letters, digits and _ . - replaced by _ (a valid scene.name)."""
    stem = Path(str(source)).stem if str(source).endswith(".toml") else str(source)
    return sanitize_name(stem)


def sanitize_name(text: str) -> str:
    """`text` as a valid scene.name: runs of characters outside letters, digits and _ . - become one _,
    leading dots are dropped, at most MAX_NAME_CHARS characters; "unnamed" when nothing is left."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(text)).lstrip(".")[:MAX_NAME_CHARS]
    return name if name and name not in (".", "..") else "unnamed"


def list_scenes() -> list[str]:
    return sorted(p.stem for p in SCENE_DIR.glob("*.toml"))


def _merge(base: dict, top: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _read_scene_file(path: Path, what: str) -> dict:
    """A scene file's TOML as a dict; every failure (missing, not a regular file, too large, not UTF-8,
    not TOML) is a SceneError naming the file."""
    try:
        st = path.stat()
    except (OSError, ValueError) as exc:
        raise SceneError(f"{what}: cannot read scene file {short(str(path))}: "
                         f"{getattr(exc, 'strerror', None) or exc}") from None
    import stat as _stat
    if not _stat.S_ISREG(st.st_mode):
        raise SceneError(f"{what}: {short(str(path))} is not a regular file (a scene is a .toml file)")
    if st.st_size > MAX_SCENE_BYTES:
        raise SceneError(f"{what}: {short(str(path))} has {st.st_size} bytes; a scene file may have at most "
                         f"{MAX_SCENE_BYTES}")
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_SCENE_BYTES + 1)
    except OSError as exc:
        raise SceneError(f"{what}: cannot read scene file {short(str(path))}: {exc.strerror or exc}") from None
    if len(raw) > MAX_SCENE_BYTES:
        raise SceneError(f"{what}: {short(str(path))} is larger than {MAX_SCENE_BYTES} bytes")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(f"{path}: not UTF-8 text (byte {exc.start}); a scene is a TOML file") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {short_text(str(exc), 200)}") from None
    except (RecursionError, ValueError, OverflowError) as exc:
        raise SceneError(f"{path}: not a usable TOML file: {type(exc).__name__}: {short(str(exc))}") from None


def _shipped(name: str) -> Path | None:
    """pbf_cuda/scenes/NAME.toml when `name` is a shipped scene's name."""
    if isinstance(name, str) and name in list_scenes():
        return SCENE_DIR / f"{name}.toml"
    return None


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except (OSError, ValueError):       # a name too long for the filesystem, a NUL byte
        return False


def _resolve_path(name_or_path: str | Path) -> Path:
    """A shipped scene's name or a path to a scene file (as given by the caller)."""
    text = str(name_or_path)
    if not text or len(text) > 4096 or "\0" in text:
        raise SceneError(f"scene {short(text)}: expected a shipped scene's name or a path to a .toml "
                         f"file; shipped scenes: {', '.join(list_scenes())}")
    path = Path(name_or_path)
    if _exists(path):
        return path
    shipped = _shipped(text) if not path.suffix else None
    if shipped is not None:
        return shipped
    raise SceneError(f"scene '{short_text(text)}' not found; shipped scenes: {', '.join(list_scenes())}")


def _resolve_extends(parent: Any, including: Path) -> Path:
    """scene.extends of the file `including`: a shipped scene's name, or a path (relative to the including
    file's folder) to a regular file inside that folder."""
    where = f"{including}: scene.extends = {short(parent)}"
    allowed = (f"allowed: a shipped scene ({', '.join(list_scenes())}) or a .toml file in "
               f"{short(str(including.parent))}")
    if not isinstance(parent, str) or not parent or len(parent) > 1024 or "\0" in parent:
        raise SceneError(f"{where}: {allowed}")
    shipped = _shipped(parent)
    base = including.resolve().parent
    candidate = (base / parent)
    if shipped is not None and not candidate.exists():
        return shipped
    try:
        resolved = candidate.resolve()
    except (OSError, RuntimeError, ValueError):
        raise SceneError(f"{where}: cannot be resolved; {allowed}") from None
    if not resolved.is_relative_to(base):
        raise SceneError(f"{where}: outside the including file's folder; {allowed}")
    if shipped is None and not resolved.exists() and resolved.suffix != ".toml":
        raise SceneError(f"{where}: no such scene; {allowed}")
    return resolved


def read_scene_dict(name_or_path: str | Path, _seen: tuple = ()) -> dict:
    """The scene file as a dict, with `scene.extends = "other"` resolved (other's values, overridden).

    `extends` names a shipped scene or a file in the including file's folder (or below it); chains
    are at most MAX_EXTENDS_DEPTH long and may not loop (compared by resolved path)."""
    path = _resolve_path(name_or_path) if not _seen else Path(name_or_path)
    resolved = path.resolve()
    if resolved in _seen:
        chain = " -> ".join(p.name for p in (*_seen, resolved))
        raise SceneError(f"{_seen[-1]}: scene.extends forms a cycle: {chain}")
    if len(_seen) >= MAX_EXTENDS_DEPTH:
        raise SceneError(f"{_seen[-1]}: scene.extends chain longer than {MAX_EXTENDS_DEPTH} files")
    data = _read_scene_file(path, str(_seen[-1]) if _seen else "scene")
    head = data.get("scene", {})
    if not isinstance(head, dict):
        raise SceneError(f"{path}: [scene] = {short(head)} must be a table (name, description, extends)")
    parent = head.get("extends")
    if parent is not None:
        parent_path = _resolve_extends(parent, path)
        base = read_scene_dict(parent_path, (*_seen, resolved))
        base_head = base.get("scene", {})
        if isinstance(base_head, dict):
            base_head.pop("description", None)
        data = _merge(base, data)
    head = data.get("scene", {})
    if isinstance(head, dict):
        head.pop("extends", None)
    return data


def load_scene(name_or_path: str | Path, **overrides) -> Scene:
    """Load a scene by name (pbf_cuda/scenes/NAME.toml) or path, apply dotted overrides.

    Every failure is a SceneError naming the file, the field and what is allowed."""
    path = _resolve_path(name_or_path)
    try:
        data = read_scene_dict(path)
        scene = scene_from_dict(data, source=str(path) if path.parent != SCENE_DIR else path.stem)
        if "name" not in (data.get("scene") or {}):
            scene.name = sanitize_name(path.stem)
        return scene.replace(**overrides) if overrides else scene
    except SceneError:
        raise
    except (ValueError, TypeError, AttributeError, OverflowError, RecursionError, OSError, MemoryError) as exc:
        # A last line of defence: whatever slipped through the checks above still names the file.
        raise SceneError(f"{path}: invalid scene ({type(exc).__name__}: {short_text(str(exc))})") from None
