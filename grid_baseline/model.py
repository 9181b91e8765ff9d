"""The grid cloud model's step, as pure jax functions of (state, aux, params).

Discretisation (Miyazaki et al. 2002 / Dobashi et al. 2008 style):

* staggered MAC grid (layout in grid_baseline/projection.py); scalars at cell
  centres: theta' (potential-temperature perturbation, K), vapor v and cloud w
  (kg/kg);
* advection: jax-cfd's flux-form van Leer scheme (``advect_van_leer``, the only
  jax-cfd advection that supports walls), forward Euler, for the three scalars
  and the three velocity components; sub-stepped so that the Courant sum
  dt (|u|/dx + |v|/dy + |w|/dz) stays <= ``cfl_target`` (the particle solver
  is Lagrangian and has no such limit, so the grid takes the scene's dt and
  sub-steps advection inside it);
* pressure projection: exact FFT/DCT Poisson solve (projection.py);
* physics per cell in the particle solver's order: ground heating (eq. 5),
  buoyancy and gravity (eq. 6, plus pbf.gravity), adiabatic cooling (eq. 7),
  phase transition (eq. 9-10) with latent heat (eq. 11), integrated exactly
  for the linearised system (stable for any alpha*dt); vorticity confinement
  f = eps (N x omega) with eps = pbf.vorticity in m/s;
* large-scale forcing of the cycling example (docs/cycling.md), as in the particle
  solver: time-of-day heating (eq. C1), exact-exponential relaxation of theta' and
  v toward 0 and v0(y) (C2), autoconversion of cloud water above q_c0 into rain
  (C3).  The state carries the clock ``time`` (s) and the running budget sums
  ``rain_total``, ``water_relaxation_total`` (kg/kg m^3, like ``total_water``)
  and ``heat_relaxation_total`` (K m^3) as 0-d arrays, so water closes (C4):
  total_water(t) = total_water(0) + water_relaxation_total - rain_total;
* large-scale forcing of BOMEX (Siebesma et al. 2003; scene [forcing]), as in the particle solver
  (pbf_cuda/csrc/thermodynamics.h, L1-L3): subsidence of the environment profiles, theta' += -w_s(y)
  dtheta0/dy dt and v += -w_s(y) dv0/dy dt, radiative cooling theta' += R(y) dt, moisture tendency
  v += M(y) dt, each a per-level rate (make_aux) applied after the heating, booked in the running sums
  ``heat_subsidence_total``, ``heat_radiation_total`` (K m^3), ``water_subsidence_total`` and
  ``water_tendency_total`` (kg/kg m^3).  theta0(y) and v0(y) are the environment's (the grid's theta'
  is measured from theta0, so the mean-profile tendency is a source of theta').

Temperature: the grid advects theta' = T + Gamma_d y - theta0(y), the
perturbation of the potential temperature theta = T + Gamma_d y from the
environment's theta0(y) = T_ground + (Gamma_d - Gamma_env) y.  theta is
conserved along a dry parcel, so advecting it *is* the adiabatic cooling of
eq. 7 (DT/Dt = -Gamma_d u_y  <=>  D theta/Dt = 0): eq. 7 is therefore not
applied a second time.  theta' obeys D theta'/Dt = -u_y (Gamma_d - Gamma_env),
applied after advection.  T - T0(y) = theta' exactly, so buoyancy is computed
from a small number even in float32, and a flux-form scheme's
(divergence error) * (advected value) term acts on a few kelvin, not on 300 K
(docs/design.md: float32 wall divergence would otherwise create spurious heating).
Temperature smoothing (section 4.1) is a particle concept; the grid's own
numerical diffusion plays that role and smoothing.kappa is ignored.
"""
from __future__ import annotations

import math

import numpy as np

import jax.numpy as jnp
from jax import lax

from pbf_cuda.environment import vapor_ratio

from . import compat
from .parameters import Params, params_from_scene
from .projection import _lower_face, laplacian_eigenvalues, project, zero_wall_faces

compat.apply()
from jax_cfd.base import advection as cfd_advection  # noqa: E402
from jax_cfd.base import boundaries as cfd_boundaries  # noqa: E402
from jax_cfd.base import grids as cfd_grids  # noqa: E402

