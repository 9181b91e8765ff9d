"""The adaptive-pareto study's analysis: seed means, errors against the reference mean, the uniform front and
the speed-up at equal error, on synthetic runs whose answers are known in closed form."""
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as st

from bench.studies import adaptive_pareto as ap


def fake_result(time, cover, ms_per_step, particles, steps=100, pbf_share=0.5, seed_shift=0.0):
    stats = pd.DataFrame({"time_s": time, "cloud_cover": cover + seed_shift, "cloudy_volume": 1e9 * (cover + seed_shift),
                          "lwp_mean": 0.1 * (cover + seed_shift), "cloud_base": 600.0 + 0 * time,
                          "cloud_top": 1500.0 + 0 * time, "n_particles": particles})
    prof = pd.DataFrame({"time_s": time[-1], "z": [100.0, 300.0, 500.0], "cloud_fraction": [0.0, 0.2, 0.1]})
    timings = {"pbf": {"total_ms": pbf_share * ms_per_step * steps, "count": steps, "mean_ms": 0.0}}
    return SimpleNamespace(stable=True, reason=None, stats=lambda: stats, profiles=lambda: prof, timings=lambda: timings,
                           step_wall_s=ms_per_step * steps / 1e3, max_particles=particles, device="test", path="x")


def test_errors_vanish_against_itself_and_scale_with_an_offset():
    t = np.linspace(0, 1000, 11)
    ref = ap.signature(fake_result(t, np.linspace(0.1, 0.5, 11), 1.0, 1000))
    assert ap.errors(ref, ref)["error"] == 0.0
    off = ap.signature(fake_result(t, np.linspace(0.1, 0.5, 11), 1.0, 1000, seed_shift=0.05))
    cover = np.linspace(0.1, 0.5, 11)
    expected = 0.05 * math.sqrt(11) / np.linalg.norm(cover)
    assert ap.errors(off, ref)["e_cover"] == pytest.approx(expected, rel=1e-12)
    assert ap.errors(off, ref)["e_base"] == 0.0


def test_seed_mean_cancels_symmetric_seed_noise():
    t = np.linspace(0, 1000, 11)
    cover = np.linspace(0.1, 0.5, 11)
    sigs = [ap.signature(fake_result(t, cover, 1.0, 1000, seed_shift=s)) for s in (-0.03, 0.0, 0.03)]
    mean = ap.mean_signature(sigs)
    assert np.allclose(mean["cover"], cover)


@settings(max_examples=30, deadline=None)
@given(speedup=st.floats(0.3, 5.0), where=st.floats(0.05, 0.95))
def test_speedup_at_equal_error_is_the_uniform_front_time_over_the_variants(speedup, where):
    """Uniform runs on a front t = c e^-2: a variant at error e between them, with time t_front(e) / s,
    gets speed-up s (log-log interpolation is exact on a power law)."""
    errors = np.array([0.4, 0.2, 0.1, 0.05])
    uniform = pd.DataFrame({"config": [f"u{i}" for i in range(4)], "error": errors, "ms_per_step": 2.0 / errors**2})
    front = ap.uniform_front(uniform)
    e = float(np.exp(np.log(0.05) + where * (np.log(0.4) - np.log(0.05))))
    t_front = ap.time_at_error(front, e)
    assert t_front == pytest.approx(2.0 / e**2, rel=1e-9)
    variant = {"error": e, "ms_per_step": t_front / speedup}
    assert ap.time_at_error(front, variant["error"]) / variant["ms_per_step"] == pytest.approx(speedup, rel=1e-9)
    assert ap.time_at_error(front, 0.01) != ap.time_at_error(front, 0.01)   # NaN beyond the front


