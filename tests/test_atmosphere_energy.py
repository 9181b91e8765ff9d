"""An incompressible, energy-honest particle atmosphere: the velocity projection, the conservative
smoothing and the per-step energy and heat budget (docs/physics.md).

Each test is a physical statement: an inviscid flow never gains kinetic energy, a viscous vortex decays at
the rate its viscosity implies, a gravity wave keeps its energy and frequency, a heated closed box keeps its
mass where it is, and the heat budget closes.
"""
import math

import numpy as np
import pytest

from pbf_cuda import Simulation, load_scene, scene_from_dict
from pbf_cuda.environment import EnvironmentProfile
from pbf_cuda.noise import simplex2
from solver_helpers import BACKENDS, atmosphere_at_rest


def cellular_scene(dt, **overrides):
    """The stratified box with buoyancy off and its wave mode as a steady cellular flow (inviscid)."""
    return load_scene("stratified").replace(**{
        "atmosphere.buoyancy": 0.0, "wave.modes_x": 2, "wave.modes_y": 1, "wave.amplitude": 0.5,
        "pbf.xsph": 0.0, "pbf.vorticity": 0.0, "time.dt": dt, **overrides})


def kinetic_energy_series(sim, steps):
    out = []
    for _ in range(steps):
        sim.step(1)
        out.append(sim.stats()["kinetic_energy"])
    return np.array(out)


def initial_kinetic_energy(sim):
    st = sim.state()
    return 0.5 * float(np.sum(st["mass"].astype(np.float64) * np.sum(st["velocity"].astype(np.float64) ** 2, 1)))


@pytest.mark.parametrize("dt, steps, backend", [(5.0, 500, "cpu"), (2.5, 250, "cpu"),
                                                pytest.param(5.0, 500, "cuda", marks=pytest.mark.gpu)])
def test_inviscid_cellular_flow_never_gains_kinetic_energy(dt, steps, backend):
    sim = Simulation(cellular_scene(dt), backend=backend, seed=0)
    ke0 = initial_kinetic_energy(sim)
    ke = kinetic_energy_series(sim, steps)
    assert ke.max() <= 1.01 * ke0
    assert ke[-1] > 0.3 * ke0                     # and the flow is still there (not damped away)
    assert sim.stats()["density_error_mean"] < 0.01


def test_lattice_with_random_velocities_never_gains_kinetic_energy():
    scene = cellular_scene(5.0, **{"wave.amplitude": 0.0, "particles.max_speed": 0.05})
    sim = Simulation(scene, backend="cpu", seed=4)
    ke0 = initial_kinetic_energy(sim)
    ke = kinetic_energy_series(sim, 100)
    assert np.all(ke <= ke0 * (1 + 1e-6))


def periodic_box(viscosity, n=32, depth=8, dt=0.01):
    """A fully periodic 1 m box of water-like particles (no walls, no thermodynamics), d = 1/n."""
    d = 1.0 / n
    return scene_from_dict({
        "scene": {"name": "periodic_box"},
        "domain": {"size": [1.0, 1.0, depth * d], "boundary": ["periodic", "periodic", "periodic"]},
        "particles": {"spacing": d, "rest_density": 1000.0},
        "time": {"dt": dt},
        "pbf": {"projection": "velocity", "unilateral": False, "relaxation": 1.0, "scorr_k": 0.1,
                "divergence_iterations": 4, "xsph": 0.0, "vorticity": 0.0, "viscosity": viscosity},
    }, source="periodic_box")


def with_velocity(scene, field):
    base = Simulation(scene, backend="cpu")
    st = base.state()
    st["velocity"] = field(st["position"].astype(np.float64)).astype(np.float32)
    return Simulation.from_arrays(scene, st, backend="cpu")


def shear_wave(p, speed=0.1, k=2 * math.pi):
    u = np.zeros_like(p)
    u[:, 0] = speed * np.sin(k * p[:, 1])
    return u


def taylor_green(p, speed=0.1, k=2 * math.pi):
    u = np.zeros_like(p)
    u[:, 0] = speed * np.sin(k * p[:, 0]) * np.cos(k * p[:, 1])
    u[:, 1] = -speed * np.cos(k * p[:, 0]) * np.sin(k * p[:, 1])
    return u


