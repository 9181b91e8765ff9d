"""The large-scale forcing of BOMEX (Siebesma et al. 2003; scene [forcing], pbf_cuda/csrc/thermodynamics.h
L1-L3) in the particle solver and the grid baseline: subsidence of the environment profiles
(dtheta/dt = -w_s dtheta0/dy, dv/dt = -w_s dv0/dy), radiative cooling dtheta/dt = R(y), a moisture tendency
dv/dt = M(y), their budget terms, and that a scene without them is unchanged."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pbf_cuda import Simulation
from pbf_cuda.scene import SceneError, load_scene
from solver_helpers import BACKENDS

try:   # the grid baseline (the grid extra)
    import jax
    import jax.numpy as jnp
    from grid_baseline import model
    jax.config.update("jax_enable_x64", True)
    GRID_MISSING = None
except ModuleNotFoundError as missing:
    GRID_MISSING = f"the grid baseline needs {missing.name} (the grid extra)"
needs_grid = pytest.mark.skipif(GRID_MISSING is not None, reason=GRID_MISSING or "")

FAST = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
LAPSE, GAMMA_D = 0.0065, 0.0098          # a stable linear profile: dtheta0/dy = Gamma_d - Gamma = 3.3 K/km
ZERO4 = [0.0, 0.0, 0.0, 0.0]


def box_at_rest(**overrides):
    """A small closed box of air at rest in a stable linear profile, no buoyancy, heating, condensation or
    smoothing: only the large-scale forcing changes T and v."""
    base = {"domain.size": [600.0, 1600.0, 600.0], "particles.spacing": 100.0, "particles.max_speed": 0.0,
            "atmosphere.lapse_rate": LAPSE, "atmosphere.dry_lapse_rate": GAMMA_D, "atmosphere.buoyancy": 0.0,
            "atmosphere.cloud_gravity": 0.0, "atmosphere.heating_rate": 0.0, "atmosphere.phase_rate": 0.0,
            "atmosphere.initial_vapor_ratio": 0.5, "pbf.vorticity": 0.0, "smoothing.kappa": 0.0,
            "time.dt": 2.0}
    base.update(overrides)
    return load_scene("growing").replace(**base)


def profile(heights, values, y):
    return np.interp(y, heights, values)   # piecewise linear, constant outside (knots non-decreasing)


def ulp(x):
    return np.spacing(np.abs(np.asarray(x, np.float32))).astype(np.float64)


def by_id(state):
    order = np.argsort(state["id"])
    return {k: v[order] for k, v in state.items()}


def run(scene, steps, backend="cpu"):
    """(state at the start, its stats, state after `steps`, its stats), the states ordered by particle id."""
    sim = Simulation(scene, backend=backend, seed=0)
    start, s0 = by_id(sim.state()), sim.stats()
    sim.step(steps)
    return start, s0, by_id(sim.state()), sim.stats()


def forced_change(scene, steps, field, backend="cpu"):
    """What the forcing changed of `field` per particle: the forced run minus the same run without [forcing]
    (without buoyancy the particles move alike in both, the density solve settling the lattice at the walls by
    a few m, so the difference is the forcing alone), the heights (m, mean of start and end), and both runs."""
    plain = scene.replace(**{f"forcing.{k}_values": ZERO4 for k in ("subsidence", "radiative", "moisture")})
    forced, control = run(scene, steps, backend), run(plain, steps, backend)
    assert np.array_equal(forced[2]["position"], control[2]["position"])
    y = 0.5 * (forced[0]["position"][:, 1].astype(np.float64) + forced[2]["position"][:, 1])
    change = forced[2][field].astype(np.float64) - control[2][field]
    return change, y, forced


# ---- the particle solver ------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
def test_particle_subsidence_warms_air_at_rest_at_minus_ws_dtheta_dz(backend):
    heights, values, steps, dt = [0.0, 900.0, 1300.0, 1600.0], [0.0, -0.05, 0.0, 0.0], 20, 2.0
    scene = box_at_rest(**{"forcing.subsidence_heights": heights, "forcing.subsidence_values": values})
    dT, y, (start, s0, end, s) = forced_change(scene, steps, "temperature", backend)
    expected = -profile(heights, values, y) * (GAMMA_D - LAPSE) * steps * dt     # K, > 0: subsiding air warms
    # the forcing's add rounds by less than one ulp of T (3e-5 K at 300 K, stochastic rounding), the adiabatic
    # term's by half an ulp in either run
    assert np.all(np.abs(dT - expected) <= 1.5 * steps * ulp(end["temperature"]) + 1e-2 * np.abs(expected))
    assert expected.max() > 6e-3 and np.abs(dT[y > 1305.0]).max() == 0.0
    # the vapor dries at -w_s dv0/dy (v0 falls with height): the grid's float64 gradient of the same profile
    if GRID_MISSING is None:
        dv, _, _ = forced_change(scene, steps, "vapor", backend)
        p = model.params_from_scene(scene, (6, 16, 6))
        expected_v = -profile(heights, values, y) * model.vapor_gradient(p, y) * steps * dt
        assert np.allclose(dv, expected_v, rtol=1e-2, atol=steps * ulp(start["vapor"]).max())
        assert expected_v.min() < 0.0
    # booked: the subsidence terms are the change of the mean temperature and of the total water
    assert s["heat_subsidence_total"] == pytest.approx(s["mean_temperature"] - s0["mean_temperature"]
                                                       - s["heat_adiabatic_total"] - s["heat_smoothing_total"],
                                                       abs=2e-5)   # the adiabatic term's float adds round
    assert s["water_subsidence_total"] == pytest.approx(s["total_water"] - s0["total_water"], rel=1e-6)
    assert s["heat_radiation_total"] == 0.0 and s["water_tendency_total"] == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_particle_radiative_cooling_and_moisture_tendency_follow_their_profiles(backend):
    rh, rv = [0.0, 500.0, 1000.0, 1600.0], [-1e-3, -1e-3, 0.0, 0.0]      # K/s
    mh, mv = [0.0, 300.0, 500.0, 1600.0], [-1e-7, -1e-7, 0.0, 0.0]       # 1/s
    steps, dt = 20, 2.0
    scene = box_at_rest(**{"forcing.radiative_heights": rh, "forcing.radiative_values": rv,
                           "forcing.moisture_heights": mh, "forcing.moisture_values": mv})
    dT, y, (start, s0, end, s) = forced_change(scene, steps, "temperature", backend)
    expected = profile(rh, rv, y) * steps * dt
    assert np.all(np.abs(dT - expected) <= 1.5 * steps * ulp(start["temperature"]) + 1e-2 * np.abs(expected))
    dv, _, _ = forced_change(scene, steps, "vapor", backend)
    assert np.allclose(dv, profile(mh, mv, y) * steps * dt, rtol=1e-2, atol=steps * ulp(start["vapor"]).max())
    assert s["heat_radiation_total"] == pytest.approx(s["mean_temperature"] - s0["mean_temperature"]
                                                      - s["heat_adiabatic_total"] - s["heat_smoothing_total"], abs=2e-5)
    assert s["heat_radiation_total"] < 0.0
    assert s["water_tendency_total"] == pytest.approx(s["total_water"] - s0["total_water"], rel=1e-6)
    assert s["heat_subsidence_total"] == 0.0 and s["water_subsidence_total"] == 0.0


@FAST
@given(ws=st.floats(-0.2, 0.2).filter(lambda w: abs(w) > 1e-3), z1=st.floats(100.0, 1400.0),
       width=st.floats(0.0, 800.0), lapse=st.floats(-0.002, 0.009))
def test_particle_subsidence_closed_form(ws, z1, width, lapse):
    """w_s(y) = ws from the ground to z1, falling to 0 at z1 + width (0: a step), for any stable or unstable
    profile: every particle's T changes by -w_s(y) (Gamma_d - Gamma) t."""
    heights, values, steps, dt = [0.0, z1, z1 + width, max(z1 + width, 1600.0)], [ws, ws, 0.0, 0.0], 5, 2.0
    scene = box_at_rest(**{"atmosphere.lapse_rate": lapse, "forcing.subsidence_heights": heights,
                           "forcing.subsidence_values": values})
    dT, y, (start, s0, end, s) = forced_change(scene, steps, "temperature")
    w = profile(heights, values, y)
    expected = -w * (GAMMA_D - lapse) * steps * dt
    # near a step (width 0) the particles' few metres of settling cross it: compare away from it
    far = np.abs(y - z1) > 5.0
    bound = 1.5 * steps * ulp(end["temperature"]) + 1e-2 * np.abs(expected) + abs(ws) * (GAMMA_D - lapse) * steps * dt * (
        5.0 / width if width > 5.0 else 0.0)
    assert np.all((np.abs(dT - expected) <= bound)[far])
    assert s["heat_subsidence_total"] == pytest.approx(s["mean_temperature"] - s0["mean_temperature"]
                                                       - s["heat_adiabatic_total"] - s["heat_smoothing_total"],
                                                       abs=1e-5)


