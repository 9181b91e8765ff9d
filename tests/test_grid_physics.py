"""Grid baseline physics: conservation, rest state, phase transition, and the design's physical checks (docs/design.md)
(lifting condensation level, internal gravity wave frequency) on the grid."""
import math

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("jax_cfd")
import jax.numpy as jnp  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from solver_helpers import INVERSION_EVERYWHERE, cloud_base_of_layers, model_lcl  # noqa: E402

from grid_baseline import GridSimulation  # noqa: E402
from pbf_cuda.scene import load_scene  # noqa: E402
from grid_baseline.model import params_from_scene, phase_transition  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def x64():
    jax.config.update("jax_enable_x64", True)   # left on (see test_grid_noise.py)


def _dew_point(p, q):
    """The model's dew point: s(T_d) = q with s = A exp(B/(T+C))  =>  T_d = B / ln(q/A) - C."""
    return p.saturation_b / math.log(q / p.saturation_a) - p.saturation_c


# ---- phase transition (eq. 9-11) -----------------------------------------------------------
def _params():
    return params_from_scene(load_scene("growing"), (4, 4, 4))


def _reference_integration(p, T, v, w, dt, n=20000):
    """The nonlinear ODE dw/dt = alpha (v - min(s(T), q)), dT/dt = Q dw/dt, dv = -dw, in n RK4 steps."""
    q = v + w

    def rhs(T, w):
        s = p.saturation_a * np.exp(p.saturation_b / (T + p.saturation_c))
        return p.phase_rate * ((q - w) - min(s, q))

    h = dt / n
    for _ in range(n):
        k1 = rhs(T, w)
        k2 = rhs(T + 0.5 * h * p.latent_heat * k1, w + 0.5 * h * k1)
        k3 = rhs(T + 0.5 * h * p.latent_heat * k2, w + 0.5 * h * k2)
        k4 = rhs(T + h * p.latent_heat * k3, w + h * k3)
        dw = h * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
        w += dw
        T += p.latent_heat * dw
    return T, q - w, w


def test_phase_transition_matches_ode_and_conserves():
    p = _params()
    T0 = 285.0
    s0 = p.saturation_a * math.exp(p.saturation_b / (T0 + p.saturation_c))
    for v, w, dt in [(1.01 * s0, 0.0, 2.0), (0.98 * s0, 2e-4, 2.0), (1.002 * s0, 1e-4, 0.5)]:
        Tn, vn, wn = _reference_integration(p, T0, v, w, dt)
        vv, ww, dT = phase_transition(p, jnp.asarray(T0), jnp.asarray(v), jnp.asarray(w), dt)
        assert float(vv + ww) == pytest.approx(v + w, rel=1e-15)
        assert float(dT) == pytest.approx(p.latent_heat * (float(ww) - w), rel=1e-12)
        # exact for the linearised system: close to the nonlinear ODE for small departures
        assert float(ww) == pytest.approx(wn, rel=2e-3, abs=1e-9)
        assert float(T0 + dT) == pytest.approx(Tn, abs=5e-4)


def test_phase_transition_stable_for_any_alpha_dt():
    p = _params()
    rng = np.random.default_rng(0)
    T = jnp.asarray(rng.uniform(260.0, 310.0, 1000))
    s = p.saturation_a * jnp.exp(p.saturation_b / (T + p.saturation_c))
    v = s * jnp.asarray(rng.uniform(0.5, 1.5, 1000))
    w = jnp.asarray(rng.uniform(0.0, 3e-3, 1000))
    for dt in (1.0, 1e2, 1e4, 1e7):   # alpha * dt from 0.5 to 5e6
        vv, ww, dT = phase_transition(p, T, v, w, dt)
        assert bool(jnp.all(jnp.isfinite(vv)) & jnp.all(jnp.isfinite(ww)) & jnp.all(jnp.isfinite(dT)))
        assert float(jnp.min(ww)) >= 0.0
        np.testing.assert_allclose(np.asarray(vv + ww), np.asarray(v + w), rtol=1e-14)
    # all-cloud evaporation toward q is exact: w (1 - exp(-alpha dt))
    Td = 300.0
    sd = p.saturation_a * math.exp(p.saturation_b / (Td + p.saturation_c))
    vv, ww, dT = phase_transition(p, jnp.asarray(Td), jnp.asarray(0.5 * sd), jnp.asarray(1e-3), 2.0)
    assert float(ww) == pytest.approx(1e-3 * math.exp(-p.phase_rate * 2.0), rel=1e-12)


