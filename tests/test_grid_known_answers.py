"""Known answers for the grid baseline's terms and its advection sub-stepping (issue 54).

  eq. 6     buoyancy and cloud-water loading: du_y = dt (k_b theta' / T0 - k_g w) on the vertical faces
  eq. 7     adiabatic cooling relative to the environment: d theta' = -dt (Gamma_d - Gamma) u_y
  eq. 9-11  phase transition and latent heat: the exact exponential, d theta' = Q dw, v + w kept
  eq. 5     ground heating: d theta' = S_e f dt, f the part of the cell below heating_depth
  vorticity confinement f = eps (N x omega) of a shear flow u_x = U sin(k y) (closed form)
  sub-steps a scalar blob carried by a uniform flow with 3 sub-steps moves U dt, as 3 steps of dt / 3 do
"""
import dataclasses
import math

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("jax_cfd")
import jax.numpy as jnp  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from grid_baseline import model  # noqa: E402
from pbf_cuda.scene import load_scene  # noqa: E402

SETTINGS = settings(max_examples=10, deadline=None, derandomize=True)
SHAPE = (12, 10, 6)


@pytest.fixture(scope="module", autouse=True)
def x64():
    jax.config.update("jax_enable_x64", True)   # left on (as test_grid_physics.py)


ADVECT = jax.jit(model.advect, static_argnums=2)   # compiled once per Params


def quiet_params(shape=SHAPE, **overrides):
    """The growing scene's grid parameters with every process off but those in overrides."""
    p = model.params_from_scene(load_scene("growing", **{"domain.size": [1200.0, 1000.0, 600.0]}), shape)
    base = dict(heating_rate=0.0, phase_rate=0.0, vorticity=0.0, relaxation_time=0.0, autoconversion_rate=0.0,
                gravity=(0.0, 0.0, 0.0))
    return dataclasses.replace(p, **{**base, **overrides})


def state_of(p, **fields):
    st = model.initial_state(p, jnp.float64)
    st.update({k: jnp.asarray(v, jnp.float64) for k, v in fields.items()})
    return st


def faces_up(b):
    """Cell-centred b averaged onto the upper y faces, the top (wall) face 0."""
    out = np.zeros_like(b)
    out[:, :-1, :] = 0.5 * (b[:, :-1, :] + b[:, 1:, :])
    return out


# ---- eq. 6 ---------------------------------------------------------------------------------------------
@SETTINGS
@given(k_b=st.floats(0.5, 20.0), k_g=st.floats(0.5, 20.0), dt=st.floats(0.5, 5.0), seed=st.integers(0, 2**16))
def test_grid_buoyancy_and_cloud_loading_at_rest(k_b, k_g, dt, seed):
    p = quiet_params(buoyancy=k_b, cloud_gravity=k_g, dt=dt)
    aux = model.make_aux(p, jnp.float64)
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-5.0, 5.0, SHAPE)
    cloud = rng.uniform(0.0, 5e-3, SHAPE)
    out = model.physics(state_of(p, theta=theta, cloud=cloud), aux, p)
    t0 = np.asarray(aux["t0"])
    expect = dt * faces_up(k_b * theta / t0 - k_g * cloud)
    assert np.allclose(np.asarray(out["uy"]), expect, rtol=1e-12, atol=1e-14)
    assert np.abs(np.asarray(out["ux"])).max() == 0.0 and np.abs(np.asarray(out["uz"])).max() == 0.0
    # no buoyancy where theta' = 0: the cloud water pulls down
    dry = model.physics(state_of(p, cloud=cloud), aux, p)
    assert np.all(np.asarray(dry["uy"])[:, :-1, :] < 0.0)


