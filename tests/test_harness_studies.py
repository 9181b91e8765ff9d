"""Studies: scaling of scenes, error metrics, Pareto front, verdict, largest stable dt, and a study that
reruns only what is missing after an interruption (toy solver, inline execution)."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as st

from cloudpbf import execution, runs
from cloudpbf.pareto import pareto_mask
from cloudpbf.studies import stress, sweep
from cloudpbf.studies.compare import scene_pair
from cloudpbf.studies.context import INLINE, StudyContext, StudyError
from cloudpbf.studies.scales import SCALES, fine_particles, resolve_scale, scale_scene, scale_slab
from pbf_cuda.scene import load_scene
from test_harness_toy import toy_solver  # noqa: F401  (fixture)


# ---- scales ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["growing", "growing_adaptive", "cycling_adaptive"])
def test_scale_scene_hits_the_count_and_keeps_the_heat_flux(name):
    scene = load_scene(name)
    small = scale_scene(scene, 20_000, step_fraction=0.5)
    assert 0.7 < fine_particles(small) / 20_000 < 1.3
    a, b = scene.atmosphere, small.atmosphere
    assert b.heating_rate * b.heating_depth == pytest.approx(a.heating_rate * a.heating_depth)   # eq. 5 flux
    assert b.heating_depth > small.particles.spacing / 2          # the heated layer still holds particles
    assert small.time.steps == scene.time.steps // 2 and small.time.dt == scene.time.dt


def test_fine_particles_counts_adaptive_levels():
    scene = load_scene("growing_adaptive")
    assert fine_particles(scene) == scene.estimated_particles() * 2 ** scene.adaptive.max_level
    # the paper's pairing: a fully refined adaptive run matches the non-adaptive count within 1%
    assert fine_particles(scene) == pytest.approx(load_scene("growing").estimated_particles(), rel=0.01)


def test_scale_slab_keeps_its_layers():
    slab = load_scene("smoothing_slab")
    small = scale_slab(slab, 2000)
    assert small.lattice_shape()[2] == slab.lattice_shape()[2] == 6
    assert 0.8 < small.estimated_particles() / 2000 < 1.25


def test_every_scale_gives_valid_scenes():
    for scale in SCALES.values():
        for name in ("growing", "growing_adaptive", "cycling", "cycling_adaptive"):
            scale_scene(load_scene(name), scale.particles, scale.step_fraction)
        for n in scale.sweep_particles:
            scale_scene(load_scene("growing_adaptive"), n)
        scale_slab(load_scene("smoothing_slab"), scale.slab_particles)


@pytest.mark.parametrize("backends, expected", [(["cpu"], "smoke"), (["cpu", "cuda"], "gpu")])
def test_auto_scale_is_the_minutes_long_demo_without_a_gpu(monkeypatch, backends, expected):
    from pbf_cuda import simulation
    monkeypatch.setattr(simulation, "available_backends", lambda: backends)
    assert resolve_scale("auto").name == expected
    assert resolve_scale("cpu").name == "cpu"                  # the ~50k-particle scale by name only
    with pytest.raises(ValueError, match="allowed auto, smoke, cpu, gpu"):
        resolve_scale("huge")


def test_figure1_slab_runs_all_its_steps_at_every_scale(tmp_path):
    from cloudpbf.studies.renders import slab_specs
    steps = load_scene("smoothing_slab").time.steps
    for scale in SCALES.values():       # the smoke scale's half would end before its clouds form
        ctx = StudyContext(out=tmp_path / "out", scale=scale, runs_root=tmp_path / "runs", scheduler=INLINE)
        unsmoothed, smoothed = slab_specs(ctx)
        assert unsmoothed.scene.time.steps == smoothed.scene.time.steps == steps
        assert unsmoothed.scene.smoothing.kappa == 0.0 < smoothed.scene.smoothing.kappa


def test_smoke_compare_and_sweep_run_in_the_small_box(tmp_path):
    from cloudpbf.studies.compare import compare_specs
    ctx = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", scheduler=INLINE)
    for _, _, spec in compare_specs(ctx, "growing", 5):
        assert tuple(spec.scene.domain.size) == (1200.0, 1600.0, 1200.0)
        if spec.solver == "particles":   # both modes at 100 m (the adaptive twin's level-0 particles too)
            assert spec.scene.particles.spacing == 100.0 and spec.scene.time.dt == 4.0
    plan = sweep.sweep_plan(ctx)
    spacing = [p["value"] for p in plan if p["parameter"] == "spacing"]
    adaptive = [p["value"] for p in plan if p["parameter"] == "adaptive_spacing"]
    assert spacing == adaptive == [110.0, 100.0, 90.0]        # coarse to fine; the finest is the reference
    assert {tuple(p["spec"].scene.domain.size) for p in plan} == {(1200.0, 1600.0, 1200.0)}
    for name in ("cpu", "gpu"):                                 # the other scales keep the scaled 3.2 km domain
        other = StudyContext(out=tmp_path / "out", scale=SCALES[name], runs_root=tmp_path / "runs", scheduler=INLINE)
        assert {tuple(p["spec"].scene.domain.size) for p in sweep.sweep_plan(other)} == {(3200.0, 3200.0, 3200.0)}


def test_scene_pair(tmp_path):
    base, adaptive = scene_pair("cycling")
    assert (base.name, adaptive.name) == ("cycling", "cycling_adaptive")
    path = tmp_path / "wide.toml"
    path.write_text('[scene]\nname = "wide"\nextends = "growing"\n')
    base, adaptive = scene_pair(str(path))                   # no wide_adaptive: switched on here
    assert not base.adaptive.enabled and adaptive.adaptive.enabled
    assert adaptive.particles.spacing == 2 * base.particles.spacing
    with pytest.raises(ValueError, match="cannot make an adaptive twin of 'parcel'.*periodic z axis"):
        scene_pair("parcel")                                  # 300 m thin: doubled spacing does not fit
    with pytest.raises(ValueError, match="compare needs a cloud scene"):
        scene_pair("rest_box")


# ---- sweep metrics ---------------------------------------------------------------------------------
def signature(cover, profile, time=None, z=None):
    time = np.arange(len(cover), dtype=float) if time is None else time
    z = np.arange(len(profile), dtype=float) if z is None else z
    return {"time": time, "cover": np.asarray(cover, float), "z": z, "profile": np.asarray(profile, float)}


def test_errors_are_relative_l2():
    ref = signature([0.0, 0.2, 0.4], [0.0, 0.5, 0.1])
    assert sweep.errors(ref, ref) == (0.0, 0.0, 0.0)
    doubled = signature([0.0, 0.4, 0.8], [0.0, 0.5, 0.1])
    err, e_cover, e_profile = sweep.errors(doubled, ref)
    assert (e_cover, e_profile, err) == pytest.approx((1.0, 0.0, 0.5))
    # a run sampled on other heights is interpolated onto the reference's
    fine = signature([0.0, 0.2, 0.4], [0.0, 0.25, 0.5, 0.3, 0.1], z=np.linspace(0, 2, 5))
    assert sweep.errors(fine, ref)[2] == pytest.approx(0.0)
    assert math.isnan(sweep.errors(ref, signature([0, 0, 0], [0, 0, 0]))[0])   # reference without cloud


def test_pareto_mask():
    wall = np.array([1.0, 2.0, 3.0, 2.5, np.nan])
    error = np.array([0.5, 0.2, 0.1, 0.3, 0.0])
    assert pareto_mask(wall, error).tolist() == [True, True, True, False, False]


def test_verdict_interpolates_wall_time_at_equal_error():
    rows = [dict(parameter="spacing", value=3.0, particles=1000, wall_s=2.0, error_self=0.3, stable=True),
            dict(parameter="spacing", value=2.0, particles=3000, wall_s=10.0, error_self=0.1, stable=True),
            dict(parameter="adaptive_spacing", value=4.0, particles=900, wall_s=3.0, error_self=0.2, stable=True)]
    out = sweep.verdict(pd.DataFrame(rows))
    (cmp,) = out["comparisons"]
    assert cmp["wall_non_adaptive_s"] == pytest.approx(6.0) and cmp["speedup"] == pytest.approx(2.0)
    # one comparison is one wall-clock ratio: no interval, so no difference is claimed
    assert out["verdict"].startswith("no difference measured: one comparison at equal error (2.00x")
    assert out["speedup_interval"] is None and out["no_difference"]


def test_sweep_speedups_need_an_interval_that_excludes_one():
    noisy = sweep.speedup_summary([2.00, 0.82, 0.98])                      # the demo's three single ratios
    assert noisy["no_difference"] and noisy["verdict"].startswith("no difference measured: at equal error")
    lo, hi = noisy["speedup_interval"]
    assert lo < 1 < hi and noisy["speedup"] == pytest.approx((2.0 * 0.82 * 0.98) ** (1 / 3))
    clear = sweep.speedup_summary([1.9, 2.0, 2.1, 2.05])
    assert not clear["no_difference"] and clear["speedup_interval"][0] > 1
    assert clear["verdict"].startswith("at equal error, adaptive runs are 2.01x faster than non-adaptive runs")
    slower = sweep.speedup_summary([0.5, 0.52, 0.49])
    assert "x slower" in slower["verdict"] and not slower["no_difference"]


def test_largest_stable_dt_stops_at_the_first_failure():
    frame = pd.DataFrame({"parameter": ["dt"] * 5 + ["iterations"],
                          "value": [1.0, 2.0, 4.0, 8.0, 16.0, 1.0],
                          "stable": [True, True, False, True, False, False]})
    out = stress.largest_stable_dt(frame)
    assert out["largest_stable_dt"] == 2.0 and out["smallest_unstable_dt"] == 4.0


# ---- a study interrupted, then resumed ---------------------------------------------------------------
TINY = dataclasses.replace(SCALES["smoke"], stress_particles=3000, stress_steps=6,
                           stress_dt=(1.0, 2.0, 150.0), stress_iterations=(1, 2), stress_alpha_dt=(1.0,),
                           stress_map_dt=())


def test_interrupted_study_reruns_only_what_is_missing(toy_solver, tmp_path, monkeypatch):
    real_execute = execution.execute
    calls = []

    def execute(spec, root=None, **kw):
        calls.append(spec.key())
        if len(calls) == 4:
            raise RuntimeError("worker lost")          # the 4th run dies, the study goes on
        return real_execute(spec, root, **kw)

    monkeypatch.setattr(execution, "execute", execute)     # what the inline workers call
    ctx = StudyContext(out=tmp_path / "out", scale=TINY, runs_root=tmp_path / "runs", scheduler=INLINE, quiet=True)
    # 11 cases (3 dt, 2 iterations, 5 heating rates, 1 alpha*dt), 10 distinct runs: dt = 2 s and heating x1
    # are both the base scene
    with pytest.raises(StudyError, match="1 of 10 runs failed"):
        stress.run_stress(ctx)
    assert len(calls) == 10 and not (ctx.data / "stress.csv").exists()
    first_steps = toy_solver.steps_taken
    calls.clear()
    frame = stress.run_stress(ctx)                     # the rerun: only the lost run
    assert len(calls) == 1
    assert toy_solver.steps_taken - first_steps <= 6
    assert len(frame) == 11
    dt = frame[frame.parameter == "dt"].set_index("value")
    assert dt.loc[150.0, "stable"] == False and "velocity" in dt.loc[150.0, "reason"]   # noqa: E712
    assert dt.loc[150.0, "step"] < 6 and dt.loc[150.0, "particles"]
    assert dt.loc[1.0, "stable"] and dt.loc[1.0, "step"] == 6
    summary = json.loads((ctx.data / "stress_summary.json").read_text())
    assert summary["largest_stable_dt"] == 2.0 and summary["smallest_unstable_dt"] == 150.0
    calls.clear()
    again = stress.run_stress(ctx)                     # all cached: nothing runs, same table
    assert calls == []
    pd.testing.assert_frame_equal(again, frame)


def test_stress_cases_change_one_parameter_each():
    base = scale_scene(load_scene("growing"), 3000)
    cases = stress.stress_cases(base, SCALES["smoke"])
    for parameter, value, scene in cases:
        if parameter == "alpha_dt":
            assert scene.atmosphere.phase_rate * scene.time.dt == pytest.approx(value)
            assert scene.atmosphere.initial_vapor_ratio == stress.SUPERSATURATION
        elif parameter == "dt":
            assert scene.time.dt == value and scene.pbf == base.pbf
        elif parameter == "heating_rate":
            assert scene.atmosphere.heating_rate == value <= stress.MAX_HEATING_RATE
    heating = [v for p, v, _ in cases if p == "heating_rate"]
    assert heating == sorted(set(heating)) and heating[0] == base.atmosphere.heating_rate


def test_stress_maps_vary_dt_and_one_other_parameter():
    base = scale_scene(load_scene("growing"), 3000)
    scale = SCALES["smoke"]
    cases = [(p, v, sc) for p, v, sc in stress.stress_cases(base, scale) if p.startswith("dt x ")]
    per_dt = len(scale.stress_iterations) + len(stress.MAP_HEATING_FACTORS)
    assert len(cases) == len(scale.stress_map_dt) * per_dt
    for parameter, value, scene in cases:
        assert scene.time.dt == value
        if parameter == "dt x iterations":
            assert scene.atmosphere == base.atmosphere and scene.pbf.iterations in scale.stress_iterations
        else:
            assert scene.pbf == base.pbf
            factor = scene.atmosphere.heating_rate / base.atmosphere.heating_rate
            assert min(abs(factor - f) for f in stress.MAP_HEATING_FACTORS) < 1e-9


def test_usable_is_stable_and_accurate():
    frame = pd.DataFrame({"parameter": "dt", "value": [1.0, 2.0, 4.0, 8.0, 16.0],
                          "stable": [True, True, True, True, False],
                          "density_error_mean": [0.001, 0.002, 0.004, 0.5, 0.9],
                          "density_error_max": [0.002, 0.009, 0.02, 0.6, None],
                          "energy_jump": [1.0, 1.1, 1.2, 1.3, 9.0],
                          "reference_error": [0.01, 0.05, 0.02, 0.04, 0.0]})
    usable = stress.usable_mask(frame)
    assert usable.tolist() == [True, True, False, False, False]   # 4 s: its worst step exceeds 1%
    jumpy = frame.assign(energy_jump=[1.0, 3.0, 1.0, 1.0, 1.0])
    assert stress.usable_mask(jumpy).tolist() == [True, False, False, False, False]
    # density error alone does not make a case usable: it needs the converged reference's agreement
    far = frame.assign(reference_error=[0.01, 0.5, 0.02, 0.04, 0.0])
    assert stress.usable_mask(far).tolist() == [True, False, False, False, False]
    assert not stress.usable_mask(frame.drop(columns="reference_error")).any()
    assert stress.usable_mask(frame.drop(columns="reference_error"), reference_limit=None).tolist()[:2] == [True, True]
    # a row marked unstable is never usable, whatever its other columns say
    assert not stress.usable_mask(frame.assign(stable=False)).any()
    out = stress.largest_stable_dt(frame.assign(usable=usable))
    assert (out["largest_usable_dt"], out["smallest_unusable_dt"]) == (2.0, 4.0)
    assert (out["largest_stable_dt"], out["smallest_unstable_dt"]) == (8.0, 16.0)


def test_dask_workers_run_missing_specs_and_cached_ones_stay_home(tmp_path):
    pytest.importorskip("pbf_cuda._core", reason="the particle solver is not built")
    scene = scale_scene(load_scene("growing"), 3000).replace(**{"time.steps": 4, "time.snapshot_every": 2})
    specs = [runs.RunSpec("particles", scene, backend="cpu", seed=s) for s in (0, 1, 0)]   # one duplicate
    ctx = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", workers=2, quiet=True)
    with ctx:
        results = ctx.run_parallel(specs, "test")
        env = ctx.client().run(lambda: __import__("os").environ.get("OMP_NUM_THREADS"))
    cores = __import__("os").cpu_count() or 1
    assert set(env.values()) == {str(max(1, cores // 2))}  # the cores shared out, no oversubscription
    assert [r.seed for r in results] == [0, 1, 0] and results[0].path == results[2].path
    assert all(r.stable and r.step == 4 for r in results)
    assert len(list((tmp_path / "runs").iterdir())) == 2
    again = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", quiet=True)
    assert [r.path for r in again.run_parallel(specs, "test")] == [r.path for r in results]
    assert again._client is None                          # everything cached: no cluster started


def test_table1_row_is_ms_per_step_without_double_counting():
    from types import SimpleNamespace
    from cloudpbf.studies.table1 import ROWS, TABLE1_COLUMNS, table1_row
    timings = {"pbf": {"total_ms": 100.0, "count": 10}, "neighbors": {"total_ms": 30.0, "count": 10},
               "solver": {"total_ms": 60.0, "count": 10}, "smoothing": {"total_ms": 20.0, "count": 10},
               "cloud_dynamics": {"total_ms": 4.0, "count": 10}, "splitting": {"total_ms": 5.0, "count": 2}}
    steps = pd.DataFrame({"mass_centre_height": [1600.0, 1601.0, 1602.5], "density_excess_mean": [0.0, 0.01, 0.002],
                          "density_deficit_mean": [0.0, 0.02, 0.004]})
    result = SimpleNamespace(timings=lambda: timings, max_particles=1234, device="dev", backend="cpu", stable=True,
                             reason=None, path="runs/x", steps_table=lambda: steps)
    spec = SimpleNamespace(total_steps=12, scene=load_scene("growing_adaptive"))
    ctx = SimpleNamespace(commit="abc", scale=SCALES["smoke"])
    example, figure, mode, name = ROWS[1]
    row = table1_row((example, figure, mode, "", load_scene(name)), spec, result, ctx)
    # the timing's accuracy: the mass centre's rise over the run and the final density excess / deficit
    assert (row["mass_centre_rise_m"], row["density_excess_mean"], row["density_deficit_mean"]) == (2.5, 0.002, 0.004)
    assert list(row)[:len(TABLE1_COLUMNS)] == list(TABLE1_COLUMNS)
    assert (row["pbf_ms"], row["smoothing_ms"], row["cloud_dynamics_ms"]) == (10.0, 2.0, 0.4)
    assert row["splitting_ms"] == 0.5 and row["merging_ms"] is None      # split on 2 of 10 steps; no merge timer
    assert row["total_ms"] == pytest.approx(12.9)                        # neighbors, solver are inside pbf
    assert (row["example"], row["figure"], row["mode"], row["variant"], row["max_particles"]) == \
        ("growing", "5b", "adaptive", "", 1234)
    paper_total = 628.78 + 64.55 + 12.50 + 6.10 + 23.71                  # the paper's row 5b
    assert row["paper_total_ms"] == pytest.approx(paper_total) and row["paper_max_particles"] == 540000
    # below the gpu scale (and at 1,234 particles against the paper's 540,000) no speed-up: throughput
    assert row["speedup_vs_paper"] is None and row["particle_steps_per_s"] == pytest.approx(1234 * 1e3 / 12.9)
    gpu = SimpleNamespace(commit="abc", scale=SCALES["gpu"])
    assert table1_row((example, figure, mode, "", load_scene(name)), spec, result, gpu)["speedup_vs_paper"] is None
    matched = SimpleNamespace(**{**vars(result), "max_particles": 500_000})
    row = table1_row((example, figure, mode, "", load_scene(name)), spec, matched, gpu)
    assert row["speedup_vs_paper"] == pytest.approx(paper_total / 12.9)           # 500k against 540k: within 20%
    assert np.isnan(row["step_ms_median"])                                         # no per-step times recorded
    timed = pd.DataFrame({"step": range(1, 13), "wall_ms": [50.0] * 2 + [10.0] * 9 + [30.0]})
    row = table1_row((example, figure, mode, "", load_scene(name)), SimpleNamespace(**{**vars(spec), "warmup_steps": 2}),
                     SimpleNamespace(**{**vars(result), "steps_table": lambda: timed}), ctx)
    assert row["step_ms_median"] == 10.0 and row["timed_steps"] == 10 and row["step_ms_p95"] > 10.0


@pytest.mark.parametrize("best, expected", [
    (None, None),                                                                        # no verdict file
    ({"best": None}, None),                                                              # no variant qualified
    ({"best": {"name": "paper-68m", "criterion": "paper", "spacing_m": 68.0}}, None),    # the 5b row's own setting
    ({"best": {"name": "thermal-68m", "criterion": "thermal", "spacing_m": 68.0}},            # older verdicts
     ("thermal-68m", {"adaptive.criterion": "thermal", "adaptive.max_level": 3, "particles.spacing": 68.0})),
    ({"best": {"name": "lookahead-54m", "criterion": "lookahead", "spacing_m": 54.0, "max_level": 3}},
     ("lookahead-54m", {"adaptive.criterion": "lookahead", "adaptive.max_level": 3, "particles.spacing": 54.0})),
    ({"best": {"name": "thermal-68m-L4-t0.25", "criterion": "thermal", "spacing_m": 68.0, "max_level": 4,
               "threshold_scale": 0.25}},
     ("thermal-68m-L4-t0.25", {"adaptive.criterion": "thermal", "adaptive.max_level": 4,
                               "adaptive.split_threshold": 0.075, "adaptive.merge_threshold": 0.0125,
                               "particles.spacing": 68.0})),
    ({"best": {"name": "thermal-68m-L4-t0.25-e4", "criterion": "thermal", "spacing_m": 68.0, "max_level": 4,
               "threshold_scale": 0.25, "adapt_every": 4}},
     ("thermal-68m-L4-t0.25-e4", {"adaptive.criterion": "thermal", "adaptive.max_level": 4,
                                  "adaptive.split_threshold": 0.075, "adaptive.merge_threshold": 0.0125,
                                  "adaptive.every": 4, "particles.spacing": 68.0})),
])
def test_table1_adds_the_best_adaptive_variant_beside_the_paper_rows(tmp_path, best, expected):
    """Table 1 keeps the paper's four rows and, when the growing study's verdict names a best variant other
    than growing_adaptive's own setting, times it in a fifth row (its spacing only at the GPU scale)."""
    from types import SimpleNamespace
    from cloudpbf.studies.table1 import best_variant, table1_rows
    if best is not None:
        (tmp_path / "adaptive_verdict.json").write_text(json.dumps(best))
    ctx = SimpleNamespace(data=tmp_path, scale=SCALES["gpu"])
    assert best_variant(ctx) == expected
    rows = table1_rows(ctx)
    assert [r[:4] for r in rows[:4]] == [("growing", "5a", "non-adaptive", ""), ("growing", "5b", "adaptive", ""),
                                         ("cycling", "5c", "non-adaptive", ""), ("cycling", "5d", "adaptive", "")]
    if expected is None:
        assert len(rows) == 4
    else:
        assert len(rows) == 5 and rows[4][:4] == ("growing", "5b", "adaptive", expected[0])
        assert rows[4][4].adaptive.criterion == expected[1]["adaptive.criterion"]
        assert rows[4][4].adaptive.max_level == expected[1]["adaptive.max_level"]
        assert rows[4][4].particles.spacing == expected[1]["particles.spacing"]
        smoke = SimpleNamespace(data=tmp_path, scale=SCALES["smoke"])   # below the GPU scale: all but the spacing
        assert best_variant(smoke)[1] == {k: v for k, v in expected[1].items() if k != "particles.spacing"}


