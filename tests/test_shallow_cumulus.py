"""The shallow-cumulus study (cloudpbf.studies.shallow_cumulus): its metrics on a synthetic run (closed forms),
its comparison with the LES cases. The whole study at the smoke scale runs in the smoke demo's test
(tests/test_harness_demo.py), which checks its tables and renders."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cloudpbf.studies import shallow_cumulus as sc
from pbf_cuda import load_scene


class FakeRun:
    """A finished run with given stats and profiles (what analyse reads)."""
    stable, step = True, 100

    def __init__(self, stats, profiles):
        self._stats, self._profiles = stats, profiles

    def stats(self):
        return self._stats

    def profiles(self):
        return self._profiles


def synthetic_run(cover_late, peak, z_peak, onset_step=3):
    times = np.arange(11) * 100.0
    cover = np.where(np.arange(11) < onset_step, 0.0, cover_late)
    stats = pd.DataFrame({"step": np.arange(11) * 50, "time_s": times, "cloud_cover": cover,
                          "cloud_base": 1000.0, "cloud_top": 2000.0, "lwp_mean": 0.01, "n_objects": 4})
    z = np.arange(0.0, 3200.0, 100.0)
    frames = []
    for t in times:
        cf = np.where(np.isclose(z, z_peak), peak, 0.5 * peak * (z > 900) * (z < 2100))
        frames.append(pd.DataFrame({"time_s": t, "z": z, "cloud_fraction": cf}))
    return FakeRun(stats, pd.concat(frames, ignore_index=True))


@settings(max_examples=30, deadline=None)
@given(cover=st.floats(0.02, 0.9), ratio=st.floats(1.0, 4.0), z_peak=st.sampled_from([1000.0, 1500.0, 1900.0]))
def test_metrics_of_a_synthetic_run_are_their_closed_forms(cover, ratio, z_peak):
    peak = cover / ratio
    row, series, profile = sc.analyse(synthetic_run(cover, peak, z_peak), None)
    assert row["cover_mean"] == pytest.approx(cover)
    assert row["in_shallow_range"] == (1.0 if 0.1 <= cover <= 0.4 else 0.0)
    assert row["cf_peak"] == pytest.approx(peak) and row["z_cf_peak_m"] == z_peak
    assert row["cover_to_peak"] == pytest.approx(ratio)
    assert row["z_cf_peak_over_top"] == pytest.approx(z_peak / 2000.0)
    assert row["onset_s"] == 300.0 and row["lwp_g_m2"] == pytest.approx(10.0) and row["clouds_end"] == 4
    assert list(series.columns) == ["time_s", *sc.SERIES_COLUMNS]


def test_les_table_says_which_cases_the_scene_mean_lies_in():
    summary = pd.DataFrame({"seed": ["0", "1", "mean"], "cover_mean": [0.1, 0.2, 0.15],
                            "cloud_base_m": [900.0, 1300.0, 1100.0]})
    table = sc.les_table(summary).set_index(["case", "metric"])
    assert len(table) == len(sc.LES_CASES)
    # every case's metric is a column the study writes
    row, _, _ = sc.analyse(synthetic_run(0.2, 0.1, 1500.0), None)
    assert {c["metric"] for c in sc.LES_CASES} <= set(row)
    assert table.loc[("BOMEX", "cover_mean"), "inside"] and table.loc[("ARM", "cover_mean"), "inside"]
    assert table.loc[("ARM", "cloud_base_m"), "inside"]
    assert table.loc[("ARM", "cloud_base_m"), "scene_seed_min"] == 900.0
    assert not table.loc[("BOMEX", "cover_to_peak"), "inside"]     # no such column: NaN, never "inside"
    assert math.isnan(table.loc[("BOMEX", "cover_to_peak"), "scene_mean"])


def test_the_scene_is_growing_under_an_inversion_above_its_cloud_base():
    scene = load_scene(sc.SCENE)
    a = scene.atmosphere
    assert a.inversion_height > 0.0 and a.inversion_strength > 0.0
    # the inversion lies between the LCL of the ground air and the lid
    q = a.initial_vapor_ratio * float(scene.saturation(a.ground_temperature))
    lcl = float(scene.lifting_condensation_level(a.ground_temperature, q))
    assert lcl < a.inversion_height < scene.domain.size[1] - a.inversion_depth
