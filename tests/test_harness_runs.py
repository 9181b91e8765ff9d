"""The run cache: keys, no work on a second execute, resume after a crash, atomic writes, instability."""
from __future__ import annotations

import json
import os

import numpy as np
import pandas as pd
import pytest

from cloudpbf import runs
from cloudpbf.store import identity
from test_harness_toy import ToySimulation, toy_scene, toy_solver  # noqa: F401  (fixture)


def toy_spec(**changes):
    base = dict(solver="particles", scene=toy_scene(), seed=1, checkpoint_every=5)
    base.update(changes)
    return runs.RunSpec(**base)


def test_snapshot_and_diagnostic_steps():
    spec = toy_spec(keep_snapshots=3)
    assert spec.diagnostic_steps() == [0, 5, 10, 15, 20]
    assert spec.snapshot_steps() == [0, 10, 20]
    assert toy_spec(keep_snapshots=1).snapshot_steps() == [20]
    assert toy_spec(steps=7).diagnostic_steps() == [0, 5, 7]


@pytest.mark.parametrize("field,value,message", [
    ("solver", "lattice", "solver = 'lattice': allowed particles, grid"),
    ("steps", 0, "steps = 0: expected an integer in [1, 10000000]"),
    ("seed", -1, "seed = -1"),
    ("backend", "tpu", "backend = 'tpu': allowed auto, cpu, cuda"),
    ("resolution", (4, 4), "resolution = (4, 4): expected three positive integers"),
])
def test_bad_spec_names_the_field(field, value, message):
    with pytest.raises(ValueError) as err:
        toy_spec(**{field: value})
    assert message in str(err.value)


def test_key_depends_on_what_decides_the_result(toy_solver, tmp_path, monkeypatch):
    spec = toy_spec()
    key = spec.key()
    assert toy_spec().key() == key                                   # stable
    assert toy_spec(checkpoint_every=7).key() == key                 # checkpoints do not change results
    assert toy_spec(seed=2).key() != key
    assert toy_spec(steps=21).key() != key
    assert toy_spec(scene=toy_scene(**{"pbf.iterations": 5})).key() != key
    # the code version: editing a source file of the solver (one its simulation module imports) gives a new key
    (tmp_path / "pbf_cuda").mkdir()
    (tmp_path / "pbf_cuda" / "simulation.py").write_text("from .solver import a\n")
    src = tmp_path / "pbf_cuda" / "solver.py"
    src.write_text("a = 1\n")
    monkeypatch.setattr(identity, "REPO_ROOT", tmp_path)
    runs.code_version.cache_clear()
    before = toy_spec().key()
    src.write_text("a = 2\n")
    runs.code_version.cache_clear()
    assert toy_spec().key() != before
    runs.code_version.cache_clear()


def test_second_execute_does_no_work(toy_solver, tmp_path):
    spec = toy_spec()
    first = runs.execute(spec, tmp_path, quiet=True)
    assert not first.cached and first.stable and first.step == 20
    assert toy_solver.steps_taken == 20
    mtime = (first.path / "result.json").stat().st_mtime_ns
    second = runs.execute(spec, tmp_path, quiet=True)
    assert second.cached and second.path == first.path
    assert toy_solver.steps_taken == 20                               # not one step more
    assert (first.path / "result.json").stat().st_mtime_ns == mtime
    pd.testing.assert_frame_equal(first.stats(), second.stats())


def test_run_directory_layout(toy_solver, tmp_path):
    res = runs.execute(toy_spec(record_steps=True), tmp_path, quiet=True)
    names = {p.name for p in res.path.iterdir()}
    assert {"config.json", "log.txt", "timings.csv", "stats.parquet", "profiles.parquet", "steps.csv",
            "snapshots", "checkpoint.npz", "result.json"} <= names
    assert res.path.name.startswith("particles-growing-") and len(res.path.name.split("-")[-1]) == 16
    stats = res.stats()
    assert list(stats["step"]) == [0, 5, 10, 15, 20]
    assert {"mean_height", "max_speed", "min_position_y", "level_0", "time_s"} <= set(stats.columns)
    steps = res.steps_table()
    assert list(steps["step"]) == list(range(1, 21))                  # stats() after every step
    prof = res.profiles()
    assert len(prof) == 5 * 4 and {"z", "fraction"} <= set(prof.columns)
    np.testing.assert_allclose(prof.groupby("step")["fraction"].sum(), 1.0)
    assert res.timings()["pbf"]["count"] == 20
    assert [p.name for p in res.snapshot_paths()] == ["step_000000.npz", "step_000010.npz", "step_000020.npz"]
    config = json.loads((res.path / "config.json").read_text())
    assert config["identity"]["seed"] == 1 and config["key"].startswith(res.path.name.split("-")[-1])