def test_adaptive_cost_rows_are_per_step_and_consistent(tmp_path):
    pytest.importorskip("pbf_cuda._core", reason="the particle solver is not built")
    from cloudpbf.studies.adaptive_cost import adaptive_cost
    frame = adaptive_cost(["growing_adaptive"], spacing=200.0, steps=12, backend="cpu", runs_root=tmp_path,
                          quiet=True)
    row = frame.iloc[0]
    assert row["stable"] and row["backend"] == "cpu"
    assert row["max_particles"] >= row["mean_particles"] > 1000
    parts = [row[f"{p}_ms"] for p in ("pbf", "smoothing", "cloud_dynamics", "splitting", "merging")]
    assert row["total_ms"] == pytest.approx(sum(parts))
    assert 0 < row["merge_passes_ms"] + row["compaction_ms"] <= row["merging_ms"]
    assert row["split_vs_pbf"] == pytest.approx(row["splitting_ms"] / row["pbf_ms"])
    assert pd.isna(row["meets_targets"])               # targets are for ~500k particles on the GPU
    again = adaptive_cost(["growing_adaptive"], spacing=200.0, steps=12, backend="cpu", runs_root=tmp_path,
                          quiet=True)
    assert again.iloc[0]["run_dir"] == row["run_dir"] and again.iloc[0]["splitting_ms"] == row["splitting_ms"]


