"""The time-to-solution study: its plan, its analysis on synthetic runs whose answers are known (errors, the
front, the cheapest setting at a budget, the speed-up and its interval), and one tiny real run at smoke scale."""
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from cloudpbf.studies import time_to_solution as tts
from cloudpbf.studies.scales import SCALES

TIMES = np.array([100.0, 200.0, 300.0, 400.0])
REF = {"cover": np.array([0.1, 0.2, 0.3, 0.4]), "volume": np.array([1e8, 3e8, 5e8, 7e8]),
       "lwp": np.array([0.05, 0.1, 0.2, 0.3])}


def synthetic(specs: dict, seeds: int = 8, noise: float = 0.0, unstable=()):
    """(per_run, series, meta) of settings {name: (group, default, relative offset a, wall s per sim s)}: every
    series of a setting is the reference's times (1 + a) (relative L2 error exactly |a|), plus seed noise
    (+-noise, symmetric over the seeds: it cancels in the seed mean); `unstable`: (name, seed) pairs that blew up."""
    runs, series, meta = [], [], []
    for name, (group, default, a, cost) in specs.items():
        meta.append({"setting": name, "group": group, "default": default, "spacing_m": 1.0, "dt": 1.0, "cfl": 0.0,
                     "iterations": 0, "divergence_iterations": 0, "adaptive": False})
        for seed in range(seeds):
            ok = (name, seed) not in unstable
            runs.append({"setting": name, "seed": seed, "complete": ok, "wall_per_sim_s": cost * (1 + 0.01 * (seed % 2))
                         if ok else math.nan})
            if ok:
                shift = noise * (1 if seed % 2 else -1)
                for j, t in enumerate(TIMES):
                    series.append({"setting": name, "seed": seed, "time_s": t,
                                   **{k: v[j] * (1 + a + shift) for k, v in REF.items()}})
    return pd.DataFrame(runs), pd.DataFrame(series), pd.DataFrame(meta)


SPECS = {"ref": ("reference", False, 0.0, 50.0), "default": ("grid", True, 0.20, 4.0),
         "fine": ("grid", False, 0.05, 10.0), "cheap_ok": ("cfl", False, 0.18, 1.5),
         "cheap_bad": ("grid", False, 0.60, 0.5), "dominated": ("iterations", False, 0.30, 6.0),
         "mid": ("grid", False, 0.09, 3.0)}


def test_cheapest_picks_the_least_cost_within_the_budget():
    error, cost = np.array([0.2, 0.1, 0.3, 0.1]), np.array([2.0, 5.0, 1.0, 5.0])
    ok = np.array([True, True, True, True])
    assert tts.cheapest(error, cost, ok, 0.2) == 0
    assert tts.cheapest(error, cost, ok, 0.15) == 1            # ties in cost: the first of equal error
    assert tts.cheapest(error, cost, ok, 0.05) is None
    assert tts.cheapest(error, cost, np.array([False, True, True, True]), 0.25) == 1


def test_errors_cost_front_budgets_and_speedup_on_known_answers():
    per_run, series, meta = synthetic(SPECS, noise=0.02)
    frame, verdict = tts.analyse(per_run, series, meta, {"scene": "growing"}, replicates=200)
    by = frame.set_index("setting")
    for name, (_, _, a, _) in SPECS.items():
        assert by.loc[name, "error"] == pytest.approx(abs(a), abs=1e-12)     # seed noise cancels in the mean
    assert by.loc["cheap_ok", "wall_per_sim_s"] == pytest.approx(1.5 * 1.005)
    assert set(by.index[by["front"]]) == {"cheap_bad", "cheap_ok", "mid", "fine"}
    assert not by.loc["ref", "qualified"] and not by.loc["ref", "front"]
    budgets = {b["budget"]: b for b in verdict["budgets"]}
    assert budgets["default"]["cheapest"]["setting"] == "cheap_ok"
    assert budgets["half"]["cheapest"]["setting"] == "mid"                  # 0.09 <= 0.10, cheaper than "fine"
    assert budgets["double"]["cheapest"]["setting"] == "cheap_ok"           # 0.6 > 0.4: cheap_bad stays out
    assert verdict["speedup_at_default_error"] == pytest.approx(4.0 / 1.5)
    lo, hi = verdict["speedup_interval"]
    assert lo <= verdict["speedup_at_default_error"] <= hi
    assert verdict["p_speedup_at_least_goal"] == pytest.approx(1.0)
    assert by.loc["cheap_ok", "cheapest_share"] == pytest.approx(1.0)
    assert by.loc["default", "error_p05"] <= 0.2 <= by.loc["default", "error_p95"]
    assert [f["setting"] for f in verdict["front"]] == ["cheap_bad", "cheap_ok", "mid", "fine"]
    assert "cheap_ok" in verdict["verdict"] and "2.67x" in verdict["verdict"]
    json.dumps(verdict)                                                      # no NaN, no numpy types