class Crash(RuntimeError):
    pass


def crash_at(step):
    def hook(s):
        if s >= step:
            raise Crash(f"simulated crash at step {s}")
    return hook


def test_resume_after_crash_gives_the_uninterrupted_result(toy_solver, tmp_path):
    spec = toy_spec(checkpoint_every=10)       # diagnostics at 5, 10, 15; the crash after 15 loses 11..15
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path / "a", quiet=True, on_step=crash_at(12))
    d = spec.directory(tmp_path / "a")
    assert not (d / "result.json").exists() and not (d / "stats.parquet").exists()
    assert json.loads((d / "progress.json").read_text())["step"] == 10
    toy_solver.steps_taken = 0
    resumed = runs.execute(spec, tmp_path / "a", quiet=True)
    assert resumed.resumed_from == 10 and toy_solver.steps_taken == 10
    straight = runs.execute(spec, tmp_path / "b", quiet=True)
    assert straight.resumed_from is None
    np.testing.assert_array_equal(resumed.snapshot()["position"], straight.snapshot()["position"])
    pd.testing.assert_frame_equal(resumed.stats(), straight.stats())
    pd.testing.assert_frame_equal(resumed.profiles(), straight.profiles())
    assert resumed.timings()["pbf"]["count"] == 20                    # timings of both segments
    assert "resume from checkpoint at step 10" in (d / "log.txt").read_text()


def test_inconsistent_checkpoint_restarts_from_zero(toy_solver, tmp_path):
    spec = toy_spec()
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path, quiet=True, on_step=crash_at(12))
    d = spec.directory(tmp_path)
    prog = json.loads((d / "progress.json").read_text())
    runs.atomic_write_json(d / "progress.json", {**prog, "step": 5})   # as if the crash came between the two
    toy_solver.steps_taken = 0
    res = runs.execute(spec, tmp_path, quiet=True)
    assert res.resumed_from is None and toy_solver.steps_taken == 20


def test_atomic_write_keeps_old_content_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "result.json"
    runs.atomic_write_json(target, {"a": 1})

    def broken_replace(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        runs.atomic_write_json(target, {"a": 2})
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]   # no temporary left behind


def test_failed_final_write_leaves_no_result(toy_solver, tmp_path, monkeypatch):
    real_replace = os.replace

    def replace(src, dst):
        if str(dst).endswith("result.json"):
            raise OSError("killed while writing result.json")
        real_replace(src, dst)
    monkeypatch.setattr(os, "replace", replace)
    spec = toy_spec()
    with pytest.raises(OSError):
        runs.execute(spec, tmp_path, quiet=True)
    d = spec.directory(tmp_path)
    assert not (d / "result.json").exists()
    assert not [p for p in d.iterdir() if p.name.startswith(".result.json")]
    monkeypatch.setattr(os, "replace", real_replace)
    assert runs.execute(spec, tmp_path, quiet=True).stable


def test_instability_is_recorded_with_step_and_particles(toy_solver, tmp_path):
    scene = toy_scene(**{"time.dt": 150.0, "pbf.max_velocity": 1e6, "domain.size": [600.0, 600.0, 600.0],
                         "domain.boundary": ["periodic"] * 3})           # no wall to escape through
    spec = toy_spec(scene=scene, checkpoint_every=2, snapshot_every=2)
    res = runs.execute(spec, tmp_path, quiet=True)
    assert res.stable is False and "velocity" in res.reason
    assert res.particles and res.step > res.last_good_step >= 0
    stats = res.stats()
    assert stats["step"].max() < res.step
    assert np.isfinite(stats.select_dtypes("number").to_numpy()).all()  # no NaN or Inf stored as data
    assert (res.path / "checkpoint.npz").exists()                     # the last good checkpoint stays
    before = toy_solver.steps_taken
    assert runs.execute(spec, tmp_path, quiet=True).cached and toy_solver.steps_taken == before


