"""Paper example 2, clouds that disappear and reappear: the large-scale forcing of docs/cycling.md
(C1 time-of-day heating, C2 relaxation, C3 autoconversion, C4 water budget) in the particle solver and
the grid baseline, and the cycle counting of cloudpbf/studies/cycling.py."""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cloudpbf.statistics import grid_for_scene, particle_diagnostics
from cloudpbf.studies.cycling import CPU_OVERRIDES, count_cycles, cycle_budgets
from pbf_cuda import Simulation
from pbf_cuda.scene import SceneError, load_scene
from solver_helpers import BACKENDS

try:   # the grid baseline (the grid extra); a machine with the particle solver alone runs the particle tests
    import jax
    from grid_baseline import GridSimulation
    from grid_baseline.model import diurnal_integral, initial_state, make_aux, params_from_scene, physics
    jax.config.update("jax_enable_x64", True)   # the grid checks run in float64 (as GridSimulation on a CPU)
    GRID_MISSING = None
except ModuleNotFoundError as missing:
    GRID_MISSING = f"the grid baseline needs {missing.name} (the grid extra)"
needs_grid = pytest.mark.skipif(GRID_MISSING is not None, reason=GRID_MISSING or "")

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
GRID = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])

def dry_box(**overrides):
    """A small closed box of dry-ish air at rest, neutral (lapse = Gamma_d, so the anomaly T - T0(y) does
    not change when a particle moves), no buoyancy: the particles' motion cannot feed back on T."""
    base = {"domain.size": [600.0, 800.0, 600.0], "particles.spacing": 100.0, "particles.max_speed": 0.0,
            "atmosphere.lapse_rate": 0.0098, "atmosphere.buoyancy": 0.0, "atmosphere.initial_vapor_ratio": 0.3,
            "smoothing.kappa": 0.0}
    base.update(overrides)
    return load_scene("growing").replace(**base)


# ---- C1: time of day ---------------------------------------------------------------------------
@needs_grid
@FAST
@given(period=st.floats(10.0, 1e5), cycles=st.floats(0.0, 6.0))
def test_diurnal_integral_is_the_closed_form(period, cycles):
    t = cycles * period
    s = np.linspace(0.0, t, 20001)
    numeric = np.trapezoid(np.maximum(0.0, np.sin(2 * np.pi * s / period)), s) if t > 0 else 0.0
    assert diurnal_integral(t, period) == pytest.approx(numeric, rel=1e-6, abs=1e-6 * period)
    # every full period adds P / pi, and nothing comes from the night half
    assert diurnal_integral(math.floor(cycles) * period, period) == pytest.approx(math.floor(cycles) * period / math.pi)


@pytest.mark.parametrize("backend", BACKENDS)
def test_particle_heating_follows_the_time_of_day(backend):
    dt, period, steps = 2.0, 80.0, 60                       # 1.5 periods, 40 steps per period
    runs = {}
    for p in (0.0, period):
        sim = Simulation(dry_box(**{"time.dt": dt, "atmosphere.diurnal_period": p}), backend=backend, seed=0)
        per_step = []
        for _ in range(steps):
            sim.step(1)
            per_step.append(sim.stats()["heat_source"])
        runs[p] = (np.array(per_step), sim.stats()["heat_source_total"])
    const, diurnal = runs[0.0][0], runs[period][0]
    mid = (np.arange(steps) + 0.5) * dt
    # eq. C1 step by step: the source is the constant one times f at the step's mid-time ...
    assert np.allclose(diurnal, const * np.maximum(0.0, np.sin(2 * np.pi * mid / period)), rtol=1e-5, atol=1e-12)
    # ... and its integral is int_0^T max(0, sin(2 pi t / P)) dt to the midpoint rule's O((dt/P)^2): here
    # T = 1.5 P, one whole day and one afternoon, each P / pi
    closed = (2 * period / math.pi) / (steps * dt)
    assert runs[period][1] / runs[0.0][1] == pytest.approx(closed, rel=(2 * np.pi * dt / period) ** 2)


