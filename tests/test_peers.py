"""The peer benchmark (`cloudpbf peers`, bench/studies/peers.py) without SPlisHSPlasH installed: it says so, times
cloudpbf alone, and refuses bad arguments by name."""
import sys

import pandas as pd
from typer.testing import CliRunner

from bench.cli import app
from bench.studies.peers import SPLISH_SCENE, run_peers, splish_available


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
    assert {"device", "commit"} <= set(frame.columns)


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