# ---- conservation and rest --------------------------------------------------------------------
def test_total_water_conserved_with_heating_and_condensation():
    scene = load_scene("growing").replace(**{"atmosphere.initial_vapor_ratio": 1.02,
                                             "atmosphere.heating_rate": 0.5,
                                             "atmosphere.heating_depth": 400.0})
    sim = GridSimulation(scene, resolution=(16, 16, 16), dtype="float64")
    rows = sim.run(60, stats_every=20)
    w0 = rows[0]["total_water"]
    assert rows[1]["total_cloud"] > 0.0                   # condensation active
    assert max(r["max_speed"] for r in rows) > 1.0        # and the air moves
    for r in rows[1:]:
        assert abs(r["total_water"] - w0) / w0 < 1e-12, r["total_water"] - w0
        assert r["divergence_rel"] < 1e-10
    # The budget columns (the particle solver's meaning, K of mass-weighted mean temperature): latent heat
    # is Q times the mean cloud water formed, the advection's numerical heat is negligible, and the terms
    # add up to the change of the mean temperature.
    last = rows[-1]
    assert last["mass"] == pytest.approx(np.prod(scene.domain.size) * scene.particles.rest_density)
    assert last["heat_latent_total"] == pytest.approx(scene.atmosphere.latent_heat * last["total_cloud"] / last["mass"],
                                                      rel=1e-9)
    assert abs(last["heat_numerical_total"]) < 1e-3 * last["heat_source_total"]
    terms = sum(last[f"heat_{k}_total"] for k in ("source", "latent", "adiabatic", "smoothing", "numerical"))
    assert terms == pytest.approx(last["mean_temperature"] - rows[0]["mean_temperature"], rel=1e-9)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_resting_stratified_atmosphere_stays_at_rest(dtype):
    scene = load_scene("stratified").replace(**{"wave.amplitude": 0.0})
    assert scene.atmosphere.heating_rate == 0.0
    sim = GridSimulation(scene, dtype=dtype)
    sim.step(200)
    assert all(v.dtype == jnp.dtype(dtype) for v in sim.raw_state().values())
    st = sim.stats()
    assert st["dtype"] == dtype
    assert st["max_speed"] < 1e-10
    f = sim.fields()
    t0 = scene.atmosphere.ground_temperature - scene.atmosphere.lapse_rate * f["y"]
    assert np.max(np.abs(f["temperature"] - t0[None, :, None])) < 1e-9 * 300
    assert st["total_cloud"] == 0.0


# ---- docs/design.md checks: lifting condensation level-----------------------------------------------
@settings(max_examples=2, deadline=None)   # each example compiles the step (~7 s); the particle twin draws 30
@given(ground=st.floats(280.0, 305.0), rh=st.floats(0.5, 0.95))
def test_uniform_vapor_cloud_layer_base_at_lcl(ground, rh):
    """Parcel scene with uniform vapor (atmosphere.vapor_profile = 'uniform'): neutral (theta = T_ground
    everywhere) and one q = rh s(T_ground) at every height, so the air that condenses first is the
    environment air itself, T_s = T_ground, T_d from its q: everything above z = (T_s - T_d)/Gamma_d is
    supersaturated and the first cloud forms in the first step as a layer.  Every cell whose centre lies
    above that height is cloudy and every one below is clear (the grid samples the base to a cell), and
    the base of the layer-mean cloud water (zero of the line through the two lowest cloudy layers) is
    within 1% of it.  The particle solver's twin: tests/test_cloud_physics.py."""
    scene = load_scene("parcel").replace(**{"atmosphere.vapor_profile": "uniform",
                                            "domain.size": [300.0, 1600.0, 300.0], "atmosphere.heating_rate": 0.0,
                                            "atmosphere.ground_temperature": ground,
                                            "atmosphere.initial_vapor_ratio": rh})
    sim = GridSimulation(scene)
    p = sim.params
    assert sim.fields()["cloud"].max() == 0.0
    sim.step(1)
    f = sim.fields()
    w = f["cloud"]
    lcl = model_lcl(scene.atmosphere, ground, rh * scene.saturation(ground))
    assert 50.0 < lcl < 1500.0
    above = f["y"] > lcl
    assert (w[:, above, :] > 0.0).all() and (w[:, ~above, :] == 0.0).all()
    base = cloud_base_of_layers(f["y"], w.mean(axis=(0, 2)))
    assert abs(base / lcl - 1.0) < 0.01, (base, lcl, p.steps[1])