def test_no_forcing_leaves_the_run_unchanged():
    """A [forcing] section whose profiles are all 0 is no forcing: the state is bitwise that of the scene without
    it, and stats() has no forcing keys (scripts/fingerprint.py hashes it)."""
    plain = load_scene("shallow_cumulus").replace(**{"domain.size": [1200.0, 3200.0, 1200.0],
                                                     "particles.spacing": 200.0})
    zero = plain.replace(**{"forcing.subsidence_values": ZERO4})
    assert zero.forcing is not None and not zero.large_scale_forcing
    assert plain.config_hash() == load_scene("shallow_cumulus").replace(
        **{"domain.size": [1200.0, 3200.0, 1200.0], "particles.spacing": 200.0}).config_hash()
    runs = [run(scene, 8)[2:] for scene in (plain, zero)]
    for key in runs[0][0]:
        assert np.array_equal(runs[0][0][key], runs[1][0][key]), key
    assert runs[0][1] == runs[1][1]
    assert "heat_subsidence_total" not in runs[0][1]


def test_forcing_needs_an_atmosphere_and_ordered_heights():
    with pytest.raises(SceneError, match=r"\[forcing\].*\[atmosphere\]"):
        load_scene("dam_break").replace(**{"forcing.subsidence_values": [0.0, -0.01, 0.0, 0.0]})
    with pytest.raises(SceneError, match="forcing.radiative_heights"):
        load_scene("growing").replace(**{"forcing.radiative_heights": [0.0, 500.0, 400.0, 1000.0]})
    with pytest.raises(SceneError, match="forcing.subsidence_values"):
        load_scene("growing").replace(**{"forcing.subsidence_values": [0.0, -2.0, 0.0, 0.0]})