def test_analysis_writes_a_verdict_with_cost_ratio_and_speedup():
    t = np.linspace(0, 1000, 11)
    cover = np.linspace(0.1, 0.6, 11)
    entries, results = [], []
    # uniform at four spacings: error falls (offset shrinks) and cost rises; PBF cost 1 us per particle
    for k, (spacing, n, ms, off) in enumerate([(68, 1e5, 2.0, 0.2), (54, 2e5, 4.0, 0.1), (43, 4e5, 8.0, 0.05),
                                               (34, 8e5, 16.0, 0.025)]):
        c = ap.Config(f"uniform-{spacing}m", "uniform", spacing, "")
        for seed in range(3):
            entries.append((c, seed, SimpleNamespace(total_steps=100)))
            results.append(fake_result(t, cover, ms, n, seed_shift=off, pbf_share=n * 1e-3 / ms))
    c = ap.Config("lookahead-68m", "adaptive", 68, "lookahead")
    for seed in range(3):   # error of the 43 m run at half its time, PBF 1.2 us per particle
        entries.append((c, seed, SimpleNamespace(total_steps=100)))
        results.append(fake_result(t, cover, 4.0, 4e5, seed_shift=0.05, pbf_share=4e5 * 1.2e-3 / 4.0))
    r = ap.Config("reference-27m", "reference", 27, "")
    for seed in range(3):
        entries.append((r, seed, SimpleNamespace(total_steps=100)))
        results.append(fake_result(t, cover, 32.0, 1.6e6, seed_shift=0.001 * (seed - 1)))
    per_run, per_config, verdict = ap.analyse(entries, results, "growing", "test", "abc")
    assert len(per_run) == 18 and set(per_config["config"]) >= {"lookahead-68m", "reference-27m"}
    v = verdict["variants"][0]
    assert v["speedup_at_equal_error"] == pytest.approx(2.0, rel=0.02)
    assert verdict["cost_ratio_per_particle"] == pytest.approx(1.2, rel=1e-6)
    assert verdict["noise_floor"] < 0.01
    assert "2.00x faster" in verdict["verdict"]


def test_render_configs_pick_the_best_variant_and_its_uniform_twins():
    per_config = pd.DataFrame({
        "config": ["uniform-68m", "uniform-54m", "uniform-43m", "uniform-34m", "thermal-68m", "paper-54m"],
        "kind": ["uniform"] * 4 + ["adaptive"] * 2, "spacing_m": [68.0, 54.0, 43.0, 34.0, 68.0, 54.0],
        "error": [0.8, 0.6, 0.3, 0.1, 0.2, 0.7]})
    assert ap.render_configs(per_config, {"best": {"name": "paper-54m"}}) == ["paper-54m", "uniform-54m", "uniform-34m"]
    # without a scored variant: the adaptive run of lowest error; level 3 of 68 m is 34 m
    assert ap.render_configs(per_config, {"best": None}) == ["thermal-68m", "uniform-68m", "uniform-34m"]
    assert ap.render_configs(per_config[per_config.kind == "uniform"], {}) == []


def test_pareto_states_keep_every_cloudy_particle(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    n = 5000
    cloud = np.where(rng.random(n) < 0.05, 1e-3, 0.0).astype(np.float32)
    snap = tmp_path / "snap.npz"
    np.savez(snap, position=rng.random((n, 3)).astype(np.float32), cloud=cloud, level=np.zeros(n, np.uint8),
             time_s=np.array(1000.0), step=np.array(500))
    monkeypatch.setattr("bench.store.result.RunResult.load", staticmethod(
        lambda path: SimpleNamespace(snapshot_paths=lambda: [snap])))
    per_config = pd.DataFrame({"config": ["uniform-68m", "uniform-34m", "thermal-68m"],
                               "kind": ["uniform", "uniform", "adaptive"], "spacing_m": [68.0, 34.0, 68.0],
                               "error": [0.8, 0.1, 0.2]})
    per_run = pd.DataFrame({"config": per_config["config"], "seed": 0, "run_dir": "x"})
    written = ap.pareto_states(per_run, per_config, {"best": {"name": "thermal-68m"}}, tmp_path / "states")
    assert [p.name for p in written] == ["pareto_thermal-68m.npz", "pareto_uniform-68m.npz", "pareto_uniform-34m.npz"]
    with np.load(written[0]) as z:
        assert int((z["cloud"] > 0).sum()) == int((cloud > 0).sum())
        assert 0.05 * n < len(z["cloud"]) < 0.2 * n and int(z["particles"]) == n and str(z["config"]) == "thermal-68m"
        assert str(z["kind"]) == "adaptive"
    with np.load(written[1]) as z:
        assert str(z["kind"]) == "uniform"
