"""--gpus: one dask-cuda worker per GPU.  The CPU-side logic (parsing, the device selection, the error
paths, what the cluster factory is asked for) with a fake factory; the GPUs themselves are exercised by
`cloudpbf multigpu-sweep` on a GPU machine."""
from __future__ import annotations

import sys

import pandas as pd
import pytest
from typer.testing import CliRunner

from cloudpbf import runs
from cloudpbf.cli import app
from cloudpbf.studies import context, multigpu
from cloudpbf.studies.context import GpuError, StudyContext, parse_gpus, select_gpus, visible_gpus
from cloudpbf.studies.scales import SCALES
from test_harness_toy import toy_scene, toy_solver  # noqa: F401  (fixture)

runner = CliRunner()


def test_gpus_option_parses_all_or_a_positive_count():
    assert parse_gpus(None) is None
    assert parse_gpus("all") == "all" and parse_gpus(" ALL ") == "all"
    assert parse_gpus("2") == 2 and parse_gpus(3) == 3
    for bad in ("0", "-1", "two", "1.5", "", "all,1"):
        with pytest.raises(GpuError, match="expected 'all' or a number of GPUs"):
            parse_gpus(bad)


def test_devices_follow_cuda_visible_devices(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5,7")
    assert visible_gpus() == ["3", "5", "7"]
    assert select_gpus("all", visible_gpus()) == ["3", "5", "7"]
    assert select_gpus(2, visible_gpus()) == ["3", "5"]          # the first N, in the listed order
    with pytest.raises(GpuError, match="only 3 GPU"):
        select_gpus(4, visible_gpus())
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    with pytest.raises(GpuError, match="no CUDA GPU is visible"):
        select_gpus("all", visible_gpus())


@pytest.mark.parametrize("command,env,args,expected", [
    *[(c, "", ["--gpus", "all"], "no CUDA GPU is visible") for c in ("sweep", "stress", "compare", "demo")],
    ("sweep", "0,1", ["--gpus", "3"], "only 2 GPU(s) visible"),
    ("sweep", "0,1", ["--gpus", "2"], "needs dask-cuda, which is not installed: pip install 'cloudpbf[multigpu]'"),
    ("sweep", "0,1", ["--gpus", "zero"], "expected 'all' or a number of GPUs"),
    ("sweep", "0,1", ["--gpus", "1", "--scheduler", "inline"], "cannot be combined with --scheduler"),
    ("sweep", "0,1", ["--gpus", "1", "--workers", "2"], "leave --workers out"),
    ("sweep", "0,1", ["--gpus", "1", "--backend", "cpu"], "--backend cpu contradicts it"),
])
def test_gpus_errors_exit_2_naming_the_option(command, env, args, expected, monkeypatch, tmp_path):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", env)
    monkeypatch.setitem(sys.modules, "dask_cuda", None)          # not installed (an import raises)
    out = tmp_path / "out"
    result = runner.invoke(app, [command, "--scale", "smoke", "--out", str(out), *args], catch_exceptions=False)
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.split())
    assert "Invalid value for '--gpus'" in text and expected in text
    assert not out.exists()                                       # refused before anything was written


class FakeCudaCluster:
    """Records what the factory was asked for; a threaded in-process dask cluster does the work."""
    calls = []

    def __new__(cls, devices, env):
        from distributed import LocalCluster
        cls.calls.append((list(devices), dict(env)))
        return LocalCluster(n_workers=len(devices), threads_per_worker=1, processes=False, dashboard_address=None)


def test_the_cluster_factory_gets_one_worker_per_chosen_gpu(toy_solver, monkeypatch, tmp_path):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,4,6")
    FakeCudaCluster.calls.clear()
    ctx = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", gpus="2",
                       quiet=True, cuda_cluster_factory=FakeCudaCluster)
    ctx.check_gpus()                                   # a factory given: dask-cuda is not needed
    specs = [runs.RunSpec("particles", toy_scene(), seed=s) for s in (0, 1, 2)]
    with ctx:
        assert ctx.n_workers() == 2 and "GPUs 2,4" in ctx.cluster_description()
        results = ctx.run_parallel(specs, "gpus")
        assert len(ctx.client().scheduler_info()["workers"]) == 2
    (devices, env), = FakeCudaCluster.calls
    assert devices == ["2", "4"] and env["OMP_NUM_THREADS"].isdigit()
    assert [r.seed for r in results] == [0, 1, 2] and all(r.stable for r in results)


def test_multigpu_sweep_times_each_count_from_an_empty_cache(toy_solver, monkeypatch, tmp_path):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    FakeCudaCluster.calls.clear()
    specs = [runs.RunSpec("particles", toy_scene(), seed=s) for s in range(4)]
    monkeypatch.setattr(multigpu, "sweep_particle_specs", lambda ctx: specs)
    base = StudyContext(out=tmp_path / "out", scale=SCALES["smoke"], runs_root=tmp_path / "runs", quiet=True)
    toy_solver.steps_taken = 0
    frame = multigpu.run_multigpu(base, [1, 2], cuda_cluster_factory=FakeCudaCluster)
    assert [c[0] for c in FakeCudaCluster.calls] == [["0"], ["0", "1"]]
    assert toy_solver.steps_taken == 2 * 4 * toy_scene().time.steps   # every count ran every run itself
    written = pd.read_csv(base.data / "multigpu_sweep.csv")
    assert list(written.columns[:6]) == ["device", "commit", "gpus", "runs", "wall_s", "speedup"]
    assert written["gpus"].tolist() == [1, 2] and written["runs"].tolist() == [4, 4]
    assert written["speedup"].iloc[0] == pytest.approx(1.0)
    assert written["speedup"].iloc[1] == pytest.approx(written["wall_s"].iloc[0] / written["wall_s"].iloc[1])
    assert not (base.out / "multigpu-runs" / "gpus-1").exists()       # the timing caches are removed


def test_default_factory_without_dask_cuda_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_cuda", None)
    with pytest.raises(GpuError, match=r"cloudpbf\[multigpu\]"):
        context.cuda_cluster(["0"], {})