@pytest.mark.parametrize("speed", [0.01, 0.1])
def test_shear_wave_decays_at_the_rate_its_viscosity_implies(speed):
    # u = U sin(k y) x: du/dt = nu lap u = -nu k^2 u, so KE ~ exp(-2 nu k^2 t), at any amplitude. The rate is
    # fitted after the first 20 steps (0.2 s), in which the projection adjusts the sampled field.
    nu, k, steps = 2e-3, 2 * math.pi, 150                # nu dt / d^2 = 0.02 (explicit-stable)
    sim = with_velocity(periodic_box(nu), lambda p: shear_wave(p, speed, k))
    ke0 = initial_kinetic_energy(sim)
    ke = kinetic_energy_series(sim, steps)
    t = sim.scene.time.dt * np.arange(1, steps + 1)
    rate = -np.polyfit(t[20:], np.log(ke[20:] / ke0), 1)[0]
    assert rate == pytest.approx(2 * nu * k * k, rel=0.10)
    st = sim.state()
    momentum = (st["mass"][:, None].astype(np.float64) * st["velocity"]).sum(axis=0)
    scale = float(st["mass"].astype(np.float64).sum()) * speed
    assert np.abs(momentum).max() < 1e-5 * scale           # the pairwise viscosity conserves momentum


def test_inviscid_shear_wave_and_taylor_green_vortex_never_gain_energy():
    for field in (shear_wave, taylor_green):
        sim = with_velocity(periodic_box(0.0), field)
        ke0 = initial_kinetic_energy(sim)
        ke = kinetic_energy_series(sim, 80)
        assert ke.max() <= ke0 * (1 + 1e-6)


def gravity_wave(modes_x, modes_y, periods, dt=5.0, steepness=None, backend="cpu", overrides=None):
    """The `stratified` scene's wave of one mode for `periods` periods: (kinetic + available potential energy
    per step, the measured period, the period of linear theory omega = N kx / |k|). With `steepness`, the peak
    vertical velocity is set so that the peak displacement zeta = w / omega has |k| zeta = steepness."""
    scene = load_scene("stratified").replace(**{"wave.modes_x": modes_x, "wave.modes_y": modes_y,
                                                "time.dt": dt, **(overrides or {})})
    a = scene.atmosphere
    Lx, Ly = scene.domain.size[:2]
    kx, ky = 2 * math.pi * modes_x / Lx, math.pi * modes_y / Ly
    n2 = a.buoyancy / a.ground_temperature * (a.dry_lapse_rate - float(EnvironmentProfile.of(a).lapse(Ly / 2)))
    omega = math.sqrt(n2) * kx / math.hypot(kx, ky)
    if steepness is not None:
        scene = scene.replace(**{"wave.amplitude": steepness * omega / math.hypot(kx, ky)})
    steps = int(round(periods * 2 * math.pi / omega / dt))
    sim = Simulation(scene, backend=backend)
    energy, amp, times = [], [], []
    for _ in range(steps):
        sim.step(1)
        s = sim.stats()
        energy.append(s["kinetic_energy"] + s["potential_energy"])
        st = sim.state()
        p = st["position"].astype(np.float64)
        mode = np.cos(kx * p[:, 0]) * np.sin(ky * p[:, 1])
        amp.append(-(st["velocity"][:, 1] * mode).sum() / (mode * mode).sum())
        times.append(sim.time)
    amp, times = np.array(amp), np.array(times)
    crossings = [times[i] - amp[i] * (times[i + 1] - times[i]) / (amp[i + 1] - amp[i])
                 for i in range(len(amp) - 1) if amp[i] * amp[i + 1] < 0]
    period = 2 * np.mean(np.diff(crossings))
    return np.array(energy), period, 2 * math.pi / omega


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("modes", [(2, 1), (1, 2)])
def test_linear_gravity_wave_keeps_its_energy_and_frequency_over_two_periods(modes, backend):
    # A linear wave (steepness |k| zeta = 0.1) at the scene's dt = 5 s (N dt = 0.052): kinetic + available
    # potential energy within 5% of its start over two periods and the period of linear theory within 3%.
    # Measured (50 m, CPU), lowest and highest energy and period / theory for modes (2, 1) and (1, 2): 0.971,
    # 1.024, 0.984 and 0.964, 1.000, 0.997 (H100 at dt 5: lowest 0.972 and 0.963). At dt = 2.5 s the loss halves
    # (lowest 0.989 and 0.988, CPU): first order in dt, which the steep test below holds for mode (1, 1).
    energy, period, expected = gravity_wave(*modes, periods=2.0, dt=5.0, steepness=0.1, backend=backend)
    assert period == pytest.approx(expected, rel=0.03)
    assert 0.95 * energy[0] <= energy.min() and energy.max() <= 1.05 * energy[0]