def test_cover_summary_finds_onset_and_a_vanish_and_return():
    from cloudpbf.studies.constant_gravity import cover_summary
    t = np.arange(8) * 10.0
    steady = cover_summary(pd.DataFrame({"time_s": t, "cloud_cover": [0, 0, .1, .3, .4, .4, .5, .5]}))
    assert steady == {"first_cloud_s": 20.0, "max_cover": 0.5, "final_cover": 0.5, "vanished_and_returned": False}
    cycle = cover_summary(pd.DataFrame({"time_s": t, "cloud_cover": [0, .2, .3, 0, 0, .1, .2, 0]}))
    assert cycle["first_cloud_s"] == 10.0 and cycle["vanished_and_returned"]
    gone = cover_summary(pd.DataFrame({"time_s": t, "cloud_cover": [0, .2, .3, 0, 0, 0, 0, 0]}))
    assert not gone["vanished_and_returned"] and gone["final_cover"] == 0
    never = cover_summary(pd.DataFrame({"time_s": t, "cloud_cover": np.zeros(8)}))
    assert never["first_cloud_s"] is None and never["max_cover"] == 0


def test_particles_vs_grid_means_over_the_cloudy_period_of_both():
    """Time means of the seed means, only at times where both solvers' mean cover is above 1%; the grid's
    times matched to the particles' nearest; rel_diff = (particles - grid) / grid."""
    import pandas as pd
    from cloudpbf.studies.compare import particles_vs_grid
    rows = []
    t = np.arange(0.0, 1001.0, 100.0)
    for mode, base, cover in (("non-adaptive", 600.0, np.where(t >= 300, 0.5, 0.0)),
                              ("grid", 800.0, np.where(t >= 400, 0.4, 0.0)),
                              ("adaptive", 50.0, np.full_like(t, 0.9))):
        for seed, shift in ((0, -10.0), (1, 10.0)):
            for ti, c in zip(t, cover):
                rows.append({"mode": mode, "seed": seed, "time_s": ti + (1.0 if mode == "grid" else 0.0),
                             "cloud_base": base + shift + ti / 10, "cloud_top": 2 * base, "cloud_cover": c,
                             "lwp_mean": 0.1 * c, "device": "test", "commit": "abc"})
    out = particles_vs_grid(pd.DataFrame(rows)).set_index("metric")
    cloudy = t[t >= 400]
    assert out.loc["cloud_base", "particles"] == pytest.approx(600.0 + cloudy.mean() / 10)
    assert out.loc["cloud_base", "grid"] == pytest.approx(800.0 + cloudy.mean() / 10)
    assert out.loc["cover", "rel_diff"] == pytest.approx(0.25)
    assert out.loc["cloud_top", "rel_diff"] == pytest.approx(-0.25)
    assert (out["cloudy_from_s"] == 400.0).all() and (out["times"] == len(cloudy)).all()
    assert particles_vs_grid(pd.DataFrame(rows).query("mode != 'grid'")).empty