__all__ = ["Params", "params_from_scene", "initial_state", "make_aux", "advect", "physics", "pressure_project",
           "full_step", "step_with_budget", "budget_terms", "BUDGET_TERMS", "phase_transition", "STATE_KEYS"]

FIELD_KEYS = ("ux", "uy", "uz", "theta", "vapor", "cloud")
# 0-d entries of the state: the clock and the forcing's running budget sums (docs/cycling.md C4)
SCALAR_KEYS = ("time", "rain_total", "water_relaxation_total", "heat_relaxation_total",
               "heat_subsidence_total", "heat_radiation_total", "water_subsidence_total", "water_tendency_total")
STATE_KEYS = FIELD_KEYS + SCALAR_KEYS
UP = 1  # y is up


# ---- geometry ---------------------------------------------------------------------------
def cell_centers(p: Params):
    """1-D host arrays (float64) of the cell-centre coordinates along x, y, z (m)."""
    return tuple((np.arange(n) + 0.5) * h for n, h in zip(p.shape, p.steps))


def face_coordinates(p: Params, axis: int):
    """1-D host array of the face positions of velocity component `axis` along its own axis (offset 1)."""
    n, h = p.shape[axis], p.steps[axis]
    return (np.arange(n) + 1.0) * h


def environment_temperature(p: Params, y):
    """T0(y), K (host, float64)."""
    return p.environment.temperature(y)


def stratification(p: Params, y):
    """Gamma_d - Gamma(y), K/m (host): the rate at which rising air cools relative to the environment."""
    return p.dry_lapse_rate - p.environment.lapse(y)


def saturation(p: Params, T):
    return p.saturation_a * jnp.exp(p.saturation_b / (T + p.saturation_c))


def _vapor_reference(p: Params, y):
    """(T_ref, s(T_ref)) of v0 at heights y (host, float64): the temperature of its saturation, T0(y) ('relative')
    or the ground's, K, and the saturation ratio there."""
    t_ref = environment_temperature(p, y) if p.vapor_profile == "relative" else np.full_like(y, p.environment.ground_temperature)
    return t_ref, p.saturation_a * np.exp(p.saturation_b / (t_ref + p.saturation_c))


def initial_vapor(p: Params, y):
    """v0(y) of section 5 (host, float64): k_v times saturation at T0(y) ('relative') or at the ground."""
    y = np.asarray(y, dtype=np.float64)
    k = vapor_ratio(p.environment, p.initial_vapor_ratio, p.vapor_ratio_above, y)
    return k * _vapor_reference(p, y)[1]


