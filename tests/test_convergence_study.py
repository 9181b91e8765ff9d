"""The convergence study's plan and convergence.csv (cloudpbf.studies.convergence), without running a solver."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd

from cloudpbf.studies.convergence import COLUMNS, convergence_plan, convergence_rows
from cloudpbf.studies.scales import SCALES


def test_the_plan_runs_both_solvers_at_every_resolution_and_seed_on_one_analysis_grid():
    plan = convergence_plan(SimpleNamespace(scale=SCALES["gpu"], backend="cpu"), "growing", [68, 34, 27], seeds=2)
    assert len(plan) == 2 * 3 * 2
    particles = [p for p in plan if p[0] == "particles"]
    assert sorted({p[3].scene.particles.spacing for p in particles}) == [27.0, 34.0, 68.0]
    assert {p[3].diagnostics_resolution for p in particles} == {(94, 94, 94)}     # the middle spacing's, 34 m
    grid = {(p[3].resolution, round(p[1], 1)) for p in plan if p[0] == "grid"}
    assert grid == {((47, 47, 47), 68.1), ((94, 94, 94), 34.0), ((119, 119, 119), 26.9)}
    assert {p[2] for p in plan} == {0, 1} and {p[3].seed for p in plan} == {0, 1}
    smoke = convergence_plan(SimpleNamespace(scale=SCALES["smoke"], backend="cpu"))
    assert len(smoke) == 2 * len(SCALES["smoke"].convergence_resolutions) * SCALES["smoke"].convergence_seeds
    assert smoke[0][3].scene.domain.size == [1200.0, 1600.0, 1200.0]


def _result(stable, cover):
    stats = pd.DataFrame({"time_s": [0.0, 100.0, 200.0], "cloud_cover": [0.0, cover, cover],
                          "lwp_mean": [0.0, 0.2, 0.4], "cloud_base": [0.0, 1000.0, 1100.0],
                          "cloud_top": [0.0, 2000.0, 2200.0]})
    return SimpleNamespace(stable=stable, stats=lambda: stats, max_particles=1000, device="cpu")


def test_rows_per_seed_and_mean_rows_over_the_stable_seeds():
    plan = convergence_plan(SimpleNamespace(scale=SCALES["gpu"], backend="cpu"), "growing", [68, 54, 43], seeds=2)
    results = [_result(not (solver == "grid" and h < 50 and seed == 1), 0.5 + 0.1 * seed)
               for solver, h, seed, _ in plan]
    frame = convergence_rows(plan, results, "abc123")
    assert tuple(frame.columns) == COLUMNS and len(frame) == 12 + 6
    means = frame[frame["seed"] == "mean"].set_index(["solver", "resolution_m"])
    assert np.isclose(means.loc[("particles", 68.0), "cover_mean"], 0.55) and bool(means.loc[("particles", 68.0), "stable"])
    assert means.loc[("grid", 43.2), "cover_mean"] == 0.5 and not means.loc[("grid", 43.2), "stable"]
    assert np.allclose(means["lwp_mean"], 0.3) and np.allclose(means["cloud_base_mean"], 1050.0)
    seeds = frame[frame["seed"] != "mean"]
    assert set(seeds["seed"]) == {"0", "1"} and seeds.loc[~seeds["stable"], "cover_mean"].isna().all()
