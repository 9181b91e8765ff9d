"""grid_baseline.GridSimulation: API, output formats, snapshots, timing modes, checks."""
import json

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("jax_cfd")

from grid_baseline import GridSimulation, InstabilityError, grid_shape  # noqa: E402
from pbf_cuda.scene import SceneError, load_scene  # noqa: E402

SMALL = (12, 10, 8)


@pytest.fixture(scope="module")
def cloudy_scene():
    return load_scene("growing").replace(**{"atmosphere.initial_vapor_ratio": 1.02,
                                            "atmosphere.heating_rate": 0.3,
                                            "atmosphere.heating_depth": 500.0,
                                            "time.snapshot_every": 4})


@pytest.fixture(scope="module")
def sim(cloudy_scene):
    s = GridSimulation(cloudy_scene, resolution=SMALL, dtype="float64", device="cpu")
    s.step(6)
    return s


def test_grid_shape_from_scene():
    sc = load_scene("parcel")   # 1600 x 1600 x 300 m, spacing 50 m
    assert grid_shape(sc) == (32, 32, 6)
    assert grid_shape(sc, cells_per_spacing=2.0) == (64, 64, 12)
    assert grid_shape(sc, cells_per_spacing=0.5) == (16, 16, 3)
    assert grid_shape(sc, resolution=(8, 9, 10)) == (8, 9, 10)
    assert grid_shape(load_scene("growing")) == (94, 94, 94)     # round(3200 / 34)
    with pytest.raises(ValueError):
        grid_shape(sc, resolution=(8, 1, 8))
    with pytest.raises(ValueError):
        grid_shape(sc, cells_per_spacing=0.0)


def test_fields_and_particle_format(sim):
    f = sim.fields()
    for k in ("temperature", "potential_temperature", "vapor", "cloud"):
        assert f[k].shape == SMALL and f[k].dtype == np.float64
    assert f["velocity"].shape == SMALL + (3,)
    assert f["x"].shape == (SMALL[0],) and f["y"][0] == pytest.approx(0.5 * 3200 / SMALL[1])
    st = sim.state()
    n = int(np.prod(SMALL))
    assert st["position"].shape == (n, 3) and st["velocity"].shape == (n, 3)
    for k in ("temperature", "vapor", "cloud", "mass", "kernel_radius"):
        assert st[k].shape == (n,) and st[k].dtype == np.float32
    assert st["level"].dtype == np.int32 and st["id"].dtype == np.uint32
    np.testing.assert_allclose(st["cloud"], f["cloud"].ravel().astype(np.float32))
    assert st["mass"].sum() == pytest.approx(np.prod(sim.scene.domain.size) * sim.scene.particles.rest_density,
                                             rel=1e-6)


def test_stats_and_timings(sim):
    s = sim.stats()
    assert s["step"] == 6 and s["time"] == pytest.approx(6 * sim.scene.time.dt)
    assert s["total_cloud"] > 0 and s["cloud_cells"] > 0 and s["cloud_base"] <= s["cloud_top"]
    assert s["dtype"] == "float64" and s["device"] == "cpu" and s["backend"] == "grid-cpu"
    assert s["divergence_rel"] < 1e-10
    t = sim.timings()
    assert set(t) == {"step"} and t["step"]["count"] == 6 and t["step"]["mean_ms"] > 0
    assert sim.compile_seconds > 0


def test_snapshot_round_trip(sim, tmp_path):
    path = sim.save(tmp_path / "snap.npz")
    other = GridSimulation.load(path, device="cpu")
    assert other.step_count == sim.step_count and other.shape == sim.shape
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        assert meta["solver"] == "grid_baseline" and meta["step"] == sim.step_count
        assert z["cloud"].dtype == np.float32 and z["raw_ux"].dtype == np.float64
    sim.step(3)      # (the last test that uses the shared simulation)
    other.step(3)
    for k in ("temperature", "vapor", "cloud", "velocity"):
        np.testing.assert_array_equal(sim.fields()[k], other.fields()[k])
    assert other.budget_totals() == sim.budget_totals()            # the snapshot carries the budget's totals
    assert sim.budget_totals()["heat_source_total"] > 0.0


def test_run_writes_snapshots_and_stats(cloudy_scene, tmp_path):
    s = GridSimulation(cloudy_scene, resolution=SMALL, dtype="float64", device="cpu")
    rows = s.run(8, out_dir=tmp_path, stats_every=2)
    assert [r["step"] for r in rows] == [0, 2, 4, 6, 8]
    names = sorted(p.name for p in tmp_path.glob("snapshot_*.npz"))
    assert names == ["snapshot_000000.npz", "snapshot_000004.npz", "snapshot_000008.npz"]
    lines = (tmp_path / "stats.csv").read_text().splitlines()
    assert lines[0].startswith("step,time,total_water") and len(lines) == 6
    assert "step" in json.loads((tmp_path / "timings.json").read_text())


def test_phase_timing_mode_gives_the_same_state(cloudy_scene):
    a = GridSimulation(cloudy_scene, resolution=SMALL, dtype="float64", device="cpu", timing="phases")
    b = GridSimulation(cloudy_scene, resolution=SMALL, dtype="float64", device="cpu")
    a.step(4)
    b.step(4)
    t = a.timings()
    assert set(t) == {"advection", "physics", "projection", "step"}
    assert all(t[k]["count"] == 4 for k in t)
    for k in ("temperature", "vapor", "cloud", "velocity"):
        np.testing.assert_allclose(a.fields()[k], b.fields()[k], rtol=1e-12, atol=1e-12)
    sa, sb = a.stats(), b.stats()
    for k in ("heat_source", "heat_latent", "heat_numerical", "heat_source_total", "heat_latent_total"):
        assert sa[k] == pytest.approx(sb[k], rel=1e-9, abs=1e-15), k     # one budget in both timing modes


def test_seed_moves_the_heating_pattern():
    a = GridSimulation("parcel", device="cpu", dtype="float64")
    b = GridSimulation("parcel", seed=5, device="cpu", dtype="float64")
    assert a.scene.atmosphere.noise_offset == [0.0, 0.0]
    assert b.scene.atmosphere.noise_offset != [0.0, 0.0]
    ha, hb = np.asarray(a._aux["heat"]), np.asarray(b._aux["heat"])
    assert ha.shape == hb.shape and not np.allclose(ha, hb)
    # heated below heating_depth = 60 m: all of the lowest 50 m cell and a fifth of the next, at S_e max(0, 1 + a n)
    assert (ha[:, 2:, :] == 0).all() and ha[:, 0, :].max() <= 0.02 * 2.0 + 1e-12
    assert np.allclose(ha[:, 1, :], 0.2 * ha[:, 0, :], rtol=1e-12)


def test_instability_is_reported():
    sc = load_scene("stratified").replace(**{"pbf.max_velocity": 0.1})
    s = GridSimulation(sc, device="cpu", dtype="float64")
    with pytest.raises(InstabilityError) as e:
        s.step(2)
    assert e.value.step == 1 and "pbf.max_velocity" in e.value.reason


def test_scene_without_atmosphere_is_refused():
    with pytest.raises(SceneError, match="atmosphere"):
        GridSimulation("dam_break")
