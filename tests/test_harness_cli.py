"""The cloudpbf command line: clear messages and exit code 2 for bad arguments; run goes through the cache."""
from __future__ import annotations

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from cloudpbf.cli import app
from pbf_cuda.scene import list_scenes
from test_harness_toy import toy_solver  # noqa: F401  (fixture)

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, list(args), catch_exceptions=False)


@pytest.mark.parametrize("args,expected", [
    (["run", "nosuch"], "unknown scene 'nosuch'; shipped scenes: " + ", ".join(list_scenes())),
    (["run", "growing", "--steps", "0"], "Invalid value for '--steps': 0 is not in the range 1<=x<=10000000"),
    (["run", "growing", "--seed", "-3"], "Invalid value for '--seed'"),
    (["run", "growing", "--set", "pbf.iterations=500"], "pbf.iterations = 500 is out of range: allowed [1, 200]"),
    (["run", "growing", "--set", "pbf.colour=3"], "unknown field pbf.colour"),
    (["run", "growing", "--set", "iterations"], "'iterations': expected section.field=value"),
    (["run", "dam_break", "--solver", "grid"], "the grid baseline runs cloud scenes only"),
    (["run", "growing", "--backend", "tpu"], "Invalid value for '--backend': 'tpu' is not one of"),
    (["run", "growing", "--particles", "5"], "--particles 5: "),
    (["demo", "--scale", "huge"], "Invalid value for '--scale': 'huge' is not one of 'auto', 'smoke', 'cpu', 'gpu'"),
    (["demo", "--only", "table1,plots"], "'plots': allowed table1, scaling, compare, shallow-cumulus, sweep, stress, renders"),
    (["demo", "--workers", "0"], "Invalid value for '--workers'"),
    (["compare", "growing", "--seeds", "3"], "Invalid value for '--seeds': 3 is not in the range 5<=x<=1000"),
    (["compare", "nosuch"], "unknown scene 'nosuch'"),
    (["scaling", "--sizes", "1000,abc"], "expected comma-separated integers"),
    (["scaling", "--sizes", "10"], "every size must be an integer >= 100"),
    (["report", "--out", "/nonexistent/cloudpbf"], "/nonexistent/cloudpbf/data does not exist"),
    (["frobnicate"], "No such command 'frobnicate'"),
])
def test_bad_arguments_exit_2_with_a_clear_message(args, expected):
    result = invoke(*args)
    assert result.exit_code == 2, result.output
    assert expected in " ".join(result.output.split()), result.output


def test_compare_rejects_a_scene_without_clouds(tmp_path):
    result = invoke("compare", "dam_break", "--scale", "smoke", "--out", str(tmp_path), "--scheduler", "inline")
    assert result.exit_code == 2
    assert "compare needs a cloud scene" in result.output


def test_scenes_lists_every_shipped_scene():
    result = invoke("scenes")
    assert result.exit_code == 0
    listed = [line.split()[0] for line in result.output.splitlines()]
    assert listed == list_scenes()


def test_run_twice_second_is_cached(toy_solver, tmp_path):
    args = ["run", "growing", "--particles", "3000", "--steps", "4", "--set", "time.snapshot_every=2",
            "--runs-root", str(tmp_path), "--quiet"]
    first = invoke(*args)
    assert first.exit_code == 0, first.output
    assert "(cached)" not in first.output and toy_solver.steps_taken == 4
    second = invoke(*args)
    assert second.exit_code == 0 and "(cached)" in second.output
    assert toy_solver.steps_taken == 4


def test_unstable_run_exits_1_and_names_step_and_particles(toy_solver, tmp_path):
    result = invoke("run", "growing", "--particles", "3000", "--steps", "20", "--runs-root", str(tmp_path),
                    "--set", "time.dt=150", "--set", "pbf.max_velocity=1e6", "--set",
                    'domain.boundary=["periodic","periodic","periodic"]', "--quiet")
    assert result.exit_code == 1
    assert "UNSTABLE at step" in result.output and "velocity above pbf.max_velocity; particles: " in result.output


def test_console_entry_point_returns_exit_code_2():
    proc = subprocess.run([sys.executable, "-m", "cloudpbf.cli", "run", "nosuch"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2
    assert "unknown scene 'nosuch'" in proc.stderr