@needs_grid
@GRID
@given(t=st.floats(0.0, 1e4), period=st.floats(50.0, 5e3), dt=st.floats(0.5, 20.0))
def test_grid_heating_follows_the_time_of_day(t, period, dt):
    scene = load_scene("growing").replace(**{"atmosphere.diurnal_period": period, "time.dt": dt,
                                             "atmosphere.initial_vapor_ratio": 0.1})
    p = params_from_scene(scene, (4, 4, 4))
    state = initial_state(p, np.float64)
    state["time"] = np.float64(t)
    aux = make_aux(p, np.float64)
    out = physics(state, aux, p)
    f = max(0.0, math.sin(2 * math.pi * (t + 0.5 * dt) / period))
    assert np.allclose(np.asarray(out["theta"]), dt * f * np.asarray(aux["heat"]), rtol=1e-9, atol=1e-12)
    assert float(out["time"]) == pytest.approx(t + dt)


# ---- C2: relaxation ----------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
def test_particle_relaxation_decays_an_anomaly_at_one_over_tau(backend):
    tau, dt, steps = 40.0, 2.0, 30
    scene = dry_box(**{"time.dt": dt, "atmosphere.relaxation_time": tau, "atmosphere.heating_rate": 0.0})
    base = Simulation(scene, backend="cpu", seed=0).state()
    y = base["position"][:, 1].astype(np.float64)
    T0 = scene.environment_temperature(y)
    v0 = 0.3 * scene.saturation(T0)
    fluid = dict(base, temperature=(T0 + 3.0).astype(np.float32), vapor=(v0 * 1.5).astype(np.float32))
    sim = Simulation.from_arrays(scene, fluid, backend=backend)
    start = sim.stats()
    sim.step(steps)
    st_ = sim.state()
    yn = st_["position"][:, 1].astype(np.float64)
    anomaly = st_["temperature"] - scene.environment_temperature(yn)
    decay = math.exp(-steps * dt / tau)
    assert np.allclose(anomaly, 3.0 * decay, atol=2e-3)
    # the vapor excess decays alike (0.45 of saturation: no cloud forms); the budget has both terms
    excess = st_["vapor"] / (0.3 * scene.saturation(scene.environment_temperature(yn))) - 1.0
    assert np.allclose(excess, 0.5 * decay, atol=2e-3)
    s = sim.stats()
    assert s["heat_relaxation_total"] == pytest.approx(s["mean_temperature"] - start["mean_temperature"], rel=1e-3)
    assert s["water_relaxation_total"] == pytest.approx(s["total_water"] - start["total_water"], rel=1e-5)


@needs_grid
@GRID
@given(tau=st.floats(5.0, 1e4), dt=st.floats(0.1, 50.0), steps=st.integers(1, 4))
def test_grid_relaxation_decays_an_anomaly_at_one_over_tau(tau, dt, steps):
    scene = load_scene("growing").replace(**{"atmosphere.relaxation_time": tau, "time.dt": dt,
                                             "atmosphere.heating_rate": 0.0, "atmosphere.initial_vapor_ratio": 0.3})
    p = params_from_scene(scene, (4, 4, 4))
    aux = make_aux(p, np.float64)
    state = initial_state(p, np.float64)
    state["theta"] = state["theta"] + 2.0
    state["vapor"] = 1.5 * state["vapor"]
    for _ in range(steps):
        state = physics(state, aux, p)
    decay = math.exp(-steps * dt / tau)
    assert np.allclose(np.asarray(state["theta"]), 2.0 * decay, rtol=1e-9)
    assert np.allclose(np.asarray(state["vapor"]) / np.asarray(aux["v0"]), 1.0 + 0.5 * decay, rtol=1e-9)


# ---- C3 + C4: rain and the water budget ---------------------------------------------------------
def rainy_scene(**overrides):
    """Supersaturated from the start (cloud at once), relaxation and autoconversion both on."""
    base = {"domain.size": [800.0, 1600.0, 800.0], "particles.spacing": 100.0,
            "atmosphere.initial_vapor_ratio": 1.05, "atmosphere.relaxation_time": 100.0,
            "atmosphere.autoconversion_rate": 0.02, "atmosphere.autoconversion_threshold": 2e-4,
            "atmosphere.diurnal_period": 200.0}
    base.update(overrides)
    return load_scene("growing").replace(**base)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("adaptive", [False, True])