def test_interval_widens_with_seed_noise_and_holds_the_estimate():
    quiet = tts.analyse(*synthetic(SPECS, noise=0.0), {"scene": "growing"}, replicates=200)[0]
    noisy = tts.analyse(*synthetic(SPECS, noise=0.1), {"scene": "growing"}, replicates=200)[0]
    width = lambda f: float((f["error_p95"] - f["error_p05"]).set_axis(f["setting"])["default"])  # noqa: E731
    assert width(quiet) == pytest.approx(0.0, abs=1e-12)
    assert width(noisy) > 0.01
    assert noisy.set_index("setting").loc["default", "error_seed_spread"] > 0


def test_a_setting_unstable_in_one_seed_is_left_out_of_the_verdict():
    per_run, series, meta = synthetic(SPECS, unstable={("cheap_ok", 3)})
    frame, verdict = tts.analyse(per_run, series, meta, {"scene": "growing"}, replicates=50)
    by = frame.set_index("setting")
    assert by.loc["cheap_ok", "stable_seeds"] == 7 and not by.loc["cheap_ok", "qualified"]
    assert {"setting": "cheap_ok", "stable_seeds": 7, "seeds": 8} in verdict["excluded"]
    assert verdict["budgets"][0]["cheapest"]["setting"] == "mid"
    assert verdict["speedup_at_default_error"] == pytest.approx(4.0 / 3.0)


def test_defaults_unstable_in_a_seed_give_no_verdict():
    per_run, series, meta = synthetic(SPECS, unstable={("default", 5)})
    frame, verdict = tts.analyse(per_run, series, meta, {"scene": "growing"}, replicates=20)
    assert verdict["speedup_at_default_error"] is None and verdict["speedup_interval"] is None
    assert "stable in 7 of 8 seeds" in verdict["verdict"]


def test_no_measurable_error_gives_no_verdict_rather_than_a_number():
    specs = {"ref": ("reference", False, 0.0, 5.0), "default": ("grid", True, 0.1, 1.0)}
    per_run, series, meta = synthetic(specs, seeds=2)
    series[["cover", "volume", "lwp"]] = 0.0                                # no cloud anywhere: no relative error
    frame, verdict = tts.analyse(per_run, series, meta, {"scene": "growing"}, replicates=20)
    assert verdict["speedup_at_default_error"] is None and "no verdict" in verdict["verdict"]
    json.dumps(verdict)


@pytest.mark.parametrize("paper", [False, True], ids=["smoke-scale", "paper-scale"])
def test_plan_has_one_default_a_separate_reference_and_equal_end_times(paper):
    ctx = SimpleNamespace(scale=SCALES["gpu" if paper else "smoke"], backend="cpu")
    study, entries, sizes, base = tts.plan(ctx, "growing", 2)
    assert sum(s.default for s in study) == 1 and sum(s.group == "reference" for s in study) == 1
    names = [s.name for s in study]
    assert len(names) == len(set(names)) and len(entries) == 2 * len(study)
    default = next(s for s in study if s.default)
    assert default.spacing_m == base.particles.spacing and default.dt == base.time.dt
    ref = next(s for s in study if s.group == "reference")
    assert ref.dt == min(s.dt for s in study) and ref.spacing_m == min(s.spacing_m for s in study)
    assert {e[2].end_time for e in entries} == {tts.end_time(base, sizes)}
    for setting, _, spec in entries:
        if setting.cfl:
            assert spec.scene.time.cfl == setting.cfl and spec.total_steps * spec.scene.time.dt_min >= spec.end_time
        else:
            assert spec.total_steps * setting.dt == pytest.approx(spec.end_time)
    if paper:
        assert default.spacing_m == 34.0 and default.dt == 2.0
        assert {round(s.spacing_m) for s in study} == {68, 54, 43, 34}
        assert any(s.adaptive for s in study) and any(s.cfl for s in study)
        est = tts.estimate(entries, sizes, base)
        assert est["runs"] == len(entries) and est["gpu_s_estimate"] > 0