def test_steep_gravity_wave_loses_energy_at_first_order_in_dt_and_never_gains():
    # The scene's own wave (0.5 m/s, steepness 0.30) loses energy to the first-order time integration of the
    # projection, a loss that vanishes with dt: lowest energy over 1.25 periods 0.919 at dt = 5 s and 0.958 at
    # 2.5 s, period / theory 1.000 and 0.996 (over two periods 0.871, 0.943 and 0.982 at 1.25 s; measured, CPU).
    # Halving dt must at least nearly halve the loss (0.52 of it here), and energy never grows.
    loss = []
    for dt in (5.0, 2.5):
        energy, period, expected = gravity_wave(1, 1, periods=1.25, dt=dt)
        assert energy.max() <= 1.01 * energy[0]
        assert period == pytest.approx(expected, rel=0.03)
        loss.append(1.0 - energy.min() / energy[0])
    assert 0.0 < loss[1] < 0.6 * loss[0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradient_correction_keeps_momentum_and_never_adds_kinetic_energy(backend):
    # Each row of the corrected Jacobian is sum_j a_ij (v_i - v_j), so J^T mu sums to zero over a periodic box
    # (no walls): the projection moves no momentum; and it stays M-orthogonal, so kinetic energy cannot grow.
    scene = periodic_box(0.0).replace(**{"pbf.gradient_correction": True, "pbf.scorr_k": 0.0})
    rng = np.random.default_rng(3)
    base = Simulation(scene, backend="cpu")
    st = base.state()
    st["velocity"] = rng.normal(0.0, 0.01, st["velocity"].shape).astype(np.float32)
    sim = Simulation.from_arrays(scene, st, backend=backend)
    m = st["mass"].astype(np.float64)[:, None]
    p0 = (m * st["velocity"]).sum(0)
    scale = float((m * np.abs(st["velocity"])).sum())
    ke = [float((0.5 * m * st["velocity"].astype(np.float64) ** 2).sum())]
    for _ in range(20):
        sim.step(1)
        v = sim.state()["velocity"].astype(np.float64)
        ke.append(float((0.5 * m * v ** 2).sum()))
        assert np.abs((m * v).sum(0) - p0).max() < 1e-6 * scale
    assert max(ke[1:]) <= ke[0] and ke[-1] < 0.5 * ke[0]     # the random field is mostly compressive


def test_gradient_correction_without_the_velocity_projection_is_refused_by_name():
    from pbf_cuda.scene import SceneError
    with pytest.raises(SceneError, match="pbf.gradient_correction.*pbf.projection = 'velocity'"):
        load_scene("dam_break", **{"pbf.gradient_correction": True})


def settling_atmosphere(keeps_anomaly, backend="cpu"):
    """The stratified box at rest on a jittered particle set (solver_helpers.atmosphere_at_rest), with or
    without pbf.shift_keeps_anomaly: (statistics at the start, after 1 step, after 10 steps)."""
    return atmosphere_at_rest({"pbf.shift_keeps_anomaly": keeps_anomaly}, backend=backend)[0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_density_shifts_of_an_atmosphere_at_rest_create_no_energy(backend):
    # The density constraint moves particles without a velocity: a shift, not a motion. Booked on the dry
    # adiabat (eq. 7) a shift of dy gives the particle an anomaly -(Gamma_d - Gamma_env) dy, which the buoyancy
    # turns into motion: measured (CPU) 6e4 J of potential energy after one step and 1.8e4 J of kinetic energy
    # after ten, in air at rest. With pbf.shift_keeps_anomaly the shift moves the temperature along the
    # environment (dT = -Gamma_env dy), so the anomaly stays 0 up to the float32 rounding of T (about 1 J here).
    plain = settling_atmosphere(False, backend)
    kept = settling_atmosphere(True, backend)
    # At the start T = T0(y) up to float32 rounding (0 J on the CPU, 0.009 J on an H100, whose T0(y) is fused)
    assert plain[0]["potential_energy"] < 0.1 and kept[0]["potential_energy"] < 0.1
    assert plain[1]["potential_energy"] > 1e4 and plain[2]["kinetic_energy"] > 1e3
    assert kept[1]["potential_energy"] < 10.0 and kept[2]["kinetic_energy"] < 10.0
    assert kept[2]["potential_energy"] < 1e-3 * plain[2]["potential_energy"]
    # The shift's share of the adiabatic term is in the step's heat budget: the mean temperature moves by the
    # sum of the terms (float32 temperatures of ~297 K: 1e-6 K).
    for run in (plain, kept):
        terms = sum(run[1][k] for k in ("heat_source", "heat_latent", "heat_adiabatic", "heat_smoothing"))
        assert run[1]["mean_temperature"] - run[0]["mean_temperature"] == pytest.approx(terms, abs=1e-6)
    assert kept[1]["heat_adiabatic"] != plain[1]["heat_adiabatic"]


def heated_box(steps=100, backend="cpu"):
    """A dry, closed, completely filled 800 x 3200 x 800 m atmosphere heated from the ground (no smoothing)."""
    scene = load_scene("growing").replace(**{
        "domain.size": [800.0, 3200.0, 800.0], "particles.spacing": 50.0,
        "atmosphere.initial_vapor_ratio": 0.1, "smoothing.kappa": 0.0})
    return Simulation(scene, backend=backend, seed=0), steps


def layer_mass(y, edges):
    """Particles per layer (edges: equal layers) with linear weights between the layers' centres."""
    width = edges[1] - edges[0]
    n = len(edges) - 1
    s = (y - edges[0]) / width - 0.5
    k = np.floor(s).astype(int)
    f = s - k
    out = np.zeros(n)
    np.add.at(out, np.clip(k, 0, n - 1), 1.0 - f)
    np.add.at(out, np.clip(k + 1, 0, n - 1), f)
    return out


@pytest.mark.parametrize("backend", BACKENDS)
def test_heated_closed_box_keeps_its_mass_in_place_and_closes_its_heat_budget(backend):
    sim, steps = heated_box(backend=backend)
    p0 = sim.state()["position"].astype(np.float64)
    y0 = p0[:, 1]
    edges = np.arange(0.0, 3201.0, 200.0)
    first = None
    totals = {"heat_source": 0.0, "heat_latent": 0.0, "heat_adiabatic": 0.0, "heat_smoothing": 0.0}
    for _ in range(steps):
        sim.step(1)
        s = sim.stats()
        first = first if first is not None else s
        for key in totals:
            totals[key] += s[key]
    s = sim.stats()
    y = sim.state()["position"][:, 1].astype(np.float64)
    # Incompressible in both directions, and no drift of the whole column (pbf.remove_column_drift): the
    # mass centre stays within 1 m and every 200 m layer keeps its mass within 2% over 200 s (measured:
    # -0.3 m and 0.8%; without the drift removal +6.4 m and 3%, with the unilateral position projection
    # +14 m and 8%). A layer's mass is counted with linear (cloud-in-cell) weights between the layers'
    # centres: a sharp count jumps by a quarter of a layer whenever one of its four lattice planes edges
    # across the boundary (the sharp counts move by up to 2.7% here).
    assert abs(float(y.mean()) - float(y0.mean())) < 1.0
    assert np.abs(layer_mass(y, edges) / layer_mass(y0, edges) - 1).max() < 0.02
    assert s["density_deficit_mean"] < 0.01 and s["density_excess_mean"] < 0.01
    # Heat budget: the mean warming is the sum of the budget's terms (each computed on its own) ...
    start_mean = first["mean_temperature"] - sum(first[k] for k in totals)
    warming = s["mean_temperature"] - start_mean
    assert warming == pytest.approx(sum(totals.values()), rel=1e-3)
    # ... the source is S_e x the noise pattern summed over the heated layer (eq. 5), per unit mass, x time
    # (the layer's particles move sideways, so the pattern they see drifts a little) ...
    a = sim.scene.atmosphere
    heated = y0 < a.heating_depth
    f, off = a.noise_frequency, a.noise_offset
    pattern = np.maximum(0.0, 1.0 + a.noise_amplitude * simplex2(p0[heated, 0] * f + off[0], p0[heated, 2] * f + off[1]))
    expected = a.heating_rate * pattern.sum() / len(y0) * steps * sim.scene.time.dt
    assert totals["heat_source"] == pytest.approx(expected, rel=0.10)
    # ... smoothing adds nothing, and dry air releases no latent heat.
    assert abs(totals["heat_smoothing"]) < 1e-6 and abs(totals["heat_latent"]) < 1e-6


@pytest.mark.parametrize("spacing, seed", [(100.0, 0), (100.0, 1), (80.0, 2)])
def test_heated_ground_layer_stays_on_the_floor(spacing, seed):
    """Convection in a small `growing` box for 1000 s: the column does not lift off the floor, so the
    ground keeps heating a full layer. The heated mass (eq. 5's layer weights, csrc/thermodynamics.h) stays
    above 0.95 of a full layer every 200 s, the heat per 200 s does not fall below 0.97 of the first 200 s,
    and the mass centre moves less than 0.5 m (measured at 100 m, seed 0: heated mass 0.97-1.00, heat
    0.509 -> 0.517 K, +0.07 m; with pbf.remove_shift_drift off, the default: 0.88, 0.459 K and +8.9 m)."""
    from cloudpbf.statistics import heated_mass_fraction
    scene = load_scene("growing").replace(**{"domain.size": [1200.0, 1600.0, 1200.0],
                                             "particles.spacing": spacing, "time.dt": 8.0,
                                             "time.reference_dt": 8.0,   # kappa and xsph per step of 8 s
                                             "pbf.remove_shift_drift": True})
    sim = Simulation(scene, backend="cpu", seed=seed)
    y0 = float(sim.state()["position"][:, 1].astype(np.float64).mean())
    heats, previous = [], 0.0
    for _ in range(5):
        sim.step(25)
        st, total = sim.state(), sim.stats()["heat_source_total"]
        assert heated_mass_fraction(st, scene) > 0.95, sim.time
        heats.append(total - previous)
        previous = total
    assert heats[-1] > 0.97 * heats[0], heats
    assert abs(float(st["position"][:, 1].astype(np.float64).mean()) - y0) < 0.5


@pytest.mark.parametrize("backend", BACKENDS)
def test_smoothing_and_water_budget_of_a_cloudy_run(backend):
    scene = load_scene("growing").replace(**{"domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0,
                                             "atmosphere.initial_vapor_ratio": 0.95, "smoothing.kappa": 0.1,
                                             "smoothing.fields": ["temperature", "vapor", "cloud"]})
    sim = Simulation(scene, backend=backend, seed=1)
    water0 = None
    latent = 0.0
    for _ in range(150):
        sim.step(1)
        s = sim.stats()
        water0 = water0 if water0 is not None else s["total_water"]
        latent += s["heat_latent"]
        assert abs(s["heat_smoothing"]) < 1e-6 * s["mean_temperature"]
    assert abs(sim.stats()["total_water"] - water0) < 1e-6 * water0
    st = sim.state()
    m = st["mass"].astype(np.float64)
    assert latent == pytest.approx(scene.atmosphere.latent_heat * np.sum(m * st["cloud"]) / m.sum(), rel=1e-3,
                                   abs=1e-9)