def test_parcel_scene_rising_air_condenses_at_its_lcl():
    """Parcel scene with a relative-humidity profile (vapor_profile = 'relative', as shipped: RH 0.8 at
    every height, so the environment never saturates): air heated at the ground rises and must first
    condense where its own dew point is reached.
    T_s is the potential temperature theta - Q w (conserved through condensation) of the air that condenses
    first, T_d the dew point of its total water q = v + w; z = (T_s - T_d)/Gamma_d is compared with the
    height of that cell.  (Mixing on the grid dilutes the rising air, so T_s and q are taken from the
    condensing air, not from the ground.)"""
    scene = load_scene("parcel").replace(**{"atmosphere.vapor_profile": "relative"})
    sim = GridSimulation(scene)
    p = sim.params
    for _ in range(600):
        sim.step(1)
        f = sim.fields()
        if f["cloud"].max() > 0.0:
            break
    else:
        pytest.fail("no cloud formed in 600 steps")
    w = f["cloud"]
    i = np.unravel_index(np.argmax(w), w.shape)
    z = f["y"][i[1]]
    theta_s = f["potential_temperature"][i] - p.latent_heat * w[i]
    q = f["vapor"][i] + w[i]
    lcl = (theta_s - _dew_point(p, q)) / p.dry_lapse_rate
    assert z > scene.atmosphere.heating_depth and f["velocity"][i][1] > 0.0   # rising air, above the heating
    assert abs(z - lcl) / lcl < 0.10, (z, lcl, sim.step_count)
    assert abs(z - lcl) < p.steps[1], (z, lcl, sim.step_count)                # within one cell


# ---- docs/design.md checks: internal gravity wave-----------------------------------------------------------
@pytest.mark.parametrize("overrides", [{}, INVERSION_EVERYWHERE], ids=["linear", "inversion-layer"])
def test_stratified_wave_frequency(overrides):
    """The stratified scene's mode psi = a sin(kx x) sin(ky y) oscillates at omega = N kx/|k|,
    N^2 = (g/T)(Gamma_d - Gamma(y)) (g = atmosphere.buoyancy, T the mean environment temperature).
    omega is measured from the zero crossings of the vertical velocity's projection on the mode. Also in
    an inversion layer that fills the box (T0 rising 1 K/km: N 1.8 times the linear profile's)."""
    sim = GridSimulation(load_scene("stratified").replace(**overrides))
    p = sim.params
    Lx, Ly = p.size[0], p.size[1]
    w = sim.scene.wave
    kx, ky = 2 * math.pi * w.modes_x / Lx, math.pi * w.modes_y / Ly
    xc = (np.arange(p.shape[0]) + 0.5) * p.steps[0]
    yf = (np.arange(p.shape[1]) + 1.0) * p.steps[1]
    mode = (np.cos(kx * xc)[:, None] * np.sin(ky * yf)[None, :])[:, :, None]

    def amplitude():
        uy = np.asarray(sim.raw_state()["uy"])
        return float((uy * mode).sum() / (mode * mode).sum() / p.shape[2])

    t, a = [0.0], [amplitude()]
    assert abs(a[0]) == pytest.approx(w.amplitude, rel=0.05)
    for _ in range(sim.scene.time.steps):
        sim.step(1)
        t.append(sim.time)
        a.append(amplitude())
    t, a = np.array(t), np.array(a)
    k = np.nonzero(a[:-1] * a[1:] < 0)[0]
    crossings = t[k] + (t[k + 1] - t[k]) * a[k] / (a[k] - a[k + 1])
    assert len(crossings) >= 3
    omega = math.pi / np.mean(np.diff(crossings))
    T = float(p.environment.temperature(Ly / 2))
    N = math.sqrt(p.buoyancy / T * (p.dry_lapse_rate - float(p.environment.lapse(Ly / 2))))
    expected = N * kx / math.hypot(kx, ky)
    assert abs(omega - expected) / expected < 0.10, (omega, expected)
