"""The benchmark history (cloudpbf.studies.benchmark_history): asv results files read as they are, each
commit against the machine's previous one, a change flagged only when it passes the factor and the two
99% intervals do not overlap; damaged files refused by name."""
import json
from pathlib import Path

import pytest
from hypothesis import given, settings, strategies as st
from typer.testing import CliRunner

from cloudpbf.cli import app
from cloudpbf.studies.benchmark_history import HistoryError, benchmark_history, read_results_file

REPO = Path(__file__).resolve().parents[1]
COLUMNS = ["result", "params", "version", "started_at", "duration", "stats_ci_99_a", "stats_ci_99_b",
           "stats_q_25", "stats_q_75", "stats_number", "stats_repeat", "samples", "profile"]
PARAMS = [["'cpu'", "'cuda'"], ["'growing'", "'growing_adaptive'"], ["64000", "1000000"]]


def write_result(folder: Path, commit: str, date_ms: int, times: list, half_width: list):
    """An asv results file of the step benchmark: times (s) over the product of PARAMS (None: skipped)."""
    folder.mkdir(parents=True, exist_ok=True)
    low = [None if t is None else t - w for t, w in zip(times, half_width)]
    high = [None if t is None else t + w for t, w in zip(times, half_width)]
    entry = [times, PARAMS, "v", 0, 1.0, low, high, None, None, None, None, None, None]
    data = {"commit_hash": commit * 5, "date": date_ms, "result_columns": COLUMNS, "env_name": "existing-py3.12",
            "results": {"step.SolverStep.time_step": entry}, "params": {}, "python": "3.12", "version": 2}
    (folder / f"{commit}-existing-py3.12.json").write_text(json.dumps(data))


@settings(max_examples=30, deadline=None)
@given(base=st.floats(1e-3, 1.0), ratio=st.floats(0.2, 5.0), spread=st.floats(0.0, 0.5))
def test_a_change_is_flagged_exactly_when_it_passes_the_factor_and_the_intervals_part(tmp_path_factory, base, ratio,
                                                                                     spread):
    root = tmp_path_factory.mktemp("results")
    n = 8
    write_result(root / "m", "aaaaaaaa", 1_000, [base] * n, [spread * base] * n)
    write_result(root / "m", "bbbbbbbb", 2_000, [base * ratio] * n, [spread * base * ratio] * n)
    df = benchmark_history(root, factor=1.05)
    later = df[df["commit"] == "bbbbbbbb"]
    assert len(later) == n and later["ratio"].to_numpy() == pytest.approx(ratio, rel=1e-9)
    apart_up = base * ratio * (1 - spread) > base * (1 + spread)
    apart_down = base * ratio * (1 + spread) < base * (1 - spread)
    expected = "slower" if ratio > 1.05 and apart_up else "faster" if ratio < 1 / 1.05 and apart_down else ""
    assert set(later["change"]) == {expected}
    assert df[df["commit"] == "aaaaaaaa"]["change"].eq("").all()   # the first commit has nothing to compare with


def test_skipped_points_are_left_out_and_commits_keep_their_order(tmp_path):
    times = [0.1, None, 0.2, None, None, 0.003, None, 0.004]
    write_result(tmp_path / "m", "bbbbbbbb", 2_000, times, [0.0] * 8)
    write_result(tmp_path / "m", "aaaaaaaa", 1_000, [0.1] * 8, [0.0] * 8)
    df = benchmark_history(tmp_path)
    assert len(read_results_file(tmp_path / "m" / "bbbbbbbb-existing-py3.12.json")) == 4
    assert list(df.drop_duplicates("commit")["commit"]) == ["aaaaaaaa", "bbbbbbbb"]
    # the product's order: (cpu, growing, 64000), (cpu, growing, 1000000), (cpu, growing_adaptive, 64000), ...
    row = df[(df["commit"] == "bbbbbbbb") & (df["backend"] == "cpu") & (df["particles"] == 64000)
             & (df["scene"] == "growing_adaptive")]
    assert row["time_ms"].item() == pytest.approx(200.0) and row["ratio"].item() == pytest.approx(2.0)


@pytest.mark.parametrize("text", ["{", "[]", '{"results": {}}', ""])
def test_a_damaged_results_file_is_refused_by_name(tmp_path, text):
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "broken.json").write_text(text)
    with pytest.raises(HistoryError, match="broken.json"):
        benchmark_history(tmp_path)
    res = CliRunner().invoke(app, ["benchmark-history", "--results", str(tmp_path), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "broken.json" in res.output


def test_the_kept_gpu_history_shows_the_velocity_projection_slowdown():
    # benchmarks/results/gpu-NVIDIA-H100-80GB-HBM3 (docs/benchmarks.md): ecdc7df made the cloud scenes project
    # their velocity (4 CG iterations per step); every CUDA point of that commit is about 2x its parent's.
    df = benchmark_history(REPO / "benchmarks" / "results")
    h100 = df[(df["machine"] == "gpu-NVIDIA-H100-80GB-HBM3") & (df["backend"] == "cuda")]
    step = h100[h100["commit"] == "ecdc7df2"]
    assert len(step) == 6 and set(step["change"]) == {"slower"} and step["ratio"].min() > 1.8