def test_particles_escaping_a_wall_are_caught_at_their_step(toy_solver, tmp_path):
    scene = toy_scene(**{"pbf.gravity": [0.0, -20.0, 0.0]})
    res = runs.execute(toy_spec(scene=scene, record_steps=True), tmp_path, quiet=True)
    assert res.stable is False and "escaping the domain" in res.reason and res.particles
    steps = res.steps_table()
    h = scene.kernel_radius
    assert steps["min_position_y"].min() >= -h                       # every stored step was inside
    assert res.step == steps["step"].max() + 1                        # caught at the first step outside


# ---- the same guarantees with the compiled particle solver ---------------------------------------------
def _solver_or_skip():
    try:
        from pbf_cuda.simulation import available_backends
        available_backends()
    except ImportError as exc:
        pytest.skip(f"the particle solver is not built: {exc}")


def small_cloud_scene(**overrides):
    """growing resampled to ~2700 particles: about 20 ms a step on one CPU core."""
    from cloudpbf.studies.scales import scale_scene
    from pbf_cuda.scene import load_scene
    scene = scale_scene(load_scene("growing"), 3000)
    return scene.replace(**{"time.steps": 12, "time.snapshot_every": 4, **overrides})


def test_real_solver_resume_is_bit_exact(tmp_path):
    _solver_or_skip()
    # diagnostics every 2 steps, checkpoints every 4: the crash after step 6 loses steps 5 and 6
    spec = runs.RunSpec("particles", small_cloud_scene(), backend="cpu", seed=4, snapshot_every=2,
                        checkpoint_every=4)
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path / "a", quiet=True, on_step=crash_at(6))
    resumed = runs.execute(spec, tmp_path / "a", quiet=True)
    assert resumed.resumed_from == 4 and resumed.stable
    straight = runs.execute(spec, tmp_path / "b", quiet=True)
    a, b = resumed.snapshot(), straight.snapshot()
    order_a, order_b = np.argsort(a["id"]), np.argsort(b["id"])      # the solver re-sorts particles by cell
    for name in ("position", "velocity", "temperature", "vapor", "cloud"):
        np.testing.assert_array_equal(a[name][order_a], b[name][order_b], err_msg=name)
    cols = ["step", "time_s", "cloud_cover", "total_water", "total_heat", "density_error_mean"]
    pd.testing.assert_frame_equal(resumed.stats()[cols], straight.stats()[cols])


def test_real_solver_instability_is_recorded_without_nan(tmp_path):
    _solver_or_skip()
    # 100 K/s of ground heating (2000 times the paper's): the heated layer blows up within a few steps
    scene = small_cloud_scene(**{"atmosphere.heating_rate": 100.0, "time.steps": 40, "time.snapshot_every": 1})
    res = runs.execute(runs.RunSpec("particles", scene, backend="cpu", seed=0, record_steps=True), tmp_path,
                       quiet=True)
    assert res.stable is False and res.reason and 1 < res.step < 40
    assert res.step > res.last_good_step
    stats = res.stats()
    assert stats["step"].max() <= res.last_good_step
    numeric = stats.drop(columns=["cloud_base", "cloud_top", "base_p10", "top_p90"], errors="ignore")
    assert np.isfinite(numeric.select_dtypes("number").to_numpy()).all()
    steps = res.steps_table()
    assert steps["step"].max() < res.step and np.isfinite(steps.select_dtypes("number").to_numpy()).all()
    if "escaping" not in res.reason:
        assert res.particles                                                  # the solver names them


def test_full_adaptive_capacity_is_logged_and_the_run_goes_on(tmp_path):
    _solver_or_skip()
    from pbf_cuda.scene import load_scene
    scene = load_scene("growing_adaptive", **{
        "domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "atmosphere.initial_vapor_ratio": 1.2,
        "adaptive.capacity": 1.0, "time.steps": 4, "time.snapshot_every": 2})
    res = runs.execute(runs.RunSpec("particles", scene, backend="cpu", seed=0, diagnostics=False), tmp_path,
                       quiet=True)
    assert res.stable and res.step == 4
    assert res.split_capacity_rejects > 0
    log = (res.path / "log.txt").read_text()
    assert "adaptive capacity full at step" in log and "adaptive.capacity = 1.0" in log
