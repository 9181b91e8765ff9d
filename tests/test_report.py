"""The HTML report (built from a synthetic study directory) and the pyvista renders."""
import json
import re
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest

from cloudpbf import render
from cloudpbf import statistics as st
from cloudpbf.pareto import pareto_front
from cloudpbf.report import plots
from cloudpbf.studies.page import build_report, sections as page_sections

DEVICE, COMMIT = "Synthetic CPU (2 threads)", "abc123def456"


# --------------------------------------------------------------------------------------------
# a synthetic study: every input of the data layout, numbers from the statistics code
# --------------------------------------------------------------------------------------------
def _box_cloud_fields(t, seed, speed):
    """A growing box of cloud on a 16 x 20 x 16 grid of 100 m cells (cloud from t = 100 s)."""
    shape = (16, 20, 16)
    rng = np.random.default_rng(seed)
    w = np.zeros(shape)
    if t >= 100:
        half = min(8, int(1 + speed * (t - 100) / 100))
        x0 = int(rng.integers(0, 16))
        w[np.arange(x0, x0 + half) % 16, 8:8 + half // 2 + 1, :half] = 3e-4
    y = (np.arange(shape[1]) + 0.5) * 100.0
    return {"cloud": w, "vapor": np.full(shape, 1e-2) - w,
            "temperature": np.broadcast_to((300 - 0.0065 * y)[None, :, None], shape),
            "cell_size": np.full(3, 100.0), "origin": np.zeros(3)}


def write_synthetic_study(out, renders=True):
    data = out / "data"
    (data / "renders").mkdir(parents=True)
    (data / "environment.json").write_text(json.dumps({
        "device": DEVICE, "backend": "cpu", "commit": COMMIT, "date": "2026-01-01T00:00:00Z",
        "python": "3.11.0", "versions": {"numpy": np.__version__, "pandas": pd.__version__}, "scale": "cpu-smoke"}))
    pd.DataFrame([
        ("growing", "5a", "non-adaptive", 4096, 30.0, 4.0, 1.0, None, None),
        ("growing", "5b", "adaptive", 2600, 15.0, 2.0, 0.5, 0.4, 1.2),
        ("cycling", "5c", "non-adaptive", 4500, 33.0, 4.2, 1.1, None, None),
        ("cycling", "5d", "adaptive", 2500, 16.0, 2.1, 0.6, 0.5, 1.3),
    ], columns=["example", "figure", "mode", "max_particles", "pbf_ms", "smoothing_ms", "cloud_dynamics_ms",
                "splitting_ms", "merging_ms"]).assign(
        total_ms=lambda d: d[["pbf_ms", "smoothing_ms", "cloud_dynamics_ms", "splitting_ms", "merging_ms"]]
        .sum(axis=1), device=DEVICE, commit=COMMIT).to_csv(data / "table1.csv", index=False)
    pd.DataFrame({"particles": [250_000, 1_000_000, 4_000_000], "iterations": 4,
                  "step_ms": [3.0, 11.0, 45.0], "neighbors_ms": [1.0, 4.0, 17.0], "solver_ms": [1.5, 5.5, 23.0],
                  "device": DEVICE, "commit": COMMIT}).to_csv(data / "pbf_scaling.csv", index=False)
    pd.DataFrame({"machine": "m1", "commit": ["aaaa1111", "bbbb2222", "aaaa1111", "bbbb2222"],
                  "date": ["2026-01-01 00:00", "2026-01-02 00:00"] * 2, "backend": "cuda", "scene": "growing",
                  "particles": [64_000, 64_000, 1_000_000, 1_000_000], "time_ms": [1.0, 2.0, 6.0, 6.1],
                  "ci_low_ms": [0.9, 1.9, 5.9, 6.0], "ci_high_ms": [1.1, 2.1, 6.1, 6.2],
                  "ratio": [None, 2.0, None, 6.1 / 6.0], "change": ["", "slower", "", ""]}).to_csv(
        data / "benchmark_history.csv", index=False)
    pd.DataFrame({"threads": [2, 2, 0], "tool": ["SPlisHSPlasH 2.19.0", "cloudpbf", "cloudpbf (cuda)"],
                  "fluid_particles": [85_184, 93_150, 93_150], "ms_per_step": [210.0, 170.0, 1.0],
                  "particle_steps_per_s": [4.06e5, 5.48e5, 9.3e7], "device": ["cpu", "cpu", DEVICE],
                  "commit": COMMIT}).to_csv(data / "cpu_peer.csv", index=False)
    pd.DataFrame({"scene": ["growing_adaptive"], "spacing_m": [45.0], "mean_particles": [480_000.0],
                  "max_particles": [600_000], "splitting_ms": [0.1], "merging_ms": [0.5], "merge_passes_ms": [0.3],
                  "compaction_ms": [0.1], "pbf_ms": [11.0], "split_target_ms": [0.3], "merge_target_ms": [1.0],
                  "meets_targets": [True], "device": DEVICE, "commit": COMMIT}).to_csv(data / "adaptive_cost.csv",
                                                                                       index=False)
    pd.DataFrame({"cells": [32**3, 64**3, 128**3], "step_ms": [5.0, 38.0, 310.0], "dtype": "float64",
                  "device": DEVICE, "commit": COMMIT}).to_csv(data / "grid_scaling.csv", index=False)
    series, profiles = [], []
    for solver, mode, speed in (("particles", "non-adaptive", 1.0), ("particles", "adaptive", 1.2),
                                ("grid", "grid", 0.8)):
        for seed in range(5):
            rows = []
            for t in range(0, 1001, 100):
                fields = _box_cloud_fields(t, seed, speed)
                rows.append({"time_s": float(t), **st.diagnostics(fields),
                             **({"n_particles": 4096 + (0 if mode != "adaptive" else 10 * t)}
                                if solver == "particles" else {})})
                prof = st.vertical_profiles(fields)
                profiles.append(prof.assign(solver=solver, mode=mode, seed=seed, time_s=float(t)))
            series.append(st.timeseries_frame(rows, solver=solver, mode=mode, seed=seed))
    pd.concat(series).assign(device=DEVICE, commit=COMMIT).to_csv(data / "compare_timeseries.csv", index=False)
    pd.concat(profiles)[["solver", "mode", "seed", "time_s", *st.PROFILE_COLUMNS]].assign(
        device=DEVICE, commit=COMMIT).to_csv(data / "compare_profiles.csv", index=False)
    sweep = []
    for mode, base in (("non-adaptive", 1.0), ("adaptive", 0.6)):
        for spacing, err in ((100.0, 0.30), (70.0, 0.15), (50.0, 0.05), (35.0, 0.0)):
            sweep.append(("particles", mode, "spacing", spacing, base * (100 / spacing) ** 3, err, err + 0.1))
    for cells, err in ((16, 0.4), (32, 0.2), (64, 0.0)):
        sweep.append(("grid", "grid", "cells", cells, 0.01 * cells**1.5, err, err + 0.15))
    pd.DataFrame(sweep, columns=["method", "mode", "parameter", "value", "wall_s", "error_self", "error_other"]).assign(
        device=DEVICE, commit=COMMIT).to_csv(data / "sweep.csv", index=False)
    (data / "sweep_verdict.json").write_text(json.dumps({   # the demo's three single wall-clock ratios
        "metric": "error_self", "verdict": "at equal error, adaptive runs are 1.02x slower than non-adaptive runs",
        "comparisons": [{"error": e, "speedup": r} for e, r in ((0.3, 2.0), (0.2, 0.82), (0.1, 0.98))],
        "non_adaptive": [{"wall_s": 8.0, "error_self": 0.05}, {"wall_s": 1.0, "error_self": 0.3}],
        "adaptive": [{"wall_s": 4.8, "error_self": 0.05}]}))
    # adaptive-pareto: uniform runs on a power-law front, two adaptive variants, the reference
    from cloudpbf.studies.adaptive_pareto import time_at_error  # noqa: F401  (the study's module imports cleanly)
    configs = [("uniform-68m", "uniform", "", 68.0, 1e5, 5.0, 0.27), ("uniform-54m", "uniform", "", 54.0, 2e5, 6.4, 0.21),
               ("uniform-43m", "uniform", "", 43.0, 4e5, 9.1, 0.14), ("uniform-34m", "uniform", "", 34.0, 8e5, 14.8, 0.08),
               ("paper-68m", "adaptive", "paper", 68.0, 1.2e5, 4.0, 0.20),
               ("lookahead-68m", "adaptive", "lookahead", 68.0, 1.4e5, 4.5, 0.15),
               ("reference-27m", "reference", "", 27.0, 1.7e6, 28.0, 0.0)]
    frame = pd.DataFrame(configs, columns=["config", "kind", "criterion", "spacing_m", "particles", "ms_per_step", "error"])
    frame = frame.assign(error_seed_spread=0.02, pbf_ms_per_particle=1e-5, e_cover=frame.error, e_volume=frame.error,
                         e_lwp=frame.error, e_base=0.05, e_top=0.05, e_profile=0.2, speedup_at_equal_error=None,
                         speedup_p05=None, speedup_p95=None)
    frame.to_csv(data / "adaptive_pareto_configs.csv", index=False)
    frame.assign(seed=0, device=DEVICE, commit=COMMIT).to_csv(data / "adaptive_pareto.csv", index=False)
    (data / "adaptive_verdict.json").write_text(json.dumps({
        "scene": "growing", "cost_ratio_per_particle": 1.1, "noise_floor": 0.02, "variants": [],
        "min_stable_seeds": 3,
        "excluded": [{"name": "paper-68m", "kind": "adaptive", "stable_seeds": 1, "seeds": 3,
                      "reasons": ["stable in 1 of 3 seeds (the verdict needs 3)"]}],
        "best": {"name": "lookahead-68m", "error": 0.15, "error_seed_spread": 0.02, "ms_per_step": 4.5,
                 "uniform_ms_at_equal_error": 7.2, "speedup_at_equal_error": 1.6, "stable_seeds": 3, "seeds": 3,
                 "speedup_interval": [1.3, 1.9]},
        "resampling": {"replicates": 1000, "seeds": 3, "goal_speedup": 1.6, "no_best_share": 0.0},
        "verdict": "growing: the best adaptive variant, lookahead-68m, is 1.60x faster than uniform particles.",
        "device": DEVICE, "commit": COMMIT}))
    stress = pd.DataFrame([
        ("dt", 0.5, True, "", 400, 4096, 3.0, 0.01), ("dt", 2.0, True, "", 400, 4096, 3.5, 0.01),
        ("dt", 8.0, True, "", 400, 4096, 6.0, 0.03), ("dt", 32.0, False, "velocity bound exceeded", 17, 4096, 250.0, 0.4),
        ("iterations", 1, True, "", 400, 4096, 4.0, 0.05), ("iterations", 4, True, "", 400, 4096, 3.0, 0.01),
        ("phase_rate_dt", 100.0, True, "", 400, 4096, 3.2, 0.01),
        ("heating_rate", 5.0, False, "NaN in temperature", 3, " ".join(map(str, range(100, 140))), 9.0, 0.02),
    ], columns=["parameter", "value", "stable", "reason", "step", "particles", "max_speed", "density_error_mean"]
    ).assign(device=DEVICE, commit=COMMIT)
    maps = []   # 2-D maps: the density error grows with dt and falls with iterations; dt 32 blows up
    for dt in (2.0, 8.0, 32.0):
        for it in (1, 4):
            maps.append(("dt x iterations", dt, dt < 32, dt, it, 0.01, 0.002 * dt / it))
        for rate in (0.01, 0.1):
            maps.append(("dt x heating_rate", dt, dt < 32, dt, 4, rate, 0.0005 * dt * (1 + 10 * rate)))
    maps = pd.DataFrame(maps, columns=["parameter", "value", "stable", "dt", "iterations", "heating_rate",
                                       "density_error_max"]).assign(density_error_mean=lambda d: d.density_error_max)
    pd.concat([stress, maps]).to_csv(data / "stress.csv", index=False)
    pd.DataFrame({"case": ["cycling (shipped)", "growing + g_c = 0.1"], "constant_gravity": [0.0, 0.1],
                  "cloud_gravity": [196.2, 9.81], "particles": [8000, 8000], "stable": [True, True],
                  "reason": [None, None], "first_cloud_s": [220.0, 100.0], "max_cover": [0.9, 1.0],
                  "final_cover": [0.85, 1.0], "vanished_and_returned": [False, False],
                  "density_error_mean": [0.02, 0.07], "max_speed": [13.0, 48.0], "device": DEVICE,
                  "commit": COMMIT}).to_csv(data / "constant_gravity.csv", index=False)
    write_synthetic_shallow_cumulus(data)
    if renders:
        import matplotlib.pyplot as plt
        for name in ("clouds_particles", "clouds_volume", "figure1_unsmoothed", "figure1_smoothed",
                     "figure3_shape_energy", "shallow_cumulus_volume", "shallow_cumulus_particles"):
            fig, ax = plt.subplots(figsize=(2, 1.5))
            ax.imshow(np.random.default_rng(0).random((8, 8)))
            fig.savefig(data / "renders" / f"{name}.png")
            plt.close(fig)
        from PIL import Image
        frames = [Image.new("RGB", (16, 12), (40 * i, 90, 200)) for i in range(3)]
        frames[0].save(data / "renders" / "clouds_animation.gif", save_all=True, append_images=frames[1:])
        frames[0].save(data / "renders" / "clouds_strip.png")
    return out


def write_synthetic_shallow_cumulus(data):
    """The shallow-cumulus study's CSVs (cloudpbf.studies.shallow_cumulus) for two seeds, from its own les_table."""
    from cloudpbf.studies.shallow_cumulus import les_table, with_seed_mean
    rows = [{"seed": str(s), "particles": 8000, "spacing_m": 100.0, "stable": True, "step": 500, "cover_mean": c,
             "cover_min": c - 0.05, "cover_max": c + 0.05, "in_shallow_range": 1.0, "onset_s": 400.0,
             "cloud_base_m": 1100.0, "cloud_top_m": 1700.0, "lwp_g_m2": 4.0, "clouds_end": 9, "cf_peak": c / 1.2,
             "z_cf_peak_m": 1500.0, "cover_to_peak": 1.2, "z_cf_peak_over_top": 0.88} for s, c in ((0, 0.12), (1, 0.16))]
    summary = with_seed_mean(pd.DataFrame(rows)).assign(device=DEVICE, commit=COMMIT)
    summary.to_csv(data / "shallow_cumulus.csv", index=False)
    les_table(summary).assign(device=DEVICE, commit=COMMIT).to_csv(data / "shallow_cumulus_les.csv", index=False)
    t = np.arange(0.0, 1001.0, 100.0)
    pd.concat([pd.DataFrame({"time_s": t, "cloud_cover": np.clip((t - 300) / 2000, 0, None) + 0.02 * s,
                             "cloud_base": 1100.0, "cloud_top": 1700.0, "lwp_mean": 0.004, "n_objects": 9,
                             "seed": s}) for s in (0, 1)]).assign(device=DEVICE, commit=COMMIT).to_csv(
        data / "shallow_cumulus_series.csv", index=False)
    z = np.arange(50.0, 3200.0, 100.0)
    pd.concat([pd.DataFrame({"z": z, "cloud_fraction": 0.1 * np.exp(-((z - 1500) / 200) ** 2), "seed": s})
               for s in (0, 1)]).assign(device=DEVICE, commit=COMMIT).to_csv(
        data / "shallow_cumulus_profile.csv", index=False)


class _Collector(HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids, self.refs, self.images = set(), [], 0

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.add(attrs["id"])
        for key in ("src", "href"):
            if attrs.get(key):
                self.refs.append(attrs[key])
        if tag == "img":
            self.images += 1


def _sections(page):
    """section id -> its HTML."""
    parts = re.split(r'<section id="', page)[1:]
    return {p.split('"', 1)[0]: p for p in parts}


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    """(study directory, index.html text) of the synthetic study with every input."""
    out = write_synthetic_study(tmp_path_factory.mktemp("report") / "study")
    index = build_report(out)
    assert index == (out / "index.html").resolve()
    return out, index.read_text()


def test_report_builds_with_every_section_and_no_external_reference(full_report):
    out, page = full_report
    assert (out / "index.html").stat().st_mode & 0o777 == 0o644
    parser = _Collector()
    parser.feed(page)
    expected = [r.id for r in page_sections()]
    assert set(expected) <= parser.ids
    assert expected == ["summary", "time_to_solution", "table1", "phases", "scaling", "benchmark_history", "peers",
                        "adaptive", "compare", "shallow_cumulus", "sweep",
                        "adaptive_pareto", "stress", "renders", "figure1", "figure3", "environment"]
    # offline: in-page anchors, embedded images and files beside the page (data, full-size figures); no URL,
    # no path of this machine
    assert not re.search(r"https?://", page)
    for ref in parser.refs:
        if ref.startswith("#") or ref.startswith(("data:image/png;base64,", "data:image/gif;base64,",
                                                  "data:image/jpeg;base64,")):
            continue
        assert (out / ref).is_file() and (out / ref).resolve().is_relative_to(out.resolve()), ref
    assert str(out) not in page and str(out.parent) not in page
    assert parser.images == 25   # every figure and render, the 2-D map, the animation and four verdict cards
    sections = _sections(page)
    for sid in expected:
        if sid == "time_to_solution":      # not in this synthetic study (tests/test_time_to_solution.py)
            continue
        assert "not run in this study" not in sections[sid], sid
        assert "could not build" not in sections[sid], sid
    # the numbers in the page come from the data
    assert DEVICE in sections["environment"] and COMMIT[:7] in sections["table1"]
    assert "needs the gpu scale" in sections["table1"]          # cpu-smoke: throughput, no paper comparison
    assert "1087" not in sections["table1"] and "speed-up" not in sections["table1"]
    assert "1.657" in sections["adaptive"]                      # the paper's step-time ratio growing: 1218.95 / 735.64
    # no converged-reference check in this stress.csv: nothing is called usable
    assert ("Largest usable dt: not determined (no converged-reference check in this data); largest stable dt "
            "(no blow-up, accuracy aside): 8 s" in sections["stress"])
    assert "40 ids: 100 101 102 …" in sections["stress"] and "120 121" not in sections["stress"]
    assert "velocity bound exceeded" in sections["stress"]
    # the sweep verdict: three single ratios whose interval holds 1
    assert ("no difference measured: at equal error the adaptive runs&#39; speed-ups are 2.00x, 0.82x, 0.98x"
            in sections["sweep"])
    # adaptive-pareto: the stable-seed rule of the verdict is stated, and what it left out is drawn apart
    assert "use only configurations stable in at least 3 seeds" in sections["adaptive_pareto"]
    assert "open markers: left out of the verdict" in sections["adaptive_pareto"]
    assert "speedup_p05 and speedup_p95: the 5th and 95th percentiles of the speed-up over 1000 resamples" in sections[
        "adaptive_pareto"]


def test_table1_below_the_gpu_scale_shows_throughput_and_no_paper_ratio(full_report):
    table1 = _sections(full_report[1])["table1"]
    heads = re.findall(r"<th>([^<]*)</th>", table1)
    assert heads[:5] == ["example", "mode", "particles", "total ms", "particle-steps/s"]
    assert not any("paper" in h for h in heads)
    assert f"{4096 * 1e3 / 35.0:.4g}" in table1                # growing non-adaptive: 4096 particles / 35 ms


def _gpu_table1(tmp_path, counts):
    """A gpu-scale table1.csv with the given max_particles per row (growing, cycling x non-adaptive, adaptive)."""
    data = tmp_path / "data"
    data.mkdir()
    pd.DataFrame({"example": ["growing", "growing", "cycling", "cycling"], "figure": ["5a", "5b", "5c", "5d"],
                  "mode": ["non-adaptive", "adaptive"] * 2, "variant": "", "max_particles": counts,
                  "pbf_ms": [3.5, 1.2, 4.1, 3.1], "total_ms": [3.8, 1.4, 4.4, 3.45], "scale": "gpu",
                  "device": "NVIDIA H100", "commit": COMMIT}).to_csv(data / "table1.csv", index=False)
    return _sections(build_report(tmp_path).read_text())


def test_table1_speedup_against_the_paper_only_where_particle_counts_match(tmp_path):
    """gpu scale: the growing adaptive row holds 128k particles against the paper's 540k, so its comparison is a
    ratio of throughputs; the rows within 20% of the paper's counts get a speed-up."""
    sections = _gpu_table1(tmp_path, [830584, 128445, 941192, 493821])
    card = sections["summary"][sections["summary"].index('id="card-table1"'):]
    card = card[:card.index('id="card-adaptive_front"')]
    assert f"growing non-adaptive {1218.95 / 3.8:.3g}x" in card and f"cycling adaptive {865.57 / 3.45:.3g}x" in card
    assert "growing adaptive " + f"{128445:,}" + f" against {540000:,} particles" in card
    throughput = (128445 / 1.4) / (540000 / 735.64)
    assert f"{throughput:.3g}x the paper&#39;s throughput" in card
    assert "growing adaptive 5" not in card                                   # never a speed-up for that row
    assert "mean over the timed steps; per-step spread not recorded" in card
    assert "no interval on the speed-ups" in card
    table1 = sections["table1"]
    assert "speed-up vs paper (same counts)" in table1 and "throughput vs paper (other counts)" in table1
    assert f"{1218.95 / 3.8:.4g}" in table1 and f"{735.64 / 1.4:.4g}" not in table1


@pytest.mark.parametrize("lock,expected,absent", [
    ({"file": "constraints.txt", "matches": False,
      "differs": {"pandas": {"locked": "2.3.3", "installed": "3.0.6"}, "asv": {"locked": "0.6.6", "installed": None}}},
     ["<td>pandas</td>", "<td>2.3.3</td>", "<td>3.0.6</td>", "1 installed package(s) differ from the lock file"],
     ["Every installed package"]),
    ({"file": "constraints.txt", "matches": True, "differs": {}},
     ["Every installed package is at the version of the lock file constraints.txt"], ["differ from the lock", "<td>pandas</td>"]),
    (None, ["were not checked against constraints.txt"], ["Every installed package"]),
])
def test_environment_section_shows_the_lock_check(tmp_path, lock, expected, absent):
    out = tmp_path / "study"
    (out / "data").mkdir(parents=True)
    (out / "data" / "environment.json").write_text(json.dumps({
        "device": DEVICE, "backend": "cpu", "commit": COMMIT, "versions": {"numpy": "2.4.6"}, "lock": lock}))
    env = _sections(build_report(out).read_text())["environment"]
    for text in expected:
        assert text in env, text
    for text in absent:
        assert text not in env, text
    assert ("Locked but not installed here: asv." in env) == bool(lock and lock["differs"])


def test_report_with_missing_inputs_says_not_run_with_the_command(tmp_path):
    out = tmp_path / "empty"
    (out / "data").mkdir(parents=True)
    page = build_report(out).read_text()
    sections = _sections(page)
    assert set(sections) == {r.id for r in page_sections()}
    for sid in sections:
        assert "not run in this study" in sections[sid], sid
        assert "<code>" in sections[sid], sid
    assert "cloudpbf sweep" in sections["sweep"] and "cloudpbf stress" in sections["stress"]
    assert "cloudpbf table1" in sections["table1"]
    assert not re.search(r"https?://", page)


def test_report_partial_inputs_and_unavailable_render(tmp_path, full_report):
    import shutil
    out = tmp_path / "study"
    shutil.copytree(full_report[0] / "data", out / "data")
    (out / "data" / "grid_scaling.csv").unlink()
    (out / "data" / "sweep.csv").unlink()
    (out / "data" / "renders" / "clouds_volume.png").unlink()
    render.note_path(out / "data" / "renders" / "clouds_volume.png").write_text("no OpenGL context here")
    sections = _sections(build_report(out).read_text())
    assert "grid_scaling.csv" in sections["scaling"] and "not run in this study" in sections["scaling"]
    assert "data:image/png" in sections["scaling"]            # the PBF half is still there
    assert "not run in this study" in sections["sweep"]
    assert "render unavailable: no OpenGL context here" in sections["renders"]
    assert "not run in this study" not in sections["compare"]


def test_broken_input_shows_an_error_in_its_section_only(tmp_path, full_report):
    out = tmp_path / "study"
    (out / "data").mkdir(parents=True)
    for name in ("environment.json", "sweep.csv"):
        (out / "data" / name).write_bytes((full_report[0] / "data" / name).read_bytes())
    (out / "data" / "stress.csv").write_text("parameter,value\ndt,1.0\n")   # no 'stable' column
    sections = _sections(build_report(out).read_text())
    assert "could not build this section" in sections["stress"] and "stable" in sections["stress"]
    assert "could not build" not in sections["sweep"]


def test_gpu_reference_layout_is_read_from_its_data_folder(tmp_path):
    out = tmp_path / "gpu"
    (out / "data").mkdir(parents=True)
    pd.DataFrame({"cells": [32**3, 64**3], "step_ms": [1.0, 6.0], "dtype": "float32", "device": "NVIDIA H100",
                  "commit": COMMIT}).to_csv(out / "data" / "grid_scaling.csv", index=False)
    sections = _sections(build_report(out).read_text())
    assert "NVIDIA H100" in sections["scaling"] and "data:image/png" in sections["scaling"]


def test_pareto_front_and_seed_spread():
    df = pd.DataFrame({"wall_s": [1.0, 2.0, 3.0, 4.0, 2.5], "error_self": [0.5, 0.3, 0.35, 0.1, 0.3]})
    front = pareto_front(df)
    assert front["wall_s"].tolist() == [1.0, 2.0, 4.0]
    ts = pd.DataFrame({"solver": "grid", "mode": "grid", "seed": [0, 1, 2, 0, 1, 2],
                       "time_s": [0, 0, 0, 10, 10, 10], "cloud_cover": [0.0, 0.0, 0.0, 0.1, 0.3, 0.2]})
    spread = plots.seed_spread(ts, "time_s", "cloud_cover")
    last = spread[spread["time_s"] == 10].iloc[0]
    assert (last["lo"], last["hi"], last["n"]) == (0.1, 0.3, 3) and last["mean"] == pytest.approx(0.2)


# --------------------------------------------------------------------------------------------
# renders
# --------------------------------------------------------------------------------------------
def _rendering():
    ok, why = render.rendering_status()
    if not ok:
        pytest.skip(f"no off-screen OpenGL here: {why}")


def _slab_state(scene, patchy):
    lo, hi = scene.fill_box()
    d = scene.particles.spacing
    axes = [np.arange(lo[a] + d / 2, hi[a], d) for a in range(3)]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    r2 = ((pos[:, 0] - 1600) / 600) ** 2 + ((pos[:, 1] - 1800) / 300) ** 2
    w = 8e-4 * np.exp(-r2)
    if patchy:
        w *= np.random.default_rng(0).random(len(w)) > 0.5
    n = len(pos)
    return {"position": pos, "cloud": w, "temperature": scene.environment_temperature(pos[:, 1]),
            "vapor": np.full(n, 1e-2), "mass": np.full(n, d**3), "kernel_radius": np.full(n, 2 * d),
            "level": np.where(w > 1e-4, 2, 0)}


def _is_picture(path, min_colours=20):
    from PIL import Image
    img = np.asarray(Image.open(path).convert("RGB"), dtype=float)
    return img.std() > 5.0 and len(np.unique(img.reshape(-1, 3), axis=0)) >= min_colours


def test_renders_produce_non_blank_pictures(tmp_path):
    _rendering()
    from pbf_cuda.scene import load_scene
    slab = load_scene("smoothing_slab", **{"particles.spacing": 100.0, "domain.size": [3200.0, 3200.0, 600.0]})
    smooth, patchy = _slab_state(slab, False), _slab_state(slab, True)
    small = (320, 240)
    paths = [
        render.render_particles(smooth, slab, tmp_path / "p.png", window_size=small),
        render.render_particles(smooth, slab, tmp_path / "e.png", color_by="shape_energy", window_size=small),
        render.render_slab_comparison(patchy, smooth, slab, tmp_path / "f1.png", window_size=(480, 240)),
        render.render_shape_energy(smooth, slab, tmp_path / "f3.png", window_size=(480, 240)),
    ]
    grid = st.deposit_state(smooth, slab)
    paths.append(render.render_volume(grid["cloud"], grid["cell_size"], tmp_path / "v.png", window_size=small))
    for path in paths:
        assert path.is_file() and _is_picture(path), path.name
    # the cloud picture differs where there is cloud: an all-clear state draws no splats
    clear = dict(smooth, cloud=np.zeros_like(smooth["cloud"]))
    empty = render.render_particles(clear, slab, tmp_path / "clear.png", window_size=small)
    from PIL import Image
    a = np.asarray(Image.open(paths[0]).convert("L"), dtype=float)
    b = np.asarray(Image.open(empty).convert("L"), dtype=float)
    assert np.abs(a - b).mean() > 0.5


def test_render_failure_becomes_a_note(tmp_path, monkeypatch):
    monkeypatch.setenv("CLOUDPBF_NO_RENDER", "1")
    render.rendering_status.cache_clear()
    try:
        with pytest.raises(render.RenderUnavailable, match="CLOUDPBF_NO_RENDER"):
            render.render_volume(np.zeros((2, 2, 2)), 1.0, tmp_path / "v.png")
        assert render.render_or_note(render.render_volume, tmp_path / "v.png", np.zeros((2, 2, 2)), 1.0) is None
        assert not (tmp_path / "v.png").exists()
        assert "CLOUDPBF_NO_RENDER" in render.note_path(tmp_path / "v.png").read_text()
    finally:
        monkeypatch.delenv("CLOUDPBF_NO_RENDER")
        render.rendering_status.cache_clear()


def test_shape_energy_is_eq_20():
    w = np.array([0.0, 1e-4, 1e-3])
    assert np.allclose(render.shape_energy(w, 2.0, 2000.0), 2.0 * (1.0 - np.exp(-2000.0 * w)))
    with pytest.raises(ValueError, match="color_by"):
        render.render_particles({"position": np.zeros((1, 3))}, None, "x.png", color_by="pressure")


def test_failed_study_is_shown_in_its_sections(tmp_path):
    out = tmp_path / "study"
    (out / "data").mkdir(parents=True)
    (out / "data" / "demo_status.json").write_text(json.dumps({"scale": "smoke", "studies": {
        "stress": {"ok": False, "error": "StudyError: stress: 3 of 3 runs failed\n  a\n  b\n  c\n  d", "seconds": 1.0},
        "sweep": {"ok": True, "error": None, "seconds": 2.0}}}))
    page = build_report(out).read_text()
    sections = _sections(page)
    assert "The stress study failed in this run: StudyError: stress: 3 of 3 runs failed" in sections["stress"]
    assert "2 more lines" in sections["stress"]
    assert "study failed" not in sections["sweep"]
    assert "Studies that failed in this run: stress" in page


# --------------------------------------------------------------------------------------------
# the page at a glance: summary, confidence intervals, tests, zoomable figures, the registry
# --------------------------------------------------------------------------------------------
def test_first_screen_is_verdict_cards_from_the_data(full_report):
    page = full_report[1]
    summary = _sections(page)["summary"]
    cards = re.findall(r'<div class="card (\w+)" id="card-([\w_]+)">', summary)
    assert [c for _, c in cards] == ["table1", "adaptive_front", "compare", "stress"]    # no time-to-solution data
    assert summary.count("<img ") == 4
    # Table 1 at the cpu-smoke scale: throughput, and the plain statement that the paper needs the gpu scale
    assert "Throughput at the cpu-smoke scale" in summary and "needs the gpu scale" in summary
    assert "faster than the paper" not in summary
    # the adaptive speed-up: with its interval and the error it holds at
    assert "best variant lookahead-68m 1.60x faster [1.30, 1.90] at equal error 0.15" in summary
    # particles against grid: the difference of the final covers with its Welch interval
    assert "Final cloud cover, particles minus grid: non-adaptive" in summary and "Welch 95% interval" in summary
    assert "Largest usable dt: not determined" in summary
    for href in ("#table1", "#adaptive_pareto", "#compare", "#stress", "data/table1.csv", "data/stress.csv",
                 "data/adaptive_verdict.json", "data/compare_timeseries.csv"):
        assert f'href="{href}"' in summary, href
    assert page.index('id="summary"') < page.index('id="table1"') < page.index('id="environment"')
    assert page.index('<section id="environment"') > page.index('<section id="figure3"')   # the environment last


def test_header_names_every_device_commit_and_scale_of_the_sections(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    pd.DataFrame({"example": ["growing"], "mode": ["non-adaptive"], "max_particles": [830584], "total_ms": [3.8],
                  "scale": "gpu", "device": "NVIDIA H100", "commit": "85a3f32c33e1"}).to_csv(data / "table1.csv",
                                                                                          index=False)
    pd.DataFrame({"cells": [32**3, 64**3], "step_ms": [1.0, 6.0], "dtype": "float32", "device": DEVICE,
                  "commit": COMMIT}).to_csv(data / "grid_scaling.csv", index=False)
    (data / "environment.json").write_text(json.dumps({"device": "NVIDIA H200", "commit": "2b95a7f", "scale": "cpu"}))
    page = build_report(tmp_path).read_text()
    header = page[page.index("<header>"):page.index("</header>")]
    for text in ("NVIDIA H100", DEVICE, "85a3f32", COMMIT[:7], ">gpu<", ">not recorded<"):
        assert text in header, text
    assert "NVIDIA H200" not in header and "2b95a7f" not in header       # environment.json's, no section's data
    assert "Which sections come from which device" in header


def test_a_time_to_solution_card_appears_when_its_data_exists(tmp_path):
    (tmp_path / "data").mkdir()
    before = _sections(build_report(tmp_path).read_text())["summary"]
    assert "card-time_to_solution" not in before
    pd.DataFrame({"setting": ["default", "coarse", "cfl"], "wall_per_sim_s": [0.02, 0.008, 0.01],
                  "error": [0.10, 0.09, 0.2], "front": [False, True, True]}).to_csv(
        tmp_path / "data" / "time_to_solution.csv", index=False)
    cheapest = {"setting": "coarse", "error": 0.09, "wall_per_sim_s": 0.008}
    (tmp_path / "data" / "time_to_solution_verdict.json").write_text(json.dumps({
        "scene": "growing", "default": {"setting": "default", "error": 0.10, "wall_per_sim_s": 0.02},
        "budgets": [{"factor": 1.0, "cheapest": cheapest}], "speedup_at_default_error": 2.5,
        "speedup_interval": [1.8, 3.1], "seeds": 8, "verdict": "growing: ..."}))
    (tmp_path / "data" / "time_to_solution_verdict_cumulus.json").write_text(json.dumps({
        "scene": "cumulus", "default": {"setting": "default", "error": 0.2},
        "budgets": [{"factor": 1.0, "cheapest": cheapest}], "speedup_at_default_error": 1.1,
        "speedup_interval": [0.9, 1.3], "verdict": "cumulus: ..."}))
    summary = _sections(build_report(tmp_path).read_text())["summary"]
    card = summary[summary.index('id="card-time_to_solution"'):]
    assert "growing: coarse 2.50x faster [1.80, 3.10] than the defaults (default) at their error 0.1" in card
    assert "cumulus: coarse no difference measured (1.10x, 5-95% over resampled seeds 0.90-1.30x)" in card
    assert 'href="data/time_to_solution_verdict.json"' in card and 'href="data/time_to_solution.csv"' in card
    assert 'href="#time_to_solution"' in card and card.count("<img ") == 1


def test_sweep_and_stress_tables_have_readable_headers_with_units(full_report):
    sections = _sections(full_report[1])
    sweep = re.findall(r"<th>([^<]*)</th>", sections["sweep"])
    stress = re.findall(r"<th>([^<]*)</th>", sections["stress"])
    for raw in ("wall_s", "error_self", "error_other", "max_speed", "density_error_mean", "density_error_max",
                "constant_gravity", "first_cloud_s"):
        assert raw not in sweep + stress, raw
    assert {"wall time (s)", "error vs own finest run", "error vs other method's finest run",
            "value (spacings in m)"} <= set(sweep)
    assert sweep.count("wall time (s)") == 2                     # the Pareto fronts and all runs
    assert {"value (dt in s, heating in K/s)", "max speed (m/s)", "density error, last step",
            "density error, worst step", "dt (s)", "heating S_e (K/s)", "unstable particle ids",
            "g_c (m/s²)", "first cloud (s)"} <= set(stress)
    assert {"parameter", "stable", "reason"} <= set(stress)     # names that read as they are stay
    from cloudpbf.report.common import _table
    html = _table(pd.DataFrame({"wall_s": [1.5], "other": [2]}), labels={"wall_s": "wall time (s)"})
    assert re.findall(r"<th>([^<]*)</th>", html) == ["wall time (s)", "other"] and "<td>1.5</td>" in html


def test_every_figure_opens_full_size(full_report):
    page = full_report[1]
    zoom = re.findall(r'<figure class="zoom" id="([^"]+)"><a href="#([^"]+)"[^>]*><img ', page)
    full = re.findall(r'<figure class="full" id="([^"]+)"><a href="([^"#]+)"[^>]*><img ', page)
    assert len(zoom) + len(full) + 4 == page.count("<img ") == 25     # the four cards' figures are not zoomed
    assert all(fid == href for fid, href in zoom)
    assert all((full_report[0] / href).is_file() for _, href in full)
    assert "figure.zoom:target" in page


def test_seed_statistics_are_t_intervals_and_welch_tests():
    from scipy import stats as sst
    from cloudpbf.report.inference import format_ci, mean_ci, welch
    x = np.array([0.61, 0.72, 0.55, 0.68, 0.70])
    ci = mean_ci(x)
    half = sst.t.ppf(0.975, 4) * x.std(ddof=1) / np.sqrt(5)    # the closed form
    assert ci.n == 5 and ci.mean == pytest.approx(x.mean())
    assert (ci.lo, ci.hi) == pytest.approx((x.mean() - half, x.mean() + half))
    assert format_ci([0.5]) == "0.5" and format_ci([]) == "–" and format_ci([np.nan, 2.0, 2.0]) == "2 (n=2)"
    # coverage: the 95% interval holds the true mean in about 95% of normal samples of 5
    rng = np.random.default_rng(1)
    samples = rng.normal(3.0, 2.0, (2000, 5))
    hits = 0
    for row in samples:
        c = mean_ci(row)
        hits += c.lo <= 3.0 <= c.hi
    assert 0.93 <= hits / len(samples) <= 0.97
    # Welch: the unequal-variance statistic by hand
    y = np.array([0.31, 0.45, 0.38, 0.29])
    t, p = welch(x, y)
    va, vb = x.var(ddof=1) / 5, y.var(ddof=1) / 4
    assert t == pytest.approx((x.mean() - y.mean()) / np.sqrt(va + vb))
    dof = (va + vb) ** 2 / (va**2 / 4 + vb**2 / 3)
    assert p == pytest.approx(2 * sst.t.sf(abs(t), dof))
    assert np.isnan(welch([1.0], y)[1]) and np.isnan(welch([1.0, 1.0], [2.0, 2.0])[1])


def test_adaptive_section_tests_the_modes_against_each_other(full_report):
    adaptive = _sections(full_report[1])["adaptive"]
    assert "Welch" in adaptive and "final cloud cover (fraction)" in adaptive
    assert "95% confidence interval" in adaptive and "± " not in adaptive


def test_plot_labels_and_relative_water_change():
    assert plots.series_name("grid", "grid") == "grid"
    assert plots.series_name("particles", "adaptive") == "particles adaptive"
    df = pd.DataFrame({"solver": "particles", "mode": "adaptive", "seed": [0, 0, 1, 1],
                       "time_s": [0.0, 10.0, 0.0, 10.0], "total_water": [3.2e8, 3.2e8 * 1.001, 4.0e8, 4.0e8 * 0.99]})
    assert plots.relative_change(df, "total_water").to_numpy() == pytest.approx([0.0, 1e-3, 0.0, -0.01])


def test_animation_is_a_looping_gif_and_a_strip_of_every_frame(tmp_path):
    _rendering()
    from PIL import Image
    from pbf_cuda.scene import load_scene
    slab = load_scene("smoothing_slab", **{"particles.spacing": 100.0, "domain.size": [3200.0, 3200.0, 600.0]})
    grow = _slab_state(slab, False)
    frames = [(t, dict(grow, cloud=grow["cloud"] * t / 200.0)) for t in (0.0, 100.0, 200.0)]   # cloud grows
    gif = render.render_animation(frames, slab, tmp_path / "a.gif", out_strip=tmp_path / "s.png",
                                  window_size=(160, 120), strip_width=80)
    with Image.open(gif) as im:
        assert im.n_frames == 3 and im.info.get("loop") == 0
    with Image.open(tmp_path / "s.png") as strip:
        assert strip.size == (3 * 80, 60)
        pixels = np.asarray(strip.convert("L"), dtype=float)
    # the first frame (no cloud) differs from the last (cloud)
    assert np.abs(pixels[:, :80] - pixels[:, 160:]).mean() > 0.5
    assert render.render_or_note(render.render_animation, tmp_path / "b.gif", [], slab) is None


def test_render_elsewhere_keeps_what_the_renders_read_and_thins_only_the_animation():
    import importlib.util
    from pathlib import Path
    spec = importlib.util.spec_from_file_location("render_elsewhere", Path(__file__).resolve().parents[1]
                                                  / "scripts" / "render_elsewhere.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rng = np.random.default_rng(0)
    n = 2000
    state = {"position": rng.random((n, 3)), "cloud": np.where(rng.random(n) < 0.3, 1e-3, 0.0), "mass": np.ones(n),
             "velocity": rng.random((n, 3)), "id": np.arange(n), "level": np.zeros(n, int)}
    whole = mod._cut(state, False)
    assert set(whole) == {"position", "cloud", "mass", "level"} and len(whole["cloud"]) == n
    frames = mod._cut([(0.0, state), (10.0, state)], False)
    kept = frames[1][1]
    assert [t for t, _ in frames] == [0.0, 10.0]
    assert (kept["cloud"] > 0).sum() == (state["cloud"] > 0).sum()          # every cloudy particle stays
    assert len(kept["cloud"]) < 0.45 * n                                       # clear ones thinned to about 10%


def test_peer_section_gives_the_ratio_per_thread_count(full_report):
    sec = _sections(full_report[1])["peers"]
    assert "cloudpbf / SPlisHSPlasH" in sec and "1.35" in sec       # 5.48e5 / 4.06e5
    assert ">GPU<" in sec                                            # threads 0: the GPU row


def _section_page(out, section_id):
    """OUT/index.html with one study section alone (the page's summary and environment around it): the
    section as the whole page has it, in a fraction of the page's build time."""
    import dataclasses

    from cloudpbf.report import build
    from cloudpbf.studies.page import catalogue
    whole = catalogue()
    return build.build_report(out, dataclasses.replace(
        whole, sections=tuple(s for s in whole.sections if s.id == section_id), cards=()))


def _compare_page(out):
    return _section_page(out, "compare")


def test_compare_section_draws_the_full_domain_convergence_when_its_csv_is_there(tmp_path, full_report):
    import shutil
    out = tmp_path / "study"
    shutil.copytree(full_report[0] / "data", out / "data")
    before = _sections(_compare_page(out).read_text())["compare"]
    assert before == _sections(full_report[1])["compare"]         # the section alone is the section of the page
    rows = [{"solver": m, "method": m, "parameter": p, "resolution_m": r, "stable": True, "cover_mean": 0.6,
             "lwp_mean": 0.3, "cloud_base_mean": 1100.0, "cloud_top_mean": 2700.0, "device": DEVICE, "commit": COMMIT}
            for m, p in (("particles", "spacing"), ("grid", "cells")) for r in (68.0, 54.0, 34.0)]
    pd.DataFrame(rows).to_csv(out / "data" / "convergence.csv", index=False)
    after = _sections(_compare_page(out).read_text())["compare"]
    assert after.count("<img") == before.count("<img") + 1
    assert "Convergence in the full domain (convergence.csv" in after and COMMIT[:7] in after
    assert "Order of convergence" in after and "flat: no change with h" in after      # flat series: no order
    # per-seed rows beside the means: the particles' cover follows 0.6 + 0.1 (h / 34)^2, the grid stays flat
    rows = [{"solver": m, "method": m, "parameter": p, "resolution_m": r, "stable": True, "seed": str(seed),
             "cover_mean": (0.6 + 0.1 * (r / 34.0) ** 2 if m == "particles" else 0.6) + 0.001 * seed,
             "device": DEVICE, "commit": COMMIT}
            for m, p in (("particles", "spacing"), ("grid", "cells")) for r in (68.0, 54.0, 43.0, 34.0) for seed in range(3)]
    frame = pd.DataFrame(rows)
    means = frame.groupby(["solver", "method", "parameter", "resolution_m", "stable", "device", "commit"],
                          as_index=False)["cover_mean"].mean().assign(seed="mean")
    pd.concat([frame, means]).to_csv(out / "data" / "convergence.csv", index=False)
    seeded = _sections(_compare_page(out).read_text())["compare"]
    assert "mean over 3 seeds" in seeded and "bootstrap, 3 seeds" in seeded
    assert "<td>2 [2, 2]</td>" in seeded                                  # p = 2 exactly: the interval closes on it


def test_shallow_cumulus_section_shows_the_statistics_beside_the_les_cases_and_the_renders(full_report):
    sec = _sections(full_report[1])["shallow_cumulus"]
    assert "BOMEX" in sec and "ARM" in sec and "Siebesma et al. 2003" in sec
    assert "cover / peak" in sec and "LWP (g/m²)" in sec
    assert sec.count("<img") == 3          # the cover and profile plot, the volume and the particle render


def test_shallow_cumulus_section_sets_the_grid_beside_the_particles_of_the_same_seeds(tmp_path, full_report):
    import shutil
    out = tmp_path / "study"
    shutil.copytree(full_report[0] / "data", out / "data")
    pd.DataFrame([{"solver": "grid", "seed": "0", "cells": 94, "cover_mean": 0.10, "cloud_base_m": 1150.0},
                  {"solver": "grid", "seed": "mean", "cells": 94, "cover_mean": 0.10, "cloud_base_m": 1150.0}]
                 ).assign(device=DEVICE, commit=COMMIT).to_csv(out / "data" / "shallow_cumulus_grid.csv", index=False)
    sec = _sections(_section_page(out, "shallow_cumulus").read_text())["shallow_cumulus"]
    assert "particles (seeds 0)" in sec and "grid, 94³ cells (seeds 0)" in sec
    assert "<td>0.12</td>" in sec and "<td>0.1</td>" in sec      # seed 0's particle cover beside the grid's


def test_cycling_renders_are_one_side_by_side_figure_with_missing_cells_marked(tmp_path, full_report):
    """Example 2's renders: the modes that have any render become rows (peak | clearest moment after it) of one
    figure; a mode with no render is left out, a missing cell is drawn as 'not rendered'."""
    import base64
    import io
    import shutil

    import matplotlib.pyplot as plt
    out = tmp_path / "study"
    shutil.copytree(full_report[0] / "data", out / "data")
    pd.DataFrame({"solver": ["particles", "particles"], "mode": ["non-adaptive", "adaptive"], "seed": [0, 0],
                  "cycles": [3, 2], "peak_cover": [0.6, 0.4], "min_cover": [0.0, 0.01], "device": DEVICE,
                  "commit": COMMIT}).to_csv(out / "data" / "cycling_cycles.csv", index=False)
    before = _sections(_compare_page(out).read_text())["compare"].count("<img")
    for name in ("cycling_non-adaptive_peak", "cycling_non-adaptive_min", "cycling_adaptive_peak"):
        fig, ax = plt.subplots(figsize=(4, 3))
        ax.imshow(np.random.default_rng(1).random((6, 8)))
        fig.savefig(out / "data" / "renders" / f"{name}.png")
        plt.close(fig)
    compare = _sections(_compare_page(out).read_text())["compare"]
    assert compare.count("<img") == before + 1 and "Fig. 5c/d" in compare
    uri = re.search(r'src="data:image/\w+;base64,([^"]+)"[^>]*>(?:(?!<img).)*Fig\. 5c/d', compare, re.S).group(1)
    from PIL import Image
    picture = np.asarray(Image.open(io.BytesIO(base64.b64decode(uri))))
    assert picture.shape[0] > 0.5 * picture.shape[1]          # two rows (the grid row is left out)
    assert picture.shape[0] < 1.0 * picture.shape[1]          # (three rows would be taller than wide)