def test_bomex_scene_states_the_papers_profiles():
    scene = load_scene("shallow_cumulus_bomex")
    f = scene.forcing
    assert scene.large_scale_forcing
    assert np.interp(1500.0, f.subsidence_heights, f.subsidence_values) == pytest.approx(-0.0065)
    assert np.interp(1800.0, f.subsidence_heights, f.subsidence_values) == pytest.approx(-0.00325)
    assert np.interp(750.0, f.subsidence_heights, f.subsidence_values) == pytest.approx(-0.00325)
    assert np.interp(1000.0, f.radiative_heights, f.radiative_values) * 86400 == pytest.approx(-2.0, rel=1e-6)
    assert np.interp(2000.0, f.radiative_heights, f.radiative_values) * 86400 == pytest.approx(-1.0, rel=1e-6)
    assert np.interp(400.0, f.moisture_heights, f.moisture_values) == pytest.approx(-0.6e-8)
    # the rest is shallow_cumulus
    base = load_scene("shallow_cumulus")
    assert scene.replace(**{"forcing." + k: v for k, v in
                            {"subsidence_values": ZERO4, "radiative_values": ZERO4, "moisture_values": ZERO4}.items()}
                         ).atmosphere == base.atmosphere


# ---- the grid baseline ------------------------------------------------------------------------------
@needs_grid
@FAST
@given(ws=st.floats(-0.05, 0.05), rate=st.floats(-1e-3, 1e-3), z1=st.floats(200.0, 1200.0))
def test_grid_forcing_closed_form(ws, rate, z1):
    """Air at rest in the grid: theta' changes by (-w_s(y) (Gamma_d - Gamma) + R(y)) t per level, v by
    (-w_s dv0/dy + M(y)) t, and the running sums book exactly that."""
    heights, values = [0.0, z1, z1 + 200.0, 1600.0], [ws, ws, 0.0, 0.0]
    rvalues, mvalues = [rate, rate, 0.0, 0.0], [-1e-7, -1e-7, 0.0, 0.0]
    scene = box_at_rest(**{"forcing.subsidence_heights": heights, "forcing.subsidence_values": values,
                           "forcing.radiative_heights": heights, "forcing.radiative_values": rvalues,
                           "forcing.moisture_heights": heights, "forcing.moisture_values": mvalues})
    p = model.params_from_scene(scene, (6, 16, 6))
    aux = model.make_aux(p, jnp.float64)
    state = model.initial_state(p, jnp.float64)
    steps = 3
    for _ in range(steps):
        state = model.physics(state, aux, p)
    y = model.cell_centers(p)[1]
    t = steps * p.dt
    w = profile(heights, values, y)
    theta = -w * (GAMMA_D - LAPSE) * t + profile(heights, rvalues, y) * t
    vapor = model.initial_vapor(p, y) + (-w * model.vapor_gradient(p, y) + profile(heights, mvalues, y)) * t
    assert np.allclose(np.asarray(state["theta"]), theta[None, :, None], rtol=1e-9, atol=1e-12)
    assert np.allclose(np.asarray(state["vapor"]), vapor[None, :, None], rtol=1e-9, atol=1e-15)
    vol, n = p.cell_volume, 36
    assert float(state["heat_subsidence_total"]) == pytest.approx(np.sum(-w * (GAMMA_D - LAPSE) * t) * 36 * vol,
                                                                  rel=1e-9, abs=1e-9)
    assert float(state["heat_radiation_total"]) == pytest.approx(np.sum(profile(heights, rvalues, y)) * t * n * vol,
                                                                 rel=1e-9, abs=1e-9)
    assert float(state["water_subsidence_total"] + state["water_tendency_total"]) == pytest.approx(
        float(np.sum(np.asarray(state["vapor"]) - model.initial_vapor(p, y)[None, :, None])) * vol, rel=1e-9,
        abs=1e-12)