# ---- eq. 7 ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dt, gamma_d", [(4.5, 1.6e-2)])
@settings(max_examples=6, deadline=None, derandomize=True)
@given(U=st.floats(-3.0, 3.0).filter(lambda u: abs(u) > 0.05))
def test_grid_adiabatic_term_of_a_uniform_updraft(dt, gamma_d, U):
    p = quiet_params(dt=dt, dry_lapse_rate=gamma_d)
    aux = model.make_aux(p, jnp.float64)
    uy = np.full(SHAPE, U)
    uy[:, -1, :] = 0.0                                             # the lid's face
    out, _ = ADVECT(state_of(p, uy=uy), aux, p)
    uy_c = 0.5 * (uy + np.concatenate([np.zeros_like(uy[:, :1]), uy[:, :-1]], axis=1))
    expect = -dt * (gamma_d - p.environment.lapse_rate) * uy_c
    assert np.allclose(np.asarray(out["theta"]), expect, rtol=1e-12, atol=1e-14)


# ---- eq. 9-11 ------------------------------------------------------------------------------------------
@SETTINGS
@given(alpha=st.floats(0.01, 2.0), Q=st.floats(500.0, 3000.0), dt=st.floats(0.5, 5.0), seed=st.integers(0, 2**16))
def test_grid_phase_transition_and_latent_heat(alpha, Q, dt, seed):
    p = quiet_params(phase_rate=alpha, latent_heat=Q, dt=dt, buoyancy=0.0, cloud_gravity=0.0)
    aux = model.make_aux(p, jnp.float64)
    rng = np.random.default_rng(seed)
    t0 = np.broadcast_to(np.asarray(aux["t0"]), SHAPE)
    theta = rng.uniform(-3.0, 3.0, SHAPE)
    T = t0 + theta
    s = p.saturation_a * np.exp(p.saturation_b / (T + p.saturation_c))
    vapor = s * rng.uniform(0.7, 1.3, SHAPE)
    cloud = np.where(rng.uniform(size=SHAPE) < 0.5, 0.0, rng.uniform(0.0, 2e-3, SHAPE))
    out = model.physics(state_of(p, theta=theta, vapor=vapor, cloud=cloud), aux, p)
    q = vapor + cloud
    ds = s * (-p.saturation_b) / (T + p.saturation_c) ** 2
    gain = 1.0 + Q * ds
    dw = np.where(s < q, (vapor - s) * (-np.expm1(-alpha * gain * dt)) / gain, -cloud * (-np.expm1(-alpha * dt)))
    dw = np.maximum(dw, -cloud)
    assert np.allclose(np.asarray(out["cloud"]), cloud + dw, rtol=1e-10, atol=1e-15)
    assert np.allclose(np.asarray(out["theta"]), theta + Q * dw, rtol=1e-10, atol=1e-12)
    assert np.allclose(np.asarray(out["vapor"]) + np.asarray(out["cloud"]), q, rtol=1e-13, atol=0)
    assert np.all(dw[vapor > 1.02 * s] > 0.0) and np.all(dw[vapor < 0.98 * s] <= 0.0)


# ---- eq. 5 ---------------------------------------------------------------------------------------------
@SETTINGS
@given(rate=st.floats(0.005, 0.5), depth=st.floats(20.0, 400.0), dt=st.floats(0.5, 5.0))
def test_grid_ground_heating(rate, depth, dt):
    p = quiet_params(heating_rate=rate, heating_depth=depth, noise_amplitude=0.0, heating_patch_radius=0.0, dt=dt,
                     buoyancy=0.0, cloud_gravity=0.0)
    aux = model.make_aux(p, jnp.float64)
    out = model.physics(state_of(p), aux, p)
    dy = p.steps[1]
    yc = (np.arange(SHAPE[1]) + 0.5) * dy
    f = np.clip((depth - (yc - 0.5 * dy)) / dy, 0.0, 1.0)
    expect = np.broadcast_to((rate * dt * f)[None, :, None], SHAPE)
    assert np.allclose(np.asarray(out["theta"]), expect, rtol=1e-12, atol=1e-14)