def test_particle_water_budget_closes_with_rain_and_relaxation(backend, adaptive):
    over = {"adaptive.enabled": True, "particles.spacing": 200.0, "domain.size": [1200.0, 1600.0, 1200.0]} \
        if adaptive else {}
    sim = Simulation(rainy_scene(**over), backend=backend, seed=1)
    w0 = sim.stats()["total_water"]
    for _ in range(4):
        sim.step(15)
        s = sim.stats()
        closure = s["total_water"] - w0 - s["water_relaxation_total"] + s["water_rain_total"]
        assert abs(closure) < 1e-6 * w0                                           # eq. C4
    assert s["water_rain_total"] > 1e-4 * w0 and abs(s["water_relaxation_total"]) > 1e-4 * w0
    assert float(sim.state()["cloud"].max()) > 0.0


def test_checkpoint_carries_the_forcing_totals(tmp_path):
    sim = Simulation(rainy_scene(), backend="cpu", seed=1)
    sim.step(10)
    back = Simulation.load(sim.save(tmp_path / "c.npz"))
    a, b = sim.stats(), back.stats()
    for key in ("heat_relaxation_total", "water_relaxation_total", "water_rain_total"):
        assert a[key] != 0.0 and b[key] == a[key]


def test_scene_refuses_bad_forcing_values_by_name():
    with pytest.raises(SceneError, match="atmosphere.relaxation_time"):
        load_scene("cycling").replace(**{"atmosphere.relaxation_time": -1.0})
    with pytest.raises(SceneError, match="atmosphere.autoconversion_rate"):
        load_scene("cycling").replace(**{"atmosphere.autoconversion_rate": -0.1})


# ---- cycle counting and the CPU cycle -----------------------------------------------------------
@FAST
@given(n=st.integers(0, 5), peak=st.floats(0.05, 1.0), low=st.floats(0.0, 0.19), high=st.floats(0.5, 1.0))
def test_count_cycles_counts_built_cycles(n, peak, low, high):
    series = [0.0, peak]
    for _ in range(n):
        series += [low * peak, 0.3 * peak, high * peak]
    out = count_cycles(series)
    assert out["cycles"] == n and out["peak_cover"] == pytest.approx(peak)
    # a dip that stays above 20% of the peak is not a cycle, nor is the flicker of a cover below 5%
    assert count_cycles([0.0, peak, 0.25 * peak, peak])["cycles"] == 0
    assert count_cycles([0.0, 0.02, 0.0, 0.02, 0.0, 0.02])["cycles"] == 0


# The cycle as properties every run must have (no vote over seeds): clouds form in the first afternoon, the sky is
# clear for a stretch of the night, and clouds come back after it. Thresholds far from the measured values, so a
# rounding change cannot move a run across one (CPU scale, 144 columns; the adaptive twin, seeds 0-5 at a74c02b:
# first peaks 0.19-0.90, clear nights of 13-16 samples at cover 0, the second afternoon back to 0.08-0.43).
FORMED = 0.1          # the first afternoon's cover reaches this (measured 0.19 or more) ...
CLEAR = 0.01          # ... then the night's cover stays at or below this (no more than one column) ...
CLEAR_SAMPLES = 5     # ... for this many samples in a row (measured 13 or more) ...
BACK = 0.02           # ... and then the cover is back at 3 columns or more (measured 0.08 or more)


def cycle_phases(cover) -> dict:
    """Where the cycle's phases of a cover series happen (sample indices, None where not reached): formed (first
    cover >= FORMED), cleared (the end of the first CLEAR_SAMPLES-long clear stretch after it), back (first cover >=
    BACK after that)."""
    c = np.asarray(cover, dtype=np.float64)
    out = {"formed": None, "cleared": None, "back": None}
    hits = np.nonzero(c >= FORMED)[0]
    if not len(hits):
        return out
    out["formed"] = int(hits[0])
    run = 0
    for k in range(out["formed"], len(c)):
        run = run + 1 if c[k] <= CLEAR else 0
        if run >= CLEAR_SAMPLES:
            out["cleared"] = k
            break
    if out["cleared"] is None:
        return out
    back = np.nonzero(c[out["cleared"]:] >= BACK)[0]
    out["back"] = int(out["cleared"] + back[0]) if len(back) else None
    return out


