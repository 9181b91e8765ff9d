"""The peer benchmark (`cloudpbf peers`, cloudpbf/studies/peers.py) without SPlisHSPlasH installed: it says so, times
cloudpbf alone, and refuses bad arguments by name."""
import sys

import pandas as pd
from typer.testing import CliRunner

from cloudpbf.cli import app
from cloudpbf.studies.peers import SPLISH_SCENE, run_peers, splish_available


def test_without_splishsplash_it_says_so_and_times_cloudpbf_alone(tmp_path):
    said = []
    frame = run_peers([1], repeats=1, splish_python=sys.executable, spacing=0.1, echo=said.append)
    if splish_available(sys.executable) is None:
        assert any("SPlisHSPlasH skipped" in line and "peers extra" in line for line in said)
        assert set(frame["tool"]) <= {"cloudpbf", "cloudpbf (cuda)"}
    cpu = frame[frame["tool"] == "cloudpbf"]
    assert len(cpu) == 1 and int(cpu["threads"].iloc[0]) == 1
    # a 1 m cube at 0.1 m spacing, as the peer's fluid block: 10^3 particles, every one stepped
    assert int(cpu["fluid_particles"].iloc[0]) == 1000
    row = cpu.iloc[0]
    assert row["ms_per_step"] > 0 and abs(row["particle_steps_per_s"] * row["ms_per_step"] / 1e3 - 1000) < 1e-6
    assert {"device", "commit", "run"} <= set(frame.columns) and frame["run"].nunique() == 1


def test_the_peer_scene_is_the_dam_break_geometry():
    c = SPLISH_SCENE["Configuration"]
    assert c["simulationMethod"] == 2 and c["PBF"]["minIterations"] == c["PBF"]["maxIterations"] == 4
    block = SPLISH_SCENE["FluidBlocks"][0]
    assert [e - s for s, e in zip(block["start"], block["end"])] == [1.0, 1.0, 1.0]
    assert SPLISH_SCENE["RigidBodies"][0]["scale"] == [4, 3, 1.5] and 2 * c["particleRadius"] == 0.022


def test_bad_arguments_exit_2_naming_the_option(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["peers", "--splish-python", str(tmp_path / "no-python"), "--out", str(tmp_path / "p.csv")])
    assert res.exit_code == 2 and "--splish-python" in res.output
    res = runner.invoke(app, ["peers", "--threads", "0", "--out", str(tmp_path / "p.csv")])
    assert res.exit_code == 2 and "--threads" in res.output
    assert not (tmp_path / "p.csv").exists()


def test_rates_keep_each_run_apart_and_give_both_ratios():
    # Two runs (commits) on one host: the faster repeat of a run never mixes with another run's, and the ratio of
    # the means differs from the ratio of the best repeats exactly as the repeats say.
    from cloudpbf.studies.peers import RATIO, SPLISH, best_rates
    rows = []
    for commit, splish, ours in (("aaa", [100.0, 200.0], [300.0, 300.0]), ("bbb", [400.0, 400.0], [500.0, 700.0])):
        rows += [{"threads": 2, "tool": SPLISH, "device": "cpu", "commit": commit, "particle_steps_per_s": r}
                 for r in splish]
        rows += [{"threads": 2, "tool": "cloudpbf", "device": "cpu", "commit": commit, "particle_steps_per_s": r}
                 for r in ours]
    wide = best_rates(pd.DataFrame(rows)).set_index("commit")
    assert wide.loc["aaa", RATIO] == 1.5 and wide.loc["aaa", RATIO + " (means)"] == 2.0
    assert wide.loc["bbb", RATIO] == 1.75 and wide.loc["bbb", RATIO + " (means)"] == 1.5
    legacy = best_rates(pd.DataFrame(rows).drop(columns="commit"))     # a CSV without the column: one run
    assert legacy[RATIO].iloc[0] == 700.0 / 400.0
