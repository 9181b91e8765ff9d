"""The environment profile T0(y) with a capping inversion (pbf_cuda/environment.py, csrc/environment.h).

Physical statements: the profile is continuous and its slope is the lapse it declares; air at rest in the
profile stays at rest in both solvers (no buoyancy, no anomaly from the density shifts or the smoothing, the
heat budget closed), which also checks that the solver's T0(y) is the Python one; a gravity wave in the
inversion layer oscillates at that layer's buoyancy frequency; a scene whose profile leaves the saturation
law's range is refused by name.
"""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pbf_cuda import Simulation, load_scene
from pbf_cuda.environment import EnvironmentProfile, vapor_ratio
from pbf_cuda.scene import SceneError
from solver_helpers import BACKENDS, INVERSION_EVERYWHERE, atmosphere_at_rest

profiles = st.builds(EnvironmentProfile, ground_temperature=st.floats(250.0, 320.0),
                     lapse_rate=st.floats(-0.01, 0.0098), inversion_height=st.floats(10.0, 3000.0),
                     inversion_depth=st.floats(1.0, 1000.0), inversion_strength=st.floats(0.0, 20.0),
                     lapse_rate_above=st.floats(-0.01, 0.0098))


@settings(max_examples=200, deadline=None)
@given(profile=profiles)
def test_profile_is_continuous_and_its_slope_is_the_declared_lapse(profile):
    zi, d = profile.inversion_height, profile.inversion_depth
    eps = 1e-6 * max(zi, 1.0)
    steepest = max(abs(profile.lapse_rate), abs(profile.lapse_rate_above), profile.inversion_strength / d)
    for kink in (zi, zi + d):   # no jump: across 2 eps the profile moves by at most its steepest slope
        jump = float(profile.temperature(kink + eps) - profile.temperature(kink - eps))
        assert abs(jump) <= 2 * eps * steepest * (1 + 1e-6) + 1e-9
    # the layer warms by the declared strength; below and above, the declared lapse rates
    assert profile.temperature(zi + d) - profile.temperature(zi) == pytest.approx(profile.inversion_strength,
                                                                                 abs=1e-9)
    for y in (0.5 * zi, zi + 0.5 * d, zi + d + 500.0):
        h = min(0.25 * zi, 0.25 * d, 100.0)
        slope = -(profile.temperature(y + h) - profile.temperature(y - h)) / (2 * h)
        assert slope == pytest.approx(float(profile.lapse(y)), rel=1e-6, abs=1e-9)
    # without an inversion it is the paper's line
    flat = EnvironmentProfile(profile.ground_temperature, profile.lapse_rate)
    y = np.linspace(0.0, 5000.0, 11)
    np.testing.assert_array_equal(flat.temperature(y), profile.ground_temperature - profile.lapse_rate * y)


CAPPED = {"atmosphere.inversion_height": 500.0, "atmosphere.inversion_depth": 150.0,
          "atmosphere.inversion_strength": 4.0, "atmosphere.lapse_rate_above": 0.005}
DRY_ABOVE = {**CAPPED, "atmosphere.initial_vapor_ratio": 0.8, "atmosphere.vapor_ratio_above": 0.25}