def test_a_tiny_real_run_writes_the_outputs_and_the_report_section(tmp_path):
    from cloudpbf.studies.context import INLINE, StudyContext
    sizes = tts.Sizes(spacing_ratios=(1.0,), dts=(16.0,), grid_cfls=(), cfls=(0.5,), iterations=(), dt_max=16.0,
                      divergence_iterations=(), adaptive=False, reference_dt=8.0, default_dt=16.0, end_time=64.0,
                      times=2, box=tts.SMOKE_BOX, spacing=200.0, analysis_grid=(8, 8, 8))
    ctx = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", backend="cpu",
                       scheduler=INLINE, quiet=True)
    result = tts.run_time_to_solution(ctx, "growing", seeds=2, replicates=20, sizes=sizes)
    runs = result["runs"]
    assert len(runs) == 6 and runs["complete"].all()
    assert runs["time_s"].ge(64.0).all() and runs["time_s"].lt(64.0 + 16.0).all()   # the first step past the end
    fixed = runs[runs["setting"] == "200m-dt16"]
    assert fixed["steps"].eq(4).all() and fixed["time_s"].eq(64.0).all()
    assert (runs.loc[runs["complete"], "wall_per_sim_s"] > 0).all()
    for run in runs[runs["setting"] == "200m-cfl0.5"].itertuples():   # rows bracket each analysis time
        rows = pd.read_parquet(Path(run.run_dir) / "stats.parquet")
        t, dt = rows["time_s"].to_numpy(), rows["dt"].to_numpy()
        for tk in (32.0, 64.0):
            after = np.flatnonzero(t >= tk - 1e-6)[0]
            assert after > 0 and t[after - 1] < tk <= t[after] and t[after] - t[after - 1] == pytest.approx(dt[after - 1])
    data = ctx.data
    for name in ("time_to_solution.csv", "time_to_solution_runs.csv", "time_to_solution_series.csv",
                 "time_to_solution_verdict.json"):
        assert (data / name).is_file()
    settings = pd.read_csv(data / "time_to_solution.csv")
    assert {"device", "commit", "error", "wall_per_sim_s", "front"} <= set(settings.columns)
    verdict = json.loads((data / "time_to_solution_verdict.json").read_text())
    assert verdict["scene"] == "growing" and verdict["default"]["setting"] == "200m-dt16"
    again = tts.rebuild(data, "growing", replicates=20)
    assert again["verdict"]["device"] == verdict["device"]
    (data / "time_to_solution_verdict.json").unlink()           # no verdict left: device and commit of the runs
    again = tts.rebuild(data, "growing", replicates=20)
    assert (again["verdict"]["device"], again["verdict"]["commit"]) == (verdict["device"], verdict["commit"])
    from cloudpbf.report.common import Inputs, Section
    from cloudpbf.studies.time_to_solution.report import time_to_solution_section as section
    sec = Section("time_to_solution", "Time to solution")
    section(Inputs(ctx.out), sec, None)
    assert any(b.kind == "image" for b in sec.blocks) and not sec.missing


def test_end_time_enters_the_run_key_only_when_set():
    from cloudpbf import runs
    from pbf_cuda.scene import load_scene
    spec = runs.RunSpec("particles", load_scene("growing"), backend="cpu", steps=10)
    assert "end_time" not in spec.options()                 # the keys of runs without it are unchanged
    timed = spec.replace(end_time=20.0)
    assert timed.options()["end_time"] == 20.0 and timed.key() != spec.key()
    with pytest.raises(ValueError, match="end_time"):
        spec.replace(end_time=-1.0)
    assert "diagnostic_times" not in spec.options()
    bracketed = spec.replace(diagnostic_times=(5, 10.5))
    assert bracketed.options()["diagnostic_times"] == [5.0, 10.5] and bracketed.key() != spec.key()
    for bad in ((10.0, 5.0), (0.0,), (float("nan"),), (True,)):
        with pytest.raises(ValueError, match="diagnostic_times"):
            spec.replace(diagnostic_times=bad)


def test_errors_below_the_seed_noise_floor_count_as_equal():
    """Seed noise of 0.3 puts the noise floor above the defaults' error 0.2: the within-noise budget then takes the
    cheapest setting under the floor (cheap_ok at 0.18, or cheaper ones whose error the floor covers), and says so."""
    per_run, series, meta = synthetic(SPECS, noise=0.0)
    frame, verdict = tts.analyse(per_run, series, meta, {"scene": "growing"}, replicates=20)
    assert verdict["within_noise"]["error_budget"] == pytest.approx(0.2)   # no noise: the defaults' own error
    assert verdict["within_noise"]["cheapest"]["setting"] == "cheap_ok"
    floor = 0.7
    point = {"error": frame["error"].to_numpy(), "cost": frame["wall_per_sim_s"].to_numpy(), "speedup": 4.0 / 1.5,
             "picks": {name: None for name, _ in tts.BUDGET_FACTORS}}
    point["picks"]["default"] = int(np.flatnonzero(frame["setting"] == "cheap_ok")[0])
    default = int(np.flatnonzero(frame["setting"] == "default")[0])
    noisy = tts.build_verdict(frame, point, default, {"speedup": [2.0, 3.0]}, {"scene": "growing"}, floor, 8)
    assert noisy["within_noise"]["cheapest"]["setting"] == "cheap_bad"     # 0.6 <= the floor, the cheapest
    assert "Within the noise floor the cheapest is cheap_bad" in noisy["verdict"]