# ---- vorticity confinement ------------------------------------------------------------------------------
def test_grid_vorticity_confinement_of_a_shear_flow():
    """u_x = U sin(k y): omega = -U k cos(k y) z, |omega| = U k |cos k y|, N = -sign(sin cos) y, so
    f = eps N x omega = eps U k |cos(k y)| sign(sin(k y)) x."""
    shape = (4, 64, 4)
    p = dataclasses.replace(quiet_params(shape), periodic=(True, True, True), vorticity=0.7)
    U, L = 2.0, p.size[1]
    k = 2.0 * math.pi / L
    yc = (np.arange(shape[1]) + 0.5) * p.steps[1]
    ux = np.broadcast_to((U * np.sin(k * yc))[None, :, None], shape)
    zero = np.zeros(shape)
    f = [np.asarray(c) for c in model.vorticity_force((jnp.asarray(ux), jnp.asarray(zero), jnp.asarray(zero)), p)]
    expect = 0.7 * U * k * np.abs(np.cos(k * yc)) * np.sign(np.sin(k * yc))
    away = (np.abs(np.sin(k * yc)) > 0.3) & (np.abs(np.cos(k * yc)) > 0.3)   # the kinks of |omega| and of N
    assert np.allclose(f[0][0, away, 0], expect[away], rtol=0.03)
    assert np.abs(f[1]).max() < 1e-12 and np.abs(f[2]).max() < 1e-12


# ---- sub-stepping ----------------------------------------------------------------------------------------
def blob_centre(c, dx, L):
    """Circular mean of the x profile of c (periodic x), m."""
    prof = np.asarray(c).sum(axis=(1, 2))
    x = (np.arange(len(prof)) + 0.5) * dx
    ang = 2.0 * math.pi * x / L
    return (math.atan2((prof * np.sin(ang)).sum(), (prof * np.cos(ang)).sum()) % (2.0 * math.pi)) * L / (2 * math.pi)


def test_grid_substeps_carry_a_scalar_blob_U_dt(courant=2.4):
    shape = (48, 4, 4)
    p0 = quiet_params(shape)
    dx = p0.steps[0]
    U = 3.0
    dt = courant * dx / U
    p = dataclasses.replace(p0, dt=dt, cfl_target=0.8)
    aux = model.make_aux(p, jnp.float64)
    x = (np.arange(shape[0]) + 0.5) * dx
    blob = np.broadcast_to(np.exp(-0.5 * ((x - 0.3 * p.size[0]) / (3 * dx)) ** 2)[:, None, None], shape)
    fields = dict(ux=np.full(shape, U), theta=blob, vapor=2e-3 * blob, cloud=1e-4 * blob)
    st0 = state_of(p, **fields)
    out, nsub = ADVECT(st0, aux, p)
    assert int(nsub) == math.ceil(courant / 0.8) > 1
    # the same interval in nsub steps of dt / nsub, each one sub-step
    p_fine = dataclasses.replace(p, dt=dt / int(nsub))
    fine = st0
    for _ in range(int(nsub)):
        fine, n1 = ADVECT(fine, aux, p_fine)
        assert int(n1) == 1
    for key, scale in (("theta", 1.0), ("vapor", 2e-3), ("cloud", 1e-4)):
        assert np.allclose(np.asarray(out[key]), np.asarray(fine[key]), rtol=0, atol=1e-12 * scale), key
        moved = (blob_centre(out[key], dx, p.size[0]) - blob_centre(blob, dx, p.size[0])) % p.size[0]
        assert abs(moved - U * dt) < 0.05 * dx, (key, moved, U * dt)
        # flux form: the scalar's total is kept
        assert abs(float(np.sum(out[key])) - float(np.sum(blob)) * scale) < 1e-10 * float(np.sum(blob)) * scale
    assert np.allclose(np.asarray(out["ux"]), U, rtol=1e-12)