def linear_profile(heights, values, y):
    """f(y) piecewise linear through (heights[k], values[k]), constant below the first knot and above the last
    (host, float64; the particle solver's LinearProfile)."""
    y = np.asarray(y, dtype=np.float64)
    z = np.asarray(heights, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    out = np.full_like(y, v[0])
    for k in range(1, len(z)):
        inside = (y > z[k - 1]) & (y <= z[k])
        span = z[k] - z[k - 1]
        seg = v[k - 1] + (v[k] - v[k - 1]) * (y - z[k - 1]) / span if span > 0.0 else np.full_like(y, v[k])
        out = np.where(inside, seg, out)
    return np.where(y > z[-1], v[-1], out)


def vapor_gradient(p: Params, y):
    """dv0/dy of initial_vapor (host, float64, 1/m): k'(y) s + k s'(T) dT_ref/dy (thermodynamics.h)."""
    y = np.asarray(y, dtype=np.float64)
    env = p.environment
    relative = p.vapor_profile == "relative"
    k = vapor_ratio(env, p.initial_vapor_ratio, p.vapor_ratio_above, y)
    dk = np.zeros_like(y)
    if p.vapor_ratio_above >= 0.0 and env.has_inversion:
        f = np.asarray(env.inversion_fraction(y), dtype=np.float64)
        dk = np.where((f > 0.0) & (f < 1.0), (p.vapor_ratio_above - p.initial_vapor_ratio) / env.inversion_depth, 0.0)
    t_ref, s = _vapor_reference(p, y)
    ds = s * (-p.saturation_b) / (t_ref + p.saturation_c) ** 2 * -np.asarray(env.lapse(y), float) if relative else np.zeros_like(y)
    return dk * s + k * ds


def large_scale_rates(p: Params, y):
    """The forcing L1-L3 per unit time at heights y (host, float64): (subsidence dtheta/dt K/s, radiative dtheta/dt
    K/s, subsidence dv/dt 1/s, moisture dv/dt 1/s)."""
    ws = linear_profile(p.subsidence_heights, p.subsidence_values, y)
    return (-ws * stratification(p, y), linear_profile(p.radiative_heights, p.radiative_values, y),
            -ws * vapor_gradient(p, y), linear_profile(p.moisture_heights, p.moisture_values, y))


def large_scale_active(p: Params) -> bool:
    return any(v != 0.0 for v in (*p.subsidence_values, *p.radiative_values, *p.moisture_values))


def diurnal_factor(t, period):
    """Time-of-day factor of eq. C1, f(t) = max(0, sin(2 pi t / P)); 1 when period <= 0 (constant)."""
    if not period > 0.0:
        return jnp.ones_like(t) if hasattr(t, "dtype") else 1.0
    return jnp.maximum(0.0, jnp.sin(2.0 * math.pi * t / period))


def diurnal_integral(t, period):
    """Closed form of int_0^t f(s) ds for eq. C1 (s * P): P / pi per full period, the rest of the last one
    (P / (2 pi)) (1 - cos(2 pi r / P)) for r = t mod P < P / 2, else P / pi."""
    if not period > 0.0:
        return float(t)
    full, r = divmod(float(t), float(period))
    part = period / math.pi if r >= period / 2 else period / (2 * math.pi) * (1.0 - math.cos(2 * math.pi * r / period))
    return full * period / math.pi + part


def _bshape(axis, n):
    sh = [1, 1, 1]
    sh[axis] = n
    return tuple(sh)


# ---- initial state and static fields -----------------------------------------------------
def make_aux(p: Params, dtype):
    """Static per-run arrays: T0 at cell centres, the heating rate field (K/s), Poisson eigenvalues."""
    from .noise import heating_pattern
    xc, yc, zc = cell_centers(p)
    t0 = environment_temperature(p, yc).reshape(_bshape(UP, p.shape[UP]))
    X, Z = np.meshgrid(xc, zc, indexing="ij")
    if p.heating_rate > 0.0:
        pattern = np.asarray(heating_pattern(X, Z, p.noise_frequency, p.noise_amplitude, p.noise_offset,
                                             dtype=jnp.float64 if dtype == jnp.float64 else jnp.float32),
                             dtype=np.float64)
        if p.heating_patch_radius > 0.0:   # one heated patch around the centre, as in the particle solver
            q = 1.0 - ((X - 0.5 * p.size[0]) ** 2 + (Z - 0.5 * p.size[2]) ** 2) / p.heating_patch_radius ** 2
            pattern = pattern * np.where(q > 0.0, q * q, 0.0)
    else:
        pattern = np.zeros_like(X)
    # each cell heated by the part of it below heating_depth, as the particles weigh their layers: the
    # column's heat input is S_e * heating_depth at every resolution
    dy = p.steps[UP]
    mask = np.clip((p.heating_depth - (yc - 0.5 * dy)) / dy, 0.0, 1.0) if p.heating_depth > 0.0 else 0.0 * yc
    heat = p.heating_rate * pattern[:, None, :] * mask[None, :, None]
    v0 = initial_vapor(p, yc).reshape(_bshape(UP, p.shape[UP]))
    aux = {
        "t0": jnp.asarray(t0, dtype=dtype),
        "v0": jnp.asarray(v0, dtype=dtype),
        "heat": jnp.asarray(heat, dtype=dtype),
        "inv_eig": laplacian_eigenvalues(p.shape, p.steps, p.periodic, dtype),
    }
    if p.environment.has_inversion:   # Gamma_d - Gamma(y) per level (a linear profile: one number, in advect)
        aux["stable"] = jnp.asarray(stratification(p, yc).reshape(_bshape(UP, p.shape[UP])), dtype=dtype)
    if large_scale_active(p):          # L1-L3 per level, times dt
        for key, rate in zip(("ls_theta_sub", "ls_theta_rad", "ls_vapor_sub", "ls_vapor_tend"),
                             large_scale_rates(p, yc)):
            aux[key] = jnp.asarray((p.dt * rate).reshape(_bshape(UP, p.shape[UP])), dtype=dtype)
    return aux


def initial_state(p: Params, dtype, wave=None):
    """T = T0(y) (theta' = 0), vapor per atmosphere.vapor_profile, w = 0, velocity 0 or the [wave] mode."""
    xc, yc, zc = cell_centers(p)
    shape = p.shape
    t0 = environment_temperature(p, yc)
    vap = initial_vapor(p, yc)
    vapor = np.broadcast_to(vap.reshape(_bshape(UP, shape[UP])), shape)
    zeros = np.zeros(shape)
    ux, uy, uz = zeros, zeros, zeros
    if wave is not None and wave.amplitude > 0.0:
        ux, uy = wave_velocity(p, wave)
    st = {"ux": ux, "uy": uy, "uz": uz, "theta": zeros, "vapor": vapor, "cloud": zeros}
    out = {k: jnp.asarray(np.ascontiguousarray(v), dtype=dtype) for k, v in st.items()}
    out.update({k: jnp.zeros((), dtype=dtype) for k in SCALAR_KEYS})   # 0-d (ascontiguousarray makes 1-d)
    return out


def wave_velocity(p: Params, wave):
    """u = dpsi/dy, v = -dpsi/dx of psi = a sin(kx x) sin(ky y), peak |v| = amplitude, discretely
    divergence-free (psi sampled at cell edges, velocities as its differences)."""
    Lx, Ly = p.size[0], p.size[1]
    kx = 2.0 * math.pi * wave.modes_x / Lx
    ky = math.pi * wave.modes_y / Ly
    a = wave.amplitude / kx
    dx, dy = p.steps[0], p.steps[1]
    nx, ny, nz = p.shape
    xe = np.arange(nx + 1) * dx  # cell edges
    ye = np.arange(ny + 1) * dy
    psi = a * np.sin(kx * xe)[:, None] * np.sin(ky * ye)[None, :]   # (nx+1, ny+1) at (x edge, y edge)
    # ux at (x face i+1, y centre j): (psi[i+1, j+1] - psi[i+1, j]) / dy
    ux2 = (psi[1:, 1:] - psi[1:, :-1]) / dy
    # uy at (x centre i, y face j+1): -(psi[i+1, j+1] - psi[i, j+1]) / dx
    uy2 = -(psi[1:, 1:] - psi[:-1, 1:]) / dx
    ux = np.repeat(ux2[:, :, None], nz, axis=2)
    uy = np.repeat(uy2[:, :, None], nz, axis=2)
    return ux, uy


# ---- helpers ------------------------------------------------------------------------------
def _to_center(u, axis, periodic):
    return 0.5 * (u + _lower_face(u, axis, periodic))


def _to_faces(f, axis, periodic):
    """Cell-centred f averaged onto the upper faces along `axis` (0 on a stored wall face)."""
    if periodic:
        return 0.5 * (f + jnp.roll(f, -1, axis=axis))
    n = f.shape[axis]
    upper = jnp.concatenate([lax.slice_in_dim(f, 1, n, axis=axis), lax.slice_in_dim(f, n - 1, n, axis=axis)],
                            axis=axis)
    return zero_wall_faces(0.5 * (f + upper), axis, False)


def _ddx(f, axis, h, periodic):
    """Central difference of a cell-centred field; at a wall the ghost cell repeats the edge value."""
    if periodic:
        return (jnp.roll(f, -1, axis=axis) - jnp.roll(f, 1, axis=axis)) / (2.0 * h)
    n = f.shape[axis]
    up = jnp.concatenate([lax.slice_in_dim(f, 1, n, axis=axis), lax.slice_in_dim(f, n - 1, n, axis=axis)], axis=axis)
    dn = jnp.concatenate([lax.slice_in_dim(f, 0, 1, axis=axis), lax.slice_in_dim(f, 0, n - 1, axis=axis)], axis=axis)
    return (up - dn) / (2.0 * h)


class _Cfd:
    """jax-cfd grid and boundary conditions matching Params (built once per model)."""

    def __init__(self, p: Params):
        P = cfd_boundaries.BCType.PERIODIC
        D = cfd_boundaries.BCType.DIRICHLET
        N = cfd_boundaries.BCType.NEUMANN
        self.grid = cfd_grids.Grid(p.shape, domain=tuple((0.0, L) for L in p.size))
        self.vel_bc = cfd_boundaries.HomogeneousBoundaryConditions(
            tuple((P, P) if per else (D, D) for per in p.periodic))
        self.scalar_bc = cfd_boundaries.HomogeneousBoundaryConditions(
            tuple((P, P) if per else (N, N) for per in p.periodic))
        self.faces = self.grid.cell_faces
        self.center = self.grid.cell_center

    def velocity(self, vel):
        return tuple(cfd_grids.GridVariable(cfd_grids.GridArray(u, o, self.grid), self.vel_bc)
                     for u, o in zip(vel, self.faces))

    def scalar(self, c):
        return cfd_grids.GridVariable(cfd_grids.GridArray(c, self.center, self.grid), self.scalar_bc)


_CFD_CACHE: dict = {}


def _cfd(p: Params) -> _Cfd:
    key = (p.shape, p.size, p.periodic)
    if key not in _CFD_CACHE:
        _CFD_CACHE[key] = _Cfd(p)
    return _CFD_CACHE[key]


def courant_sum(vel, p: Params, dt):
    """dt * max over cells of sum_a |u_a| / h_a, with each component's largest adjacent face value."""
    total = None
    for a, (u, h, per) in enumerate(zip(vel, p.steps, p.periodic)):
        c = jnp.maximum(jnp.abs(u), jnp.abs(_lower_face(u, a, per))) / h
        total = c if total is None else total + c
    return dt * jnp.max(total)


# ---- phases ---------------------------------------------------------------------------------
def advect(state, aux, p: Params):
    """Flux-form van Leer advection of theta', v, w and the velocity (sub-stepped), then the
    theta' source -u_y (Gamma_d - Gamma(y)) (the adiabatic cooling of eq. 7 relative to the
    environment).  Returns (state, number of sub-steps)."""
    cfd = _cfd(p)
    dt = p.dt
    vel0 = (state["ux"], state["uy"], state["uz"])
    cfl = courant_sum(vel0, p, dt)
    nsub = jnp.clip(jnp.ceil(cfl / p.cfl_target), 1, p.max_substeps).astype(jnp.int32)
    dts = (dt / nsub).astype(state["theta"].dtype)
    V = cfd.velocity(vel0)

    def body(_, fields):
        theta, vapor, cloud, ux, uy, uz = fields
        out = []
        for c in (theta, vapor, cloud):
            out.append(c + dts * cfd_advection.advect_van_leer(cfd.scalar(c), V, dts).data)
        for a, (u, var) in enumerate(zip((ux, uy, uz), cfd.velocity((ux, uy, uz)))):
            un = u + dts * cfd_advection.advect_van_leer(var, V, dts).data
            out.append(zero_wall_faces(un, a, p.periodic[a]))
        return tuple(out)

    fields = (state["theta"], state["vapor"], state["cloud"], *vel0)
    theta, vapor, cloud, ux, uy, uz = lax.fori_loop(0, nsub, body, fields)
    uy_c = _to_center(vel0[UP], UP, p.periodic[UP])
    stable = aux["stable"] if "stable" in aux else p.dry_lapse_rate - p.environment.lapse_rate
    theta = theta - dt * stable * uy_c
    return {**state, "ux": ux, "uy": uy, "uz": uz, "theta": theta, "vapor": vapor, "cloud": cloud}, nsub


def phase_transition(p: Params, T, vapor, cloud, dt):
    """Eq. 9-11 integrated exactly for the linearised coupled system; returns (vapor, cloud, dT).

    q = v + w; s = A exp(B/(T+C)); gamma = min(s, q); D = v - gamma.
    s < q: s' = s (-B)/(T+C)^2, k = alpha (1 + Q s'), dw = D (1 - exp(-k dt)) / (1 + Q s');
    else (all cloud evaporates toward q): dw = -w (1 - exp(-alpha dt)).
    dw = max(dw, -w); w += dw; v = q - w; T += Q dw.
    """
    Q, alpha, B, C = p.latent_heat, p.phase_rate, p.saturation_b, p.saturation_c
    q = vapor + cloud
    s = saturation(p, T)
    saturated = s < q
    sprime = s * (-B) / ((T + C) * (T + C))
    denom = 1.0 + Q * sprime
    k = alpha * denom
    dw_sat = (vapor - s) * (-jnp.expm1(-k * dt)) / denom
    dw_dry = -cloud * (-jnp.expm1(-alpha * dt))
    dw = jnp.where(saturated, dw_sat, dw_dry)
    dw = jnp.maximum(dw, -cloud)
    cloud = cloud + dw
    vapor = q - cloud
    return vapor, cloud, Q * dw


def vorticity_force(vel, p: Params):
    """Vorticity confinement f = eps (N x omega) at cell centres (m/s^2), eps = pbf.vorticity (m/s)."""
    steps, per = p.steps, p.periodic
    uc = [_to_center(u, a, per[a]) for a, u in enumerate(vel)]
    d = lambda f, a: _ddx(f, a, steps[a], per[a])  # noqa: E731
    wx = d(uc[2], 1) - d(uc[1], 2)
    wy = d(uc[0], 2) - d(uc[2], 0)
    wz = d(uc[1], 0) - d(uc[0], 1)
    mag = jnp.sqrt(wx * wx + wy * wy + wz * wz)
    gx, gy, gz = d(mag, 0), d(mag, 1), d(mag, 2)
    gnorm = jnp.sqrt(gx * gx + gy * gy + gz * gz)
    inv = jnp.where(gnorm > 0.0, 1.0 / jnp.where(gnorm > 0.0, gnorm, 1.0), 0.0)
    nx, ny, nz = gx * inv, gy * inv, gz * inv
    eps = p.vorticity
    return (eps * (ny * wz - nz * wy), eps * (nz * wx - nx * wz), eps * (nx * wy - ny * wx))


def physics(state, aux, p: Params):
    """Vorticity confinement, then cloud dynamics in the particle solver's order (eq. 5, L1-L3, C2, 6, 7, 9-11)."""
    dt = p.dt
    per = p.periodic
    vel = [state["ux"], state["uy"], state["uz"]]
    if p.vorticity > 0.0:
        f = vorticity_force(vel, p)
        vel = [u + dt * _to_faces(fa, a, per[a]) for a, (u, fa) in enumerate(zip(vel, f))]
    theta, vapor, cloud = state["theta"], state["vapor"], state["cloud"]
    clock = state["time"]
    vol = p.cell_volume
    out = {}
    # eq. 5: ground heating (aux["heat"] = S_e * max(0, 1 + a * noise) times the part of the cell below heating_depth),
    # times the time-of-day factor of eq. C1 at the step's mid-time
    if p.heating_rate > 0.0:
        theta = theta + (dt * diurnal_factor(clock + 0.5 * dt, p.diurnal_period)) * aux["heat"]
    # L1-L3: large-scale subsidence, radiative cooling and moisture tendency (per-level rates times dt)
    if "ls_theta_sub" in aux:
        theta_sub = theta + aux["ls_theta_sub"]
        theta_new = theta_sub + aux["ls_theta_rad"]
        vapor_sub = jnp.maximum(vapor + aux["ls_vapor_sub"], 0.0)
        vapor_new = jnp.maximum(vapor_sub + aux["ls_vapor_tend"], 0.0)
        out["heat_subsidence_total"] = state["heat_subsidence_total"] + jnp.sum(theta_sub - theta) * vol
        out["heat_radiation_total"] = state["heat_radiation_total"] + jnp.sum(theta_new - theta_sub) * vol
        out["water_subsidence_total"] = state["water_subsidence_total"] + jnp.sum(vapor_sub - vapor) * vol
        out["water_tendency_total"] = state["water_tendency_total"] + jnp.sum(vapor_new - vapor_sub) * vol
        theta, vapor = theta_new, vapor_new
    # eq. C2: relaxation toward the initial profiles, exact over the step (theta' = T - T0(y) -> 0, v -> v0)
    if p.relaxation_time > 0.0:
        decay = math.exp(-dt / p.relaxation_time)
        theta_new = theta * decay
        vapor_new = jnp.maximum(aux["v0"] + (vapor - aux["v0"]) * decay, 0.0)
        out["heat_relaxation_total"] = state["heat_relaxation_total"] + jnp.sum(theta_new - theta) * vol
        out["water_relaxation_total"] = state["water_relaxation_total"] + jnp.sum(vapor_new - vapor) * vol
        theta, vapor = theta_new, vapor_new
    # eq. 6: buoyancy - cloud weight (at cell centres, averaged onto the vertical faces) + pbf.gravity
    t0 = aux["t0"]
    b = p.buoyancy * theta / t0 - p.cloud_gravity * cloud
    vel[UP] = vel[UP] + dt * _to_faces(b, UP, per[UP])
    for a, g in enumerate(p.gravity):
        if g != 0.0:
            vel[a] = zero_wall_faces(vel[a] + dt * g, a, per[a])
    # eq. 7: adiabatic cooling is the conservation of theta = T + Gamma_d y in advect() (nothing to add here).
    # eq. 9-11: phase transition and latent heat
    T = t0 + theta
    vapor, cloud, dT = phase_transition(p, T, vapor, cloud, dt)
    theta = theta + dT
    # eq. C3: autoconversion, w above q_c0 decays at k_auto (exact over the step) and leaves as rain;
    # its latent heat was released at condensation, so T does not change
    if p.autoconversion_rate > 0.0:
        q0 = p.autoconversion_threshold
        cloud_new = jnp.where(cloud > q0, q0 + (cloud - q0) * math.exp(-p.autoconversion_rate * dt), cloud)
        out["rain_total"] = state["rain_total"] + jnp.sum(cloud - cloud_new) * vol
        cloud = cloud_new
    out["time"] = clock + dt
    return {**state, **out, "ux": vel[0], "uy": vel[1], "uz": vel[2], "theta": theta, "vapor": vapor, "cloud": cloud}


def pressure_project(state, aux, p: Params):
    vel, _ = project((state["ux"], state["uy"], state["uz"]), p.steps, p.periodic, aux["inv_eig"])
    return {**state, "ux": vel[0], "uy": vel[1], "uz": vel[2]}


def full_step(state, aux, p: Params):
    """advect -> physics -> project. Returns (state, nsub)."""
    state, nsub = advect(state, aux, p)
    state = physics(state, aux, p)
    state = pressure_project(state, aux, p)
    return state, nsub


# ---- budget ---------------------------------------------------------------------------------
# The particle solver's StepBudget (pbf_cuda/csrc/solver_api.h) for the grid: each term is the step's
# change of the mass-weighted mean temperature (K) from one process.  Cells hold equal masses
# (rest_density * cell volume), so mass-weighted means are plain cell means.
#   heat_source    = dt mean(S)                      ground heating (eq. 5)
#   heat_latent    = Q (mean(w_after) - mean(w_before))   latent heat (eq. 11)
#   heat_adiabatic = -Gamma_d dt mean(u_y)            eq. 7: -Gamma_d times the rise of the mass centre
#                                                     (0 up to the projection's tolerance: a divergence-free
#                                                     flow between walls carries no net mass upward)
#   heat_smoothing = 0                                no temperature smoothing in the grid (section 4.1)
#   heat_numerical = the rest of the change of mean(T): what the advection scheme creates or
#                    destroys (flux-form van Leer conserves sum(theta') only for a divergence-free
#                    velocity; it is the grid's counterpart of the particles' smoothing heat)
# The five add up to mean(T_after) - mean(T_before) exactly.
BUDGET_TERMS = ("heat_source", "heat_latent", "heat_adiabatic", "heat_smoothing", "heat_numerical")


def budget_terms(before, after, aux, p: Params):
    """The step budget (K, see BUDGET_TERMS) from the states before and after one step; a 1-D array."""
    dt = p.dt
    source = dt * jnp.mean(aux["heat"]) if p.heating_rate > 0.0 else jnp.zeros((), before["theta"].dtype)
    latent = p.latent_heat * (jnp.mean(after["cloud"]) - jnp.mean(before["cloud"]))
    adiabatic = -p.dry_lapse_rate * dt * jnp.mean(_to_center(before["uy"], UP, p.periodic[UP]))
    change = jnp.mean(after["theta"] - before["theta"])
    zero = jnp.zeros_like(change)
    return jnp.stack([source, latent, adiabatic, zero, change - source - latent - adiabatic])


def step_with_budget(state, aux, p: Params):
    """full_step and its budget: (state, nsub, budget_terms)."""
    new, nsub = full_step(state, aux, p)
    return new, nsub, budget_terms(state, new, aux, p)
