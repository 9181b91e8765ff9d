"""The adaptive-pareto study's analysis: seed means, errors against the reference mean, the uniform front and
the speed-up at equal error, on synthetic runs whose answers are known in closed form."""
import json
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as st

from cloudpbf.studies import adaptive_pareto as ap
from cloudpbf.studies.plans import scene_file_suffix


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
    # as many particles as the 43 m run (8 ms) and its error: placement buys nothing, the step costs half
    assert v["uniform_ms_at_equal_particles"] == pytest.approx(8.0)
    assert (v["speedup_from_particles"], v["step_cost_ratio"]) == pytest.approx((1.0, 0.5), rel=0.02)
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
    # a deeper variant's finest spacing: level 0 108 m (nearest uniform 68 m), level 6 27 m (34 m; level 3 would be 54 m)
    deep = pd.concat([per_config, pd.DataFrame({"config": ["thermal-108m-L6"], "kind": ["adaptive"],
                                                "spacing_m": [108.0], "error": [0.05]})], ignore_index=True)
    deep["max_level"] = np.where(deep.kind == "adaptive", 3, 0)
    deep.loc[deep.config == "thermal-108m-L6", "max_level"] = 6
    assert ap.render_configs(deep, {"best": {"name": "thermal-108m-L6"}}) == [
        "thermal-108m-L6", "uniform-68m", "uniform-34m"]


@pytest.mark.parametrize("scene_name", ap.SCENES)
@pytest.mark.parametrize("scale", ["smoke", "cpu"])   # (a "gpu" id would mark it a GPU test)
def test_every_variant_runs_the_scene_it_names(scale, scene_name):
    """Each adaptive configuration's scene is the study scene's adaptive twin with its criterion, finest level
    and scaled eq. 20 thresholds; names are unique, and uniform and reference runs are the plain scene at their
    spacing."""
    configs = ap.configs(scale)
    assert len({c.name for c in configs}) == len(configs)
    f = ap.SPACING_FACTOR[scale]
    plain = ap.load_scene(scene_name)
    for config in configs:
        scene = ap.scene_for(config, scene_name, 1.0)
        assert scene.particles.spacing == pytest.approx(config.spacing_m)
        assert scene.adaptive.enabled == (config.kind == "adaptive")
        for field in ("lapse_rate", "inversion_height", "inversion_strength", "heating_patch_radius", "noise_frequency"):
            assert getattr(scene.atmosphere, field) == getattr(plain.atmosphere, field), field   # the regime's own air
        if config.kind != "adaptive":
            assert scene.name == scene_name
            continue
        assert scene.name == f"{scene_name}_adaptive"
        base = ap.load_scene(f"{scene_name}_adaptive").adaptive
        assert (scene.adaptive.criterion, scene.adaptive.max_level) == (config.criterion, config.max_level)
        assert scene.adaptive.split_threshold == pytest.approx(base.split_threshold * config.threshold_scale)
        assert scene.adaptive.merge_threshold == pytest.approx(base.merge_threshold * config.threshold_scale)
        assert scene.adaptive.every == (config.adapt_every or base.every)
        assert scene.adaptive.pair_kernel == (config.pair_kernel or base.pair_kernel)
        assert config.finest_spacing_m == pytest.approx(config.spacing_m / 2 ** (config.max_level / 3))
        assert config.name.startswith(f"{config.criterion}-{config.spacing_m / f:g}m")
    assert {"thermal-68m-L4", "thermal-54m-t0.25", "thermal-68m-L4-t0.25-e4",
            "thermal-68m-L4-t0.25-e4-km", "thermal-68m-L4-t0.25-e8-km",
            "thermal-68m-L4-t0.25-e16-km"} <= {c.name for c in configs}