@settings(max_examples=100, deadline=None)
@given(profile=profiles, below=st.floats(0.0, 1.2), above=st.floats(0.0, 1.2))
def test_vapor_ratio_is_the_boundary_layers_below_and_the_free_tropospheres_above(profile, below, above):
    zi, d = profile.inversion_height, profile.inversion_depth
    y = np.array([0.0, 0.5 * zi, zi, zi + 0.5 * d, zi + d, zi + d + 1000.0])
    k = vapor_ratio(profile, below, above, y)
    np.testing.assert_allclose(k[:3], below, atol=1e-12)
    np.testing.assert_allclose(k[4:], above, atol=1e-12)
    assert k[3] == pytest.approx(0.5 * (below + above))          # linear across the layer
    np.testing.assert_array_equal(vapor_ratio(profile, below, -1.0, y), below)   # -1: the same above


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("jitter, kappa, energy", [(5.0, 0.0, 10.0), (0.0, 0.3, 200.0)])
def test_capped_atmosphere_at_rest_stays_at_rest_and_closes_its_heat_budget(backend, jitter, kappa, energy):
    # Were the solver's T0 linear (the inversion ignored), the particles above 500 m would start up to 4 K +
    # 150 m x 6.5 K/km = 5 K warm: about 1e6 J of available potential energy.
    # Jittered, no smoothing: the density shifts are booked on the profile (pbf.shift_keeps_anomaly), so the
    # anomaly stays at float32 rounding (as test_density_shifts_of_an_atmosphere_at_rest_create_no_energy
    # measures for the linear profile). On the lattice with smoothing: the smoothing's anomaly is the
    # profile's, so the resting air is its fixed point; what energy there is comes from the small shifts
    # next to the walls (measured, CPU: 55 J after 3 steps, 87 J with the linear profile). Jittered AND
    # smoothed air is no fixed point with either profile: the smoothing runs on the shifted positions before
    # the cloud dynamics books the shift's temperature change (1.4e4 J with the inversion, 1.6e4 J linear).
    # the stratified box (1000 m) with the inversion at 500-650 m, at rest in its environment
    run, anomaly = atmosphere_at_rest({"smoothing.kappa": kappa, **CAPPED}, jitter, backend)
    assert run[0]["potential_energy"] < 0.1
    assert run[1]["potential_energy"] < energy and run[2]["kinetic_energy"] < energy
    assert np.abs(anomaly).max() < (1e-3 if kappa == 0.0 else 2e-2)
    # the step's heat budget closes (float32 temperatures of ~297 K: 1e-6 K), with the shift booked on the profile
    terms = sum(run[1][t] for t in ("heat_source", "heat_latent", "heat_adiabatic", "heat_smoothing"))
    assert run[1]["mean_temperature"] - run[0]["mean_temperature"] == pytest.approx(terms, abs=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gravity_wave_in_an_inversion_layer_has_that_layers_buoyancy_frequency(backend):
    # N^2 = (g/T)(Gamma_d - Gamma(y)) with Gamma = -1 K/km in the layer: omega 1.81 times the linear profile's.
    from test_atmosphere_energy import gravity_wave
    energy, period, expected = gravity_wave(1, 1, periods=2.0, dt=2.5, steepness=0.1, backend=backend,
                                            overrides=INVERSION_EVERYWHERE)
    assert period == pytest.approx(expected, rel=0.03)
    assert energy.max() <= 1.05 * energy[0] and energy.min() >= 0.9 * energy[0]


def test_grid_keeps_a_capped_atmosphere_at_rest():
    pytest.importorskip("jax_cfd")
    from grid_baseline import GridSimulation
    scene = load_scene("stratified").replace(**{"wave.amplitude": 0.0, **CAPPED})
    sim = GridSimulation(scene, dtype="float64")
    sim.step(100)
    assert sim.stats()["max_speed"] < 1e-10
    f = sim.fields()
    t0 = scene.environment_temperature(f["y"])
    assert np.max(np.abs(f["temperature"] - t0[None, :, None])) < 1e-9 * 300


@pytest.mark.parametrize("backend", BACKENDS)
def test_initial_vapor_under_and_over_the_inversion_is_the_relaxations_fixed_point(backend):
    # The solver's v0(y) (the relaxation's target, eq. C2, thermodynamics.h) is the Python one the initial state
    # is built from (initial_state.environment_state): with a strong relaxation (tau = 50 s) the vapor of air
    # at rest stays where it started, to float32 rounding; had the solver a different v0 above the inversion,
    # 20 steps of 5 s would move it 87% of the way there.
    scene = load_scene("stratified").replace(**{"wave.amplitude": 0.0, "atmosphere.relaxation_time": 50.0,
                                                **DRY_ABOVE})
    sim = Simulation(scene, backend=backend)
    v_start = sim.state()["vapor"]
    y_start = sim.state()["position"][:, 1]
    a = scene.atmosphere
    expected = vapor_ratio(EnvironmentProfile.of(a), 0.8, 0.25, y_start) * scene.saturation(
        scene.environment_temperature(y_start))
    np.testing.assert_allclose(v_start, expected, rtol=1e-6)
    assert v_start[y_start > 700].max() < 0.4 * v_start[y_start < 450].min()      # the free troposphere is dry
    sim.step(20)
    end = sim.state()
    y = end["position"][:, 1].astype(np.float64)
    v0 = vapor_ratio(EnvironmentProfile.of(a), 0.8, 0.25, y) * scene.saturation(scene.environment_temperature(y))
    # within 0.1% of the vapor jump across the inversion (the particles the density constraint moves a few cm
    # lag their new height's v0 by up to 2.6e-6 kg/kg, measured on the CPU)
    jump = float(v_start[y_start < 450].min() - v_start[y_start > 700].max())
    np.testing.assert_allclose(end["vapor"], v0, rtol=0, atol=1e-3 * jump)


def test_grid_starts_from_the_same_vapor_profile_and_keeps_it_at_rest():
    pytest.importorskip("jax_cfd")
    from grid_baseline import GridSimulation
    scene = load_scene("stratified").replace(**{"wave.amplitude": 0.0, **DRY_ABOVE})
    sim = GridSimulation(scene, dtype="float64")
    sim.step(50)
    f = sim.fields()
    a = scene.atmosphere
    v0 = vapor_ratio(EnvironmentProfile.of(a), 0.8, 0.25, f["y"]) * scene.saturation(scene.environment_temperature(f["y"]))
    np.testing.assert_allclose(f["vapor"], np.broadcast_to(v0[None, :, None], f["vapor"].shape), rtol=1e-9)


def test_inversion_that_leaves_the_saturation_range_is_refused_by_name():
    cold = {"atmosphere.ground_temperature": 200.0, "atmosphere.lapse_rate_above": 0.05}
    load_scene("growing", **cold)   # without an inversion lapse_rate_above is unused: T0 = 179 K at the top
    with pytest.raises(SceneError, match=r"atmosphere\.lapse_rate_above = 0.05 K/m give T0 = 63.\d K at y = 3200"):
        load_scene("growing", **cold, **{"atmosphere.inversion_height": 300.0})
    with pytest.raises(SceneError, match="atmosphere.inversion_depth"):
        load_scene("stratified", **{"atmosphere.inversion_height": 300.0, "atmosphere.inversion_depth": 0.0})


def test_profile_of_the_shipped_scenes_is_the_papers_line():
    for name in ("growing", "stratified", "dry_cbl"):
        scene = load_scene(name)
        a = scene.atmosphere
        y = np.linspace(0.0, scene.domain.size[1], 7)
        assert not EnvironmentProfile.of(a).has_inversion
        np.testing.assert_array_equal(scene.environment_temperature(y), a.ground_temperature - a.lapse_rate * y)
        assert math.isfinite(float(scene.environment_temperature(0.0)))