def test_cycle_phases_of_built_series():
    day = [0.0] * 3 + [0.3, 0.6, 0.2] + [0.0] * 6 + [0.01, 0.05]
    assert cycle_phases(day) == {"formed": 3, "cleared": 10, "back": 13}
    assert cycle_phases([0.0, 0.05, 0.09])["formed"] is None                 # never formed
    assert cycle_phases([0.5, 0.0, 0.02, 0.0, 0.0, 0.0, 0.3])["cleared"] is None   # no clear stretch
    assert cycle_phases([0.5] + [0.0] * 5 + [0.015])["back"] is None          # one column's flicker is no cloud


def cover_series(kind, seconds=3600.0, every=5, seed=0):
    """Cloud cover of the CPU cycle every `every` steps, for up to three model days (P = 1200 s); for the
    grid the water budget (C4) is checked at every sample too (the grid's budget test: one compilation for
    both).  The series stops once the clouds are back after a clear night (cycle_phases)."""
    scene = load_scene("cycling").replace(**CPU_OVERRIDES)
    shape, _ = grid_for_scene(scene)
    if kind == "adaptive":
        scene = load_scene("cycling_adaptive").replace(**CPU_OVERRIDES)   # the deposit grid stays the base one's
    steps = int(seconds / scene.time.dt)
    out = []
    if kind == "grid":
        if GRID_MISSING:
            pytest.skip(GRID_MISSING)
        sim = GridSimulation(scene, seed=0, resolution=shape)
        w0 = sim.stats()["total_water"]
        for _ in range(steps // every):
            sim.step(every)
            s = sim.stats()
            assert abs(s["total_water"] - w0 - s["water_relaxation_total"] + s["rain_total"]) < 1e-6 * w0  # C4
            out.append(s["cloud_cover"])
            if cycle_phases(out)["back"] is not None:
                break                                      # one full cycle: the rest of the run adds nothing
        assert s["rain_total"] > 1e-4 * w0 and abs(s["water_relaxation_total"]) > 1e-4 * w0
    else:
        sim = Simulation(scene, backend="cpu", seed=seed)
        for _ in range(steps // every):
            sim.step(every)
            out.append(particle_diagnostics(sim.state(), scene, resolution=shape)["cloud_cover"])
            if cycle_phases(out)["back"] is not None:
                break
    return np.array(out)


def test_cpu_cycle_adapts_at_the_gpu_scenes_interval_in_model_time():
    # The CPU cycle's steps are longer (dt 8 s against 2 s), so it splits and merges every step to keep the
    # shipped scene's interval between adaptations in model seconds (docs/cycling.md).
    gpu = load_scene("cycling_adaptive")
    cpu = gpu.replace(**CPU_OVERRIDES)
    assert gpu.adaptive.enabled and cpu.adaptive.enabled
    assert cpu.adaptive.every * cpu.time.dt == pytest.approx(gpu.adaptive.every * gpu.time.dt)


@pytest.mark.slow
@pytest.mark.parametrize("kind, seed", [("particles", 0), ("adaptive", 0), ("adaptive", 1), ("grid", 0)])
def test_clouds_disappear_and_reappear_at_cpu_scale(kind, seed):
    # Every run must cycle (no majority of seeds): whether the second day's clouds reach half the first day's peak
    # (count_cycles, the study's count) is chance in this 2,304-particle box, that they come back at all is not.
    cover = cover_series(kind, seed=seed)
    phases = cycle_phases(cover)
    shown = np.round(cover, 3).tolist()
    assert phases["formed"] is not None, ("no clouds in the first afternoon", kind, seed, shown)
    assert phases["cleared"] is not None, ("no clear night", kind, seed, shown)
    assert phases["back"] is not None, ("no clouds after the night", kind, seed, shown)
    # the phases follow the sun (P = 1200 s, a sample every 40 s: 30 per day): the clouds come back on a later day
    assert phases["back"] - phases["formed"] > 15


def test_report_shows_the_cycling_study(tmp_path):
    from cloudpbf.studies.page import build_report
    data = tmp_path / "data"
    data.mkdir()
    t = np.arange(0.0, 2400.0, 40.0)
    rows, cycles = [], []
    for solver, mode in (("particles", "non-adaptive"), ("particles", "adaptive"), ("grid", "grid")):
        for seed in range(3):
            cover = np.maximum(0.0, np.sin(2 * np.pi * t / 1200.0)) * (0.4 + 0.05 * seed)
            rows += [{"solver": solver, "mode": mode, "seed": seed, "time_s": ti, "step": int(ti / 8),
                      "cloud_cover": c, "lwp_mean": 0.1 * c, "cloud_top": 1000.0 * (c > 0)} for ti, c in zip(t, cover)]
            cycles.append({"solver": solver, "mode": mode, "seed": seed, **count_cycles(cover), "device": "cpu",
                           "commit": "abc"})
    import pandas as pd
    pd.DataFrame(rows).to_csv(data / "cycling_timeseries.csv", index=False)
    pd.DataFrame(cycles).to_csv(data / "cycling_cycles.csv", index=False)
    frame = pd.DataFrame(rows).assign(total_water=1e5, rain_total=0.0, water_relaxation_total=0.0)
    cycle_budgets(frame).assign(device="cpu", commit="abc").to_csv(data / "cycling_budgets.csv", index=False)
    (data / "renders").mkdir()
    import matplotlib.pyplot as plt
    plt.imsave(data / "renders" / "cycling_grid_peak.png", np.zeros((4, 4, 3)))
    section = build_report(tmp_path).read_text().split('<section id="compare"', 1)[1].split("<section", 1)[0]
    assert "clouds that disappear and reappear" in section and "cycling_cycles.csv" in section
    assert "data:image/png" in section and "could not build" not in section
    assert "cycling_budgets.csv" in section and "at its first cover peak" in section


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(2, 5), period=st.floats(300.0, 3000.0), leak=st.floats(-1e-3, 1e-3))
def test_cycle_budgets_window_each_cycle_and_close_the_water_budget(n, period, leak):
    import pandas as pd
    from cloudpbf.studies.cycling import cycle_budgets, cycle_windows
    t = np.linspace(0.0, n * period, 40 * n + 1)
    cover = 0.5 * np.maximum(0.0, np.sin(2 * np.pi * t / period)) ** 2
    rain = 2.0 * t / period                                      # kg, running sums
    relax = -0.5 * np.sin(2 * np.pi * t / period)
    water = 1e5 + relax - rain + leak * 1e5 * t / period        # C4 with a leak of `leak` per period
    frame = pd.DataFrame({"solver": "grid", "mode": "grid", "seed": 0, "time_s": t, "cloud_cover": cover,
                          "total_water": water, "rain_total": rain, "water_relaxation_total": relax})
    windows = cycle_windows(cover, t)
    assert len(windows) == n - 1                                 # the last generation never returns
    for k, w in enumerate(windows):
        assert w["start_s"] < w["peak_s"] < w["min_s"] < w["end_s"] and w["min_cover"] == 0.0
        assert w["peak_s"] == pytest.approx((k + 0.25) * period, abs=period / 40 + 1e-9)
    budgets = cycle_budgets(frame)
    assert list(budgets["cycle"]) == list(range(1, n))
    span = budgets["end_s"] - budgets["start_s"]
    assert np.allclose(budgets["rain"], 2.0 * span / period)
    assert np.allclose(budgets["closure"], leak * span / period, rtol=1e-2, atol=1e-12)   # of ~1e5 kg


def test_cycle_budgets_name_a_missing_column():
    import pandas as pd
    from cloudpbf.studies.cycling import cycle_budgets
    with pytest.raises(ValueError, match="rain_total"):
        cycle_budgets(pd.DataFrame({"solver": [], "mode": [], "seed": [], "time_s": [], "cloud_cover": [],
                                    "total_water": [], "water_relaxation_total": []}))