def test_pareto_states_keep_every_cloudy_particle(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    n = 5000
    cloud = np.where(rng.random(n) < 0.05, 1e-3, 0.0).astype(np.float32)
    snap = tmp_path / "snap.npz"
    np.savez(snap, position=rng.random((n, 3)).astype(np.float32), cloud=cloud, level=np.zeros(n, np.uint8),
             time_s=np.array(1000.0), step=np.array(500))
    monkeypatch.setattr("cloudpbf.store.result.RunResult.load", staticmethod(
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


# ---- the verdict rests only on configurations stable in every seed -----------------------------------------
def _frame(adaptive_stable: dict[str, int], uniform_stable: int = 3, seeds: int = 3):
    """Per-configuration and per-run rows as the study writes them: uniform runs on the front t = 2 / e^2,
    `cheap-54m` below the front (cheapest and most accurate), `ok-68m` at the 43 m run's error in half its time."""
    rows = [(f"uniform-{s}m", "uniform", "", s, e, 2.0 / e**2, 1e5 * 2**k, uniform_stable)
            for k, (s, e) in enumerate([(68, 0.4), (54, 0.2), (43, 0.1), (34, 0.05)])]
    adaptive = {"cheap-54m": ("paper", 54, 0.06, 1.0, 2e5), "ok-68m": ("lookahead", 68, 0.1, 100.0, 1.5e5)}
    rows += [(name, "adaptive", crit, s, e, ms, n, adaptive_stable[name])
             for name, (crit, s, e, ms, n) in adaptive.items()]
    rows.append(("reference-27m", "reference", "", 27, 0.0, 500.0, 1.7e6, seeds))
    per_config = pd.DataFrame(rows, columns=["config", "kind", "criterion", "spacing_m", "error", "ms_per_step",
                                             "particles", "stable_seeds"])
    per_config = per_config.assign(seeds=seeds, error_seed_spread=0.01,
                                   pbf_ms_per_particle=1e-5 * per_config["ms_per_step"] / per_config["ms_per_step"])
    per_run = pd.DataFrame([{"config": r.config, "kind": r.kind, "seed": seed, "stable": seed < r.stable_seeds,
                             "reason": None if seed < r.stable_seeds else "speed above max_velocity",
                             "error_this_seed": 0.02 if r.kind == "reference" else r.error}
                            for r in per_config.itertuples() for seed in range(seeds)])
    return per_run, per_config


def test_verdict_skips_a_variant_stable_in_one_seed_of_three():
    per_run, per_config = _frame({"cheap-54m": 1, "ok-68m": 3})
    verdict = ap.build_verdict(per_run, per_config, "growing", "test", "abc")
    verdict.pop("_speedups")
    # without the rule cheap-54m would win (it is below the front: 2/0.06^2 = 556 ms at equal error, 556x)
    assert verdict["best"]["name"] == "ok-68m"
    assert (verdict["best"]["stable_seeds"], verdict["best"]["seeds"]) == (3, 3)
    assert verdict["best"]["speedup_at_equal_error"] == pytest.approx(2.0)   # 200 ms at e = 0.1, it takes 100
    assert verdict["min_stable_seeds"] == 3 and [v["name"] for v in verdict["variants"]] == ["ok-68m"]
    (out,) = verdict["excluded"]
    assert out["name"] == "cheap-54m" and (out["stable_seeds"], out["seeds"]) == (1, 3)
    assert out["reasons"][0] == "stable in 1 of 3 seeds (the verdict needs 3)"
    assert "seed 1: speed above max_velocity" in out["reasons"]
    assert out["error_seed_spread"] is None          # one stable seed has no spread
    assert "ok-68m (stable in 3 of 3 seeds)" in verdict["verdict"] and "cheap-54m (1/3 stable)" in verdict["verdict"]
    assert verdict["noise_floor"] == pytest.approx(0.02)
    # a looser rule lets it back in, and then it wins
    loose = ap.build_verdict(per_run, per_config, "growing", "test", "abc", min_stable_seeds=1)
    assert loose["best"]["name"] == "cheap-54m" and loose["excluded"] == []


def test_no_qualifying_variant_gives_no_best():
    per_run, per_config = _frame({"cheap-54m": 1, "ok-68m": 2})
    verdict = ap.build_verdict(per_run, per_config, "growing", "test", "abc")
    assert verdict["best"] is None and verdict["variants"] == []
    assert {e["name"] for e in verdict["excluded"]} == {"cheap-54m", "ok-68m"}
    assert verdict["verdict"].startswith("growing: no best variant: no adaptive variant is stable in at least 3 seeds")
    # uniform configurations are held to the same rule: with none left there is no front and no best
    per_run, per_config = _frame({"cheap-54m": 3, "ok-68m": 3}, uniform_stable=2)
    verdict = ap.build_verdict(per_run, per_config, "growing", "test", "abc")
    assert verdict["best"] is None and verdict["uniform_front"] == []
    assert sum(e["kind"] == "uniform" for e in verdict["excluded"]) == 4
    assert "no uniform front" in verdict["verdict"]


def test_verdict_rebuilt_from_the_csvs_keeps_the_runs_device_and_commit(tmp_path):
    per_run, per_config = _frame({"cheap-54m": 1, "ok-68m": 3})
    per_run.assign(device="csv-device", commit="csv-commit").to_csv(tmp_path / "adaptive_pareto.csv", index=False)
    per_config.to_csv(tmp_path / "adaptive_pareto_configs.csv", index=False)
    verdict = ap.rebuild_verdict(tmp_path, "growing")          # no verdict yet: device and commit of the runs
    assert (verdict["device"], verdict["commit"]) == ("csv-device", "csv-commit")
    (tmp_path / "adaptive_verdict.json").write_text('{"device": "H100", "commit": "18dd959", "best": null}')
    verdict = ap.rebuild_verdict(tmp_path, "growing")
    written = json.loads((tmp_path / "adaptive_verdict.json").read_text())
    assert (written["device"], written["commit"]) == ("H100", "18dd959")
    assert written["best"]["name"] == "ok-68m" and written["excluded"][0]["name"] == "cheap-54m"
    assert "_speedups" not in written
    with pytest.raises(FileNotFoundError):
        ap.rebuild_verdict(tmp_path, "cumulus")


def test_from_data_command_prints_the_verdict_and_what_it_left_out(tmp_path):
    from typer.testing import CliRunner
    import typer
    per_run, per_config = _frame({"cheap-54m": 1, "ok-68m": 2})
    (tmp_path / "data").mkdir()
    per_run.assign(device="d", commit="c").to_csv(tmp_path / "data" / "adaptive_pareto.csv", index=False)
    per_config.to_csv(tmp_path / "data" / "adaptive_pareto_configs.csv", index=False)
    app = typer.Typer()
    app.command()(ap.adaptive_pareto_command)
    result = CliRunner().invoke(app, ["--from-data", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "no best variant" in result.output and "best variant: none" in result.output
    assert "left out: cheap-54m (1/3 seeds stable)" in result.output
    assert json.loads((tmp_path / "data" / "adaptive_verdict.json").read_text())["best"] is None


def test_analysis_leaves_out_a_variant_that_blew_up_in_two_seeds():
    t = np.linspace(0, 1000, 11)
    cover = np.linspace(0.1, 0.6, 11)
    entries, results = [], []
    steps = SimpleNamespace(total_steps=100)
    for spacing, n, ms, off in [(68, 1e5, 2.0, 0.2), (54, 2e5, 4.0, 0.1), (43, 4e5, 8.0, 0.05), (34, 8e5, 16.0, 0.025)]:
        for seed in range(3):
            entries.append((ap.Config(f"uniform-{spacing}m", "uniform", spacing, ""), seed, steps))
            results.append(fake_result(t, cover, ms, n, seed_shift=off))
    for name, ms, unstable in (("paper-54m", 1.0, (0, 1)), ("lookahead-68m", 4.0, ())):
        for seed in range(3):
            r = fake_result(t, cover, ms, 4e5, seed_shift=0.05)
            if seed in unstable:
                r.stable, r.reason = False, "speed above max_velocity"
            entries.append((ap.Config(name, "adaptive", 68, name.split("-")[0]), seed, steps))
            results.append(r)
    for seed in range(3):
        entries.append((ap.Config("reference-27m", "reference", 27, ""), seed, steps))
        results.append(fake_result(t, cover, 32.0, 1.6e6, seed_shift=0.001 * (seed - 1)))
    per_run, per_config, verdict = ap.analyse(entries, results, "growing", "test", "abc")
    assert verdict["best"]["name"] == "lookahead-68m" and verdict["best"]["stable_seeds"] == 3
    assert [(e["name"], e["stable_seeds"], e["seeds"]) for e in verdict["excluded"]] == [("paper-54m", 1, 3)]
    row = per_config.set_index("config").loc["paper-54m"]
    assert row["stable_seeds"] == 1 and math.isnan(row["error_seed_spread"])   # one seed: no spread
    assert row["speedup_at_equal_error"] == pytest.approx(8.0, rel=0.02)      # still in the CSV, not in the verdict
    assert "_speedups" not in verdict


# ---- resampling the seeds: how sure the speed-up is ----------------------------------------------------------
def _noisy_study(noise: float, seeds: int, shifts=None):
    """A study on the front t = 0.4 / e (uniform offsets 0.2 ... 0.025 at 2 ... 16 ms) with one variant at the
    43 m run's error (offset 0.05) in 4 ms, i.e. 2x; its seeds scatter by `noise` (a fixed draw per seed)."""
    t = np.linspace(0, 1000, 11)
    cover = np.linspace(0.1, 0.6, 11)
    steps = SimpleNamespace(total_steps=100)
    z = np.random.default_rng(7).standard_normal(seeds) if shifts is None else np.asarray(shifts)
    z = z - z.mean()
    entries, results = [], []
    for spacing, ms, off in [(68, 2.0, 0.2), (54, 4.0, 0.1), (43, 8.0, 0.05), (34, 16.0, 0.025)]:
        for seed in range(seeds):
            entries.append((ap.Config(f"uniform-{spacing}m", "uniform", spacing, ""), seed, steps))
            results.append(fake_result(t, cover, ms, 1e5, seed_shift=off))
    for seed in range(seeds):
        entries.append((ap.Config("thermal-68m", "adaptive", 68, "thermal"), seed, steps))
        results.append(fake_result(t, cover, 4.0, 1e5, seed_shift=0.05 + noise * z[seed]))
        entries.append((ap.Config("reference-27m", "reference", 27, ""), seed, steps))
        results.append(fake_result(t, cover, 32.0, 1.6e6))
    return entries, results


def test_without_seed_noise_every_resample_gives_the_same_speedup():
    entries, results = _noisy_study(0.0, 5)
    _, per_config, verdict = ap.analyse(entries, results, "growing", "test", "abc", replicates=50)
    best = verdict["best"]
    assert best["speedup_at_equal_error"] == pytest.approx(2.0, rel=1e-9)
    assert best["speedup_interval"] == pytest.approx([2.0, 2.0], rel=1e-9)
    assert best["p_speedup_at_least_goal"] == 1.0 and best["best_share"] == 1.0
    assert verdict["resampling"] == {"replicates": 50, "seeds": 5, "goal_speedup": ap.GOAL_SPEEDUP,
                                     "no_best_share": 0.0}
    row = per_config.set_index("config").loc["thermal-68m"]
    assert (row["speedup_p05"], row["speedup_p95"]) == pytest.approx((2.0, 2.0))
    assert "between 2.00x and 2.00x (5-95%), reaches 1.6x in 100% of them" in verdict["verdict"]


@settings(max_examples=5, deadline=None)
@given(noise=st.floats(0.003, 0.02))
def test_the_interval_holds_the_speedup_widens_with_noise_and_narrows_with_seeds(noise):
    """Seed scatter of the variant widens its interval about linearly; four times the seeds (with the same
    scatter) narrow it (about twice, as 1/sqrt(n))."""
    widths = {}
    for amplitude, seeds in ((noise, 4), (2 * noise, 4), (noise, 16)):
        shifts = np.tile([-1.0, -0.3, 0.3, 1.0], seeds // 4)      # the same spread of seeds at 4 and 16
        entries, results = _noisy_study(amplitude, seeds, shifts)
        _, _, verdict = ap.analyse(entries, results, "growing", "test", "abc", replicates=200)
        v = verdict["variants"][0]
        lo, hi = v["speedup_interval"]
        assert lo <= v["speedup_at_equal_error"] * 1.02 and v["speedup_at_equal_error"] <= hi * 1.02
        widths[(amplitude, seeds)] = hi - lo
    assert widths[(noise, 4)] > 0
    assert widths[(2 * noise, 4)] > 1.4 * widths[(noise, 4)]
    assert widths[(noise, 16)] < 0.75 * widths[(noise, 4)]


@settings(max_examples=10, deadline=None)
@given(n_times=st.integers(2, 30), n_z=st.integers(1, 20), seed=st.integers(0, 10**6))
def test_series_table_gives_back_every_signature(n_times, n_z, seed):
    rng = np.random.default_rng(seed)
    def sig():
        out = {"time": np.sort(rng.uniform(0, 1000, n_times))}
        for key, _ in ap.SERIES:
            out[key] = rng.uniform(0, 1, n_times)
        out["base"][rng.integers(n_times)] = np.nan          # a time without cloud
        out["z"], out["profile"] = np.sort(rng.uniform(0, 3000, n_z)), rng.uniform(0, 1, n_z)
        return out
    keys = [("uniform-68m", 0), ("uniform-68m", 1), ("thermal-68m", 0), ("thermal-68m", 1)]
    sigs = [sig(), sig(), None, sig()]
    back = ap.signatures_from_series(ap.series_frame(keys, sigs))
    assert set(back) == {k for k, s in zip(keys, sigs) if s is not None}
    for key, s in zip(keys, sigs):
        if s is None:
            continue
        for name in ("time", "z", "profile") + tuple(k for k, _ in ap.SERIES):
            np.testing.assert_array_equal(back[key][name], s[name])


def test_from_data_redoes_the_resampling_from_the_series(tmp_path):
    entries, results = _noisy_study(0.01, 6)
    per_run, per_config, verdict = ap.analyse(entries, results, "growing", "test", "abc", replicates=100)
    per_run.to_csv(tmp_path / "adaptive_pareto.csv", index=False)
    per_config.to_csv(tmp_path / "adaptive_pareto_configs.csv", index=False)
    series = ap.series_frame([(c.name, seed) for c, seed, _ in entries], [ap.signature(r) for r in results])
    series.to_csv(tmp_path / "adaptive_pareto_series.csv", index=False)
    again = ap.rebuild_verdict(tmp_path, "growing", replicates=100)
    assert again["best"]["speedup_interval"] == pytest.approx(verdict["best"]["speedup_interval"], rel=1e-9)
    assert again["resampling"] == verdict["resampling"]
    (tmp_path / "adaptive_pareto_series.csv").unlink()        # older data: no series, no interval
    older = ap.rebuild_verdict(tmp_path, "growing")
    assert older["resampling"] is None and "speedup_interval" not in older["best"]
    assert older["best"]["speedup_at_equal_error"] == pytest.approx(verdict["best"]["speedup_at_equal_error"])


@settings(max_examples=25, deadline=None)
@given(exponent=st.floats(0.3, 1.5), count=st.floats(1.1e5, 7e5), overhead=st.floats(0.8, 2.0))
def test_speedup_is_what_the_particles_buy_over_what_the_step_costs(exponent, count, overhead):
    """Uniform runs with t = c N^p: the time at a count inside their range is exact (log-log), and the two
    factors multiply to the speed-up."""
    n = np.array([1e5, 2e5, 4e5, 8e5])
    uniform = pd.DataFrame({"particles": n, "ms_per_step": 2e-3 * n**exponent})
    t_count = ap.uniform_time_at_count(uniform, count)
    assert t_count == pytest.approx(2e-3 * count**exponent, rel=1e-9)
    assert math.isnan(ap.uniform_time_at_count(uniform, 9e5))      # beyond the uniform runs: unknown
    t_error, t_variant = 3.0 * t_count, overhead * t_count
    f = ap.speedup_factors(t_error, t_count, t_variant)
    assert f["step_cost_ratio"] == pytest.approx(overhead)
    assert f["speedup_from_particles"] / f["step_cost_ratio"] == pytest.approx(t_error / t_variant)


@pytest.mark.parametrize("damage", ["columns", "runs", "bytes"])
def test_from_data_refuses_a_damaged_series_file_naming_it(tmp_path, damage):
    """A series file that is not one, lacks runs, or is not a CSV: exit code 2 naming the file; nothing written."""
    from typer.testing import CliRunner
    import typer
    entries, results = _noisy_study(0.01, 4)
    per_run, per_config, _ = ap.analyse(entries, results, "growing", "test", "abc", replicates=20)
    data = tmp_path / "data"
    data.mkdir()
    per_run.to_csv(data / "adaptive_pareto.csv", index=False)
    per_config.to_csv(data / "adaptive_pareto_configs.csv", index=False)
    series = ap.series_frame([(c.name, seed) for c, seed, _ in entries], [ap.signature(r) for r in results])
    path = data / "adaptive_pareto_series.csv"
    if damage == "columns":
        series.drop(columns="value").to_csv(path, index=False)
    elif damage == "runs":
        series[series["seed"] != 2].to_csv(path, index=False)
    else:
        path.write_bytes(b'"\xff\xfe unterminated\n\x00')
    app = typer.Typer()
    app.command()(ap.adaptive_pareto_command)
    result = CliRunner().invoke(app, ["--from-data", "--resamples", "20", "--out", str(tmp_path)])
    assert result.exit_code == 2, result.output
    import re
    assert "adaptive_pareto_series.csv" in re.sub(r"[\s│╭╮╰╯─]+", "", result.output)   # the error box wraps it
    assert not (data / "adaptive_verdict.json").exists()


def test_the_section_and_card_show_every_scene_with_a_verdict(tmp_path):
    """Each scene's files (suffix _<scene> but for growing) give its own plot, table and line on the card."""
    from cloudpbf.report.common import Inputs, Section
    from cloudpbf.studies.adaptive_pareto.report import _adaptive_pareto, adaptive_front_card
    data = tmp_path / "data"
    data.mkdir()
    per_run, per_config = _frame({"cheap-54m": 3, "ok-68m": 3})
    for scene_name in ("growing", "shallow_cumulus"):
        sfx = scene_file_suffix(scene_name)
        verdict = ap.build_verdict(per_run, per_config, scene_name, "test", "abc")
        configs = per_config.copy()
        ap.add_verdict_columns(configs, verdict)
        per_run.assign(device="d", commit="abc").to_csv(data / f"adaptive_pareto{sfx}.csv", index=False)
        configs.to_csv(data / f"adaptive_pareto_configs{sfx}.csv", index=False)
        (data / f"adaptive_verdict{sfx}.json").write_text(json.dumps(verdict))
    sec = Section("adaptive_pareto", "Adaptive")
    _adaptive_pareto(Inputs(tmp_path), sec, None)
    captions = " ".join(str(b.caption or "") for b in sec.blocks if getattr(b, "caption", None))
    assert "growing:" in captions and "shallow_cumulus:" in captions and "cumulus:" not in captions.replace(
        "shallow_cumulus:", "")
    card = adaptive_front_card(Inputs(tmp_path), None, {})
    assert "growing:" in card.answer and "shallow_cumulus:" in card.answer