@needs_grid
def test_vapor_gradient_is_the_derivative_of_v0():
    """model.vapor_gradient (and the particle solver's twin, thermodynamics.h) against a central difference of
    v0(y), across a capping inversion with a drier free troposphere."""
    scene = load_scene("shallow_cumulus")
    p = model.params_from_scene(scene, (4, 32, 4))
    y = np.array([50.0, 800.0, 1599.0, 1650.0, 1750.0, 1810.0, 2500.0])
    h = 1e-3
    fd = (model.initial_vapor(p, y + h) - model.initial_vapor(p, y - h)) / (2 * h)
    assert np.allclose(model.vapor_gradient(p, y), fd, rtol=1e-5)
    assert model.vapor_gradient(p, np.array([1700.0]))[0] < 10 * model.vapor_gradient(p, np.array([800.0]))[0]


def test_checkpoint_carries_the_forcing_totals(tmp_path):
    scene = box_at_rest(**{"forcing.subsidence_values": [-0.01, -0.01, 0.0, 0.0],
                           "forcing.radiative_values": [-1e-4, 0.0, 0.0, 0.0],
                           "forcing.moisture_values": [-1e-8, 0.0, 0.0, 0.0]})
    sim = Simulation(scene, backend="cpu", seed=0)
    sim.step(3)
    path = sim.save(tmp_path / "ck.npz")
    sim.step(3)
    restored = Simulation.load(path, backend="cpu")
    restored.step(3)
    a, b = sim.stats(), restored.stats()
    for key in ("heat_subsidence_total", "heat_radiation_total", "water_subsidence_total", "water_tendency_total"):
        assert a[key] != 0.0 and a[key] == b[key], key


def test_particle_forcing_of_about_one_ulp_per_step_is_unbiased():
    """BOMEX's 2 K/day at dt = 2 s is 1.5 ulp of T per step: rounded to nearest every particle would cool at
    2 ulp per step (+32%); the stochastic rounding keeps the mean change at the stated rate."""
    rate, steps, dt = -2.0 / 86400.0, 40, 2.0
    scene = box_at_rest(**{"forcing.radiative_heights": [0.0, 1.0, 2.0, 1600.0],
                           "forcing.radiative_values": [rate] * 4})
    dT, y, (start, s0, end, s) = forced_change(scene, steps, "temperature")
    assert 1.4 < abs(rate) * dt / ulp(start["temperature"]).max() < 1.6
    assert dT.mean() == pytest.approx(rate * steps * dt, rel=0.03)
    assert s["heat_radiation_total"] == pytest.approx(rate * steps * dt, rel=0.03)
