"""`cloudpbf demo --scale smoke` end to end: every study, the renders and the HTML report (CI runs it)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pandas as pd
import pytest

from cloudpbf import runs
from cloudpbf.studies.demo import study_names as demo_study_names
from cloudpbf.studies.page import sections
from cloudpbf.studies.scales import SCALES
from cloudpbf.studies.table1 import TABLE1_COLUMNS

pytest.importorskip("pbf_cuda._core", reason="the particle solver is not built")

DATA_FILES = ("environment.json", "table1.csv", "pbf_scaling.csv", "grid_scaling.csv", "compare_timeseries.csv",
              "compare_profiles.csv", "sweep.csv", "stress.csv", "demo_status.json")


@pytest.mark.slow
def test_smoke_demo_writes_every_study_and_the_report(tmp_path):
    out, root = tmp_path / "report", tmp_path / "runs"
    env = {**os.environ, "CLOUDPBF_RUNS": str(root)}
    cmd = [sys.executable, "-m", "cloudpbf.cli", "demo", "--scale", "smoke", "--out", str(out), "--quiet"]
    code = {solver: runs.code_version(solver) for solver in runs.SOLVERS}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    first = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stdout + proc.stderr
    index = out / "index.html"
    assert f"report: {index}" in proc.stdout
    html = index.read_text()
    for section_id in [r.id for r in sections()]:
        assert f'id="{section_id}"' in html, section_id
    for name in DATA_FILES:
        assert (out / "data" / name).is_file(), name
    status = json.loads((out / "data" / "demo_status.json").read_text())["studies"]
    assert all(s["ok"] for s in status.values()), status
    assert json.loads((out / "data" / "environment.json").read_text())["scale"] == "cpu-smoke"
    table1 = pd.read_csv(out / "data" / "table1.csv")
    assert list(table1.columns[:len(TABLE1_COLUMNS)]) == list(TABLE1_COLUMNS)
    assert list(table1["example"]) == ["growing", "growing", "cycling", "cycling"]
    stable = table1[table1["stable"]]
    phases = stable[["pbf_ms", "smoothing_ms", "cloud_dynamics_ms", "splitting_ms", "merging_ms"]]
    assert (stable["total_ms"] - phases.sum(axis=1, skipna=True)).abs().max() < 1e-6   # no double counting
    assert stable[stable["mode"] == "non-adaptive"][["splitting_ms", "merging_ms"]].isna().all().all()
    compare = pd.read_csv(out / "data" / "compare_timeseries.csv")
    assert set(compare["mode"]) == {"non-adaptive", "adaptive", "grid"}
    assert compare.groupby("mode")["seed"].nunique().min() >= 5
    # the smoke box forms clouds in every mode, and the adaptive runs split
    assert (compare.groupby("mode")["cloud_cover"].max() > 0.1).all(), compare.groupby("mode")["cloud_cover"].max()
    adaptive = compare[compare["mode"] == "adaptive"]
    assert adaptive["n_particles"].max() > adaptive["n_particles"].iloc[0]
    # so do the sweep's particle runs: both modes have measured errors, so the Pareto plot holds points of
    # both and the verdict compares them (not "not enough stable runs")
    sweep = pd.read_csv(out / "data" / "sweep.csv")
    measured = sweep[sweep["stable"].astype(bool) & sweep["error_self"].notna()]
    assert (measured["parameter"] == "spacing").sum() >= 2, sweep[["parameter", "value", "stable", "error_self"]]
    assert (measured["parameter"] == "adaptive_spacing").sum() >= 1, sweep[["parameter", "value", "error_self"]]
    verdict = json.loads((out / "data" / "sweep_verdict.json").read_text())["verdict"]
    assert not verdict.startswith("not enough"), verdict
    # scale-honest and noise-aware: at the smoke scale Table 1 is throughput, never a speed-up against the paper;
    # the sweep's speed-up is a verdict only with an interval that excludes 1
    assert table1["speedup_vs_paper"].isna().all() and (table1["particle_steps_per_s"] > 0).all()
    glance = html[html.index('<section id="summary"'):html.index("</section>", html.index('<section id="summary"'))]
    assert "needs the gpu scale" in glance and "faster than the paper" not in glance
    sweep_verdict = json.loads((out / "data" / "sweep_verdict.json").read_text())
    if sweep_verdict["comparisons"]:
        assert sweep_verdict["no_difference"] == verdict.startswith("no difference measured"), verdict
    stress = pd.read_csv(out / "data" / "stress.csv")
    assert not (stress["usable"].astype(bool) & ~stress["stable"].astype(bool)).any()
    assert stress.loc[stress["usable"].astype(bool), "reference_error"].le(0.1).all()
    # the shallow cumulus study: every seed of the scale and their mean, all stable, its four tables
    shallow = pd.read_csv(out / "data" / "shallow_cumulus.csv", dtype={"seed": str})
    assert list(shallow["seed"]) == [str(s) for s in range(SCALES["smoke"].shallow_seeds)] + ["mean"]
    assert shallow["stable"].all() and (shallow["particles"] > 0).all()
    for stem in ("shallow_cumulus_series", "shallow_cumulus_profile", "shallow_cumulus_les"):
        assert (out / "data" / f"{stem}.csv").is_file(), stem
    for render in ("clouds_particles", "clouds_volume", "figure1_unsmoothed", "figure1_smoothed",
                   "figure3_shape_energy", "clouds_strip", "shallow_cumulus_volume", "shallow_cumulus_particles"):
        renders = out / "data" / "renders"
        assert (renders / f"{render}.png").is_file() or (renders / f"{render}.unavailable.txt").is_file()
    # the second demo finds every run in the cache: no run directory is added, and it is much faster. It runs
    # the studies that go through the run cache (the scaling study times fresh steps by design, and its minute
    # would only blur the comparison)
    cached = [s for s in demo_study_names() if s != "scaling"]
    before = sorted(p.name for p in root.iterdir())
    t0 = time.perf_counter()
    again = subprocess.run(cmd + ["--only", ",".join(cached)], capture_output=True, text=True, env=env, timeout=900)
    second = time.perf_counter() - t0
    assert again.returncode == 0, again.stdout + again.stderr
    runs.code_version.cache_clear()
    if {solver: runs.code_version(solver) for solver in runs.SOLVERS} != code:
        pytest.skip("solver sources changed during the test: new code, new runs (the cache did its job)")
    assert sorted(p.name for p in root.iterdir()) == before
    assert second < first / 2, f"first demo {first:.0f} s, cached rerun {second:.0f} s"