def test_mixed_layer_lcl_is_the_lcl_of_the_mean_air_below_half_the_cloud_base():
    """Layers below half the seed-mean cloud base are averaged (dry static temperature T + Gamma_d z and total
    water) and lifted to saturation; layers above do not count, and a time without cloud has no LCL."""
    import pandas as pd
    from cloudpbf.studies.compare import mixed_layer_lcl, particles_vs_grid
    scene = load_scene("growing")
    a = scene.atmosphere
    z = np.arange(25.0, 3200.0, 50.0)
    t_s, q = 301.0, 0.015                                   # well mixed below; anything else above
    rows, series = [], []
    for mode in ("non-adaptive", "grid"):
        for seed, wiggle in ((0, -0.2), (1, 0.2)):          # seed means cancel the wiggle
            for time_s, base in ((200.0, float("nan")), (400.0, 900.0), (600.0, 1200.0)):
                for zk in z:
                    mixed = zk < 0.5 * base
                    rows.append({"mode": mode, "seed": seed, "time_s": time_s, "z": zk,
                                 "temperature": (t_s + wiggle if mixed else 250.0) - a.dry_lapse_rate * zk,
                                 "vapor": (q - 0.001 if mixed else 0.03), "cloud": (0.001 if mixed else 0.0)})
                series.append({"mode": mode, "seed": seed, "time_s": time_s, "cloud_base": base,
                               "cloud_top": 2000.0, "cloud_cover": 0.0 if base != base else 0.5, "lwp_mean": 0.1})
    profiles, series = pd.DataFrame(rows), pd.DataFrame(series)
    lcl = mixed_layer_lcl(profiles, series, "grid", scene)
    expected = float(scene.lifting_condensation_level(t_s, q))
    assert np.isnan(lcl[200.0]) and lcl[400.0] == pytest.approx(expected) and lcl[600.0] == pytest.approx(expected)
    out = particles_vs_grid(series, profiles=profiles, scene=scene).set_index("metric")
    assert out.loc["mixed_layer_lcl", "particles"] == pytest.approx(expected)
    assert out.loc["mixed_layer_lcl", "rel_diff"] == pytest.approx(0.0, abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(t_s=st.floats(270.0, 320.0), rh=st.floats(0.05, 0.99))
def test_lifting_condensation_level_saturates_the_lifted_air(t_s, rh):
    """Closed form: air of dry static temperature T_s and total water q = rh s(T_s) lifted dry-adiabatically to
    the LCL is exactly saturated there (eq. 10), and it lies above the ground for unsaturated air."""
    scene = load_scene("growing")
    a = scene.atmosphere
    q = rh * float(scene.saturation(t_s))
    z = float(scene.lifting_condensation_level(t_s, q))
    assert z > 0.0
    assert float(scene.saturation(t_s - a.dry_lapse_rate * z)) == pytest.approx(q, rel=1e-9)


def test_sweep_cloud_means_and_the_convergence_plot():
    """cloud_means averages only the cloudy snapshots (cover > 1%); the convergence plot draws the resolution
    runs of both methods, and is left out for a sweep.csv without the statistics."""
    import pandas as pd
    from types import SimpleNamespace
    from cloudpbf.report import plots
    from cloudpbf.studies.sweep import cloud_means
    stats = pd.DataFrame({"cloud_cover": [0.0, 0.005, 0.2, 0.4], "lwp_mean": [0.0, 1.0, 0.1, 0.3],
                          "cloud_base": [np.nan, 500.0, 600.0, 800.0], "cloud_top": [np.nan, 900.0, 1000.0, 1400.0]})
    means = cloud_means(SimpleNamespace(stable=True, stats=lambda: stats))
    assert means == pytest.approx({"cover_mean": 0.3, "lwp_mean": 0.2, "cloud_base_mean": 700.0,
                                   "cloud_top_mean": 1200.0})
    assert all(math.isnan(v) for v in cloud_means(SimpleNamespace(stable=False, stats=lambda: stats)).values())
    sweep = pd.DataFrame({"method": ["particles"] * 3 + ["grid"] * 3, "parameter": ["spacing"] * 3 + ["cells"] * 3,
                          "resolution_m": [100.0, 70.0, 50.0, 100.0, 66.0, 50.0],
                          "cover_mean": [0.3, 0.35, 0.37, 0.5, 0.45, 0.41], "lwp_mean": [0.1] * 6,
                          "cloud_base_mean": [600.0] * 6, "cloud_top_mean": [1500.0] * 6})
    assert plots.convergence_plot(sweep).startswith("data:image/png;base64,")
    assert plots.convergence_plot(sweep.drop(columns=["resolution_m"])) is None


def test_studies_run_inline_without_dask_and_say_so(tmp_path, monkeypatch):
    """Without dask's distributed a study runs its specs in this process (and says so) unless a cluster was
    asked for; an asked-for cluster is refused with the missing package named, at exit code 2 on the CLI."""
    pytest.importorskip("pbf_cuda._core", reason="the particle solver is not built")
    from cloudpbf.cli_common import refusals
    from cloudpbf.studies import context as context_module
    from cloudpbf.studies.context import SchedulerError
    monkeypatch.setattr(context_module, "has_distributed", lambda: False)
    scene = scale_scene(load_scene("growing"), 3000).replace(**{"time.steps": 2, "time.snapshot_every": 2})
    ctx = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", quiet=True)
    assert ctx.runs_inline() and "distributed is not installed" in ctx.cluster_description()
    result, = ctx.run_parallel([runs.RunSpec("particles", scene, backend="cpu", seed=0)], "test")
    assert result.stable and result.step == 2 and ctx._client is None
    asked = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", quiet=True,
                         scheduler="tcp://127.0.0.1:8786")
    assert not asked.runs_inline()
    with pytest.raises(SchedulerError, match="distributed"):
        asked.client()
    import click
    with pytest.raises(click.exceptions.BadParameter, match="pip install distributed"):
        with refusals():
            asked.client()


