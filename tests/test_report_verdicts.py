"""The report's verdicts from small inputs: Table 1's rows and their intervals, the stability map's usable
region, the adaptive front's card from the adaptive-pareto study or, without it, the sweep's."""
import json
import re

import pandas as pd

from cloudpbf.studies.page import build_report

DEVICE, COMMIT = "Synthetic CPU (2 threads)", "abc123def456"


def _sections(page):
    """section id -> its HTML."""
    parts = re.split(r'<section id="', page)[1:]
    return {p.split('"', 1)[0]: p for p in parts}


def test_table1_shows_the_best_variant_row_beside_the_paper_rows(tmp_path):
    """A fifth Table 1 row (the adaptive study's best variant) is drawn as 'adaptive (name)', compared with the
    paper's adaptive row and its example's non-adaptive row, and leaves the paper rows' speed-ups alone."""
    from cloudpbf.report.common import step_time_ratios
    rows = pd.DataFrame({"example": ["growing"] * 3, "mode": ["non-adaptive", "adaptive", "adaptive"],
                         "variant": ["", "", "thermal-68m"], "total_ms": [8.0, 4.0, 5.0]})
    assert step_time_ratios(rows) == {"growing": 2.0}
    data = tmp_path / "data"
    data.mkdir()
    rows.assign(figure=["5a", "5b", "5b"], max_particles=[830584, 176488, 140000], pbf_ms=[7.0, 3.0, 4.0],
                device=DEVICE, commit=COMMIT).to_csv(data / "table1.csv", index=False)
    html = build_report(tmp_path).read_text()
    sections = _sections(html)
    assert "adaptive (thermal-68m)" in sections["table1"] and f"{1e3 * 140000 / 5.0:.4g}" in sections["table1"]
    assert "step-time ratio non-adaptive / adaptive" in sections["adaptive"] and "<td>2</td>" in sections["adaptive"]
    assert "speedup" not in sections["adaptive"]


def test_stress_usable_needs_the_converged_reference_and_never_an_unstable_run(tmp_path):
    """usable = stable and within the bound of the converged reference (the maps and the card say which bound);
    a row marked unstable is never shown as usable, even where the CSV says usable."""
    data = tmp_path / "data"
    data.mkdir()
    pd.DataFrame({"parameter": "dt", "value": [1.0, 2.0, 4.0, 8.0], "stable": [True, True, True, False],
                  "usable": [True, True, False, True], "dt": [1.0, 2.0, 4.0, 8.0],
                  "reference_dt": [0.25, 0.5, 1.0, 2.0], "reference_iterations": 16,
                  "reference_error": [0.01, 0.05, 0.6, None], "density_error_max": 0.001,
                  "device": DEVICE, "commit": COMMIT}).to_csv(data / "stress.csv", index=False)
    sections = _sections(build_report(tmp_path).read_text())
    expected = ("Largest usable dt: 2 s (usable: error against a converged reference (dt/4, 16 iterations, same "
                "simulated time) &lt;= 0.1")
    assert expected in sections["stress"] and expected in sections["summary"]
    assert "largest stable dt (no blow-up, accuracy aside): 4 s" in sections["stress"]
    from cloudpbf.studies.stress import stress_frame
    frame = stress_frame(pd.read_csv(data / "stress.csv"))
    assert frame["usable"].tolist() == [True, True, False, False]      # 8 s: unstable, whatever the CSV says


def test_sweep_verdict_card_links_to_the_data_behind_it_and_says_no_difference(tmp_path):
    """Without the adaptive-pareto study the adaptive card is the sweep's: its links lead to the sweep section and
    its JSON (never to a section without data), and three single ratios of 2.00, 0.82 and 0.98 measure no
    difference."""
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "sweep_verdict.json").write_text(json.dumps({
        "metric": "error_self", "comparisons": [{"error": e, "speedup": r} for e, r in
                                                ((0.3, 2.0), (0.2, 0.82), (0.1, 0.98))]}))
    summary = _sections(build_report(tmp_path).read_text())["summary"]
    card = summary[summary.index('id="card-adaptive_front"'):summary.index('id="card-compare"')]
    assert "no difference measured" in card and "1.02x slower" not in card and 'class="card warn"' in summary
    links = re.findall(r'<a href="([^"]+)">', card)
    assert links == ["#sweep", "data/sweep_verdict.json"]


def test_adaptive_card_gives_ms_per_step_as_the_median_over_seeds_with_its_spread(tmp_path):
    from cloudpbf.report.common import Inputs
    from cloudpbf.studies.adaptive_pareto.report import _seed_ms
    (tmp_path / "data").mkdir()
    pd.DataFrame({"config": ["best"] * 4 + ["other"], "seed": [0, 1, 2, 3, 0],
                  "stable": [True, True, True, False, True],
                  "ms_per_step": [1.0, 1.2, 1.1, 9.0, 5.0]}).to_csv(tmp_path / "data" / "adaptive_pareto.csv",
                                                                  index=False)
    text = _seed_ms(Inputs(tmp_path), "", {"name": "best", "ms_per_step": 1.1})
    assert text.startswith("1.1 ms per step (median over 3 seeds, 5-95%: 1.01-1.19)")     # the unstable seed left out
    assert _seed_ms(Inputs(tmp_path), "_cumulus", {"name": "best", "ms_per_step": 1.1}) == (
        "1.1 ms per step (mean over seeds)")


def test_table1_speedup_carries_the_interval_of_the_per_step_spread(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    pd.DataFrame({"example": ["growing"], "mode": ["non-adaptive"], "variant": "", "max_particles": [830584],
                  "total_ms": [3.8], "step_ms_median": [3.8], "step_ms_p05": [3.6], "step_ms_p95": [4.0],
                  "timed_steps": [495], "scale": "gpu", "device": "NVIDIA H100", "commit": COMMIT}).to_csv(
        data / "table1.csv", index=False)
    summary = _sections(build_report(tmp_path).read_text())["summary"]
    assert f"growing non-adaptive {1218.95 / 3.8:.3g}x [{1218.95 / 4.0:.3g}, {1218.95 / 3.6:.3g}]" in summary
    assert "3.8 ms per step (median over 495 timed steps, 5-95%: 3.6-4)" in summary