def test_stress_reference_is_the_same_scene_converged_and_catches_a_collapse():
    base = scale_scene(load_scene("growing"), 3000).replace(**{"time.steps": 10, "time.snapshot_every": 10})
    specs = [runs.RunSpec("particles", base.replace(**{"time.dt": 8.0, "pbf.iterations": it}), seed=0,
                          record_steps=True, diagnostics=False, keep_snapshots=0) for it in (1, 4)]
    refs = [stress.reference_spec(spec) for spec in specs]
    assert refs[0].key() == refs[1].key()                        # cases differing in iterations share a reference
    ref = refs[0].scene
    assert ref.time.dt == 8.0 / stress.REFERENCE_DT_DIVISOR and ref.pbf.iterations == stress.REFERENCE_ITERATIONS
    assert ref.time.dt * ref.time.steps == 8.0 * 10                 # the same simulated time
    reference = pd.DataFrame({"mass_centre_height": [800.0, 801.0], "mean_temperature": [290.0, 291.0]})
    close = pd.DataFrame({"mass_centre_height": [801.0, 805.0], "mean_temperature": [290.0, 291.05]})
    collapsed = pd.DataFrame({"mass_centre_height": [10.0, 0.0], "mean_temperature": [290.0, 291.0]})
    assert stress.reference_error(close, reference, 100.0) == pytest.approx(0.05)   # 4 m of 100 m; 0.05 K of 1 K
    assert stress.reference_error(collapsed, reference, 100.0) > 1.0             # the mass centre fell 8 spacings
    assert np.isnan(stress.reference_error(close.iloc[:0], reference, 100.0))
