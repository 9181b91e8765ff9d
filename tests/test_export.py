"""Exports: particle series for ParaView (.pvd + .vtp/.vtu), grid and deposited particle fields as xarray
Datasets with CF attributes, NetCDF/zarr round trips, and `cloudpbf export` on real runs."""
from __future__ import annotations

import json

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
xr = pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")
pytest.importorskip("zarr")

from typer.testing import CliRunner  # noqa: E402

from cloudpbf.cli import app  # noqa: E402
from cloudpbf_io.export import (COORD_ATTRS, FIELD_ATTRS, PARTICLE_UNITS, fields_to_xarray, read_pvd,  # noqa: E402
                             state_to_pyvista, write_particle_series)

runner = CliRunner()


def _fake_state(n, rng, step, time):
    return {"position": rng.uniform(0, 100, (n, 3)).astype(np.float32),
            "velocity": rng.normal(size=(n, 3)).astype(np.float32),
            "temperature": rng.uniform(250, 300, n).astype(np.float32),
            "vapor": rng.uniform(0, 0.02, n).astype(np.float32),
            "cloud": rng.uniform(0, 1e-3, n).astype(np.float32),
            "mass": np.full(n, 2.5, np.float32), "level": rng.integers(0, 3, n).astype(np.int32),
            "kernel_radius": np.full(n, 7.0, np.float32), "id": np.arange(n, dtype=np.uint32),
            "step": np.int64(step), "time_s": np.float64(time)}


@pytest.mark.parametrize("fmt", ["vtp", "vtu"])
def test_particle_series_round_trip(tmp_path, fmt):
    rng = np.random.default_rng(1)
    frames = [_fake_state(50, rng, 0, 0.0), _fake_state(60, rng, 10, 20.0)]
    pvd = write_particle_series(frames, tmp_path / "series", fmt=fmt, name="p", scene_name="toy")
    entries = read_pvd(pvd)
    assert [t for t, _ in entries] == [0.0, 20.0]
    assert [f.name for _, f in entries] == [f"p_000000.{fmt}", f"p_000010.{fmt}"]
    # ParaView's own reader of the collection sees the two time steps
    reader = pv.get_reader(str(pvd))
    assert list(reader.time_values) == [0.0, 20.0]
    for (time, path), frame in zip(entries, frames):
        mesh = pv.read(path)
        assert mesh.n_points == len(frame["id"])
        np.testing.assert_array_equal(mesh.points, frame["position"])
        for name in ("velocity", "temperature", "vapor", "cloud", "mass", "level", "kernel_radius"):
            np.testing.assert_array_equal(mesh.point_data[name], frame[name])
            assert mesh.field_data[f"{name}_unit"][0] == PARTICLE_UNITS[name]
        np.testing.assert_array_equal(mesh.point_data["id"], frame["id"].astype(np.int64))
        assert mesh.field_data["TimeValue"][0] == time
        assert mesh.field_data["step"][0] == frame["step"]
        assert mesh.field_data["scene"][0] == "toy"


def test_fields_to_xarray_has_cf_attributes_and_round_trips(tmp_path):
    rng = np.random.default_rng(2)
    fields = {"temperature": rng.uniform(250, 300, (4, 5, 6)), "cloud": rng.uniform(0, 1e-3, (4, 5, 6)),
              "velocity": rng.normal(size=(4, 5, 6, 3)), "cell_size": np.array([10.0, 20.0, 5.0])}
    ds = fields_to_xarray(fields, time=12.5, step=3)
    np.testing.assert_allclose(ds.x, [5, 15, 25, 35])
    np.testing.assert_allclose(ds.y, 10 + 20 * np.arange(5))
    assert ds.y.attrs["axis"] == "Z" and ds.y.attrs["positive"] == "up" and ds.y.attrs["units"] == "m"
    assert ds.temperature.attrs["standard_name"] == "air_temperature" and ds.temperature.attrs["units"] == "K"
    np.testing.assert_array_equal(ds.velocity_y.values, fields["velocity"][..., 1])
    assert ds.velocity_y.attrs == FIELD_ATTRS["velocity_y"]
    assert float(ds.time) == 12.5 and int(ds.step) == 3 and ds.attrs["Conventions"].startswith("CF-")
    ds.to_netcdf(tmp_path / "f.nc", engine="h5netcdf")
    with xr.open_dataset(tmp_path / "f.nc", engine="h5netcdf") as back:
        xr.testing.assert_identical(back.load(), ds)
    ds.to_zarr(tmp_path / "f.zarr", mode="w")
    with xr.open_zarr(tmp_path / "f.zarr") as back:
        xr.testing.assert_identical(back.load(), ds)


@pytest.fixture(scope="module")
def particle_sim():
    simulation = pytest.importorskip("pbf_cuda.simulation")
    try:
        simulation._core()
    except ImportError:
        pytest.skip("compiled solver not built")
    from pbf_cuda import load_scene
    sim = simulation.Simulation(load_scene("growing").with_particle_count(3000), backend="cpu", seed=2)
    sim.step(2)
    return sim


def test_simulation_to_pyvista_holds_the_state(particle_sim, tmp_path):
    st = particle_sim.state()
    for kind, suffix in (("polydata", ".vtp"), ("unstructured", ".vtu")):
        mesh = particle_sim.to_pyvista(kind)
        mesh.save(tmp_path / f"p{suffix}")
        back = pv.read(tmp_path / f"p{suffix}")
        np.testing.assert_array_equal(back.points, st["position"])
        for name in ("velocity", "temperature", "vapor", "cloud", "mass", "level", "kernel_radius"):
            np.testing.assert_array_equal(back.point_data[name], st[name])
        assert back.field_data["TimeValue"][0] == pytest.approx(particle_sim.time)
        assert back.field_data["temperature_unit"][0] == "K"


def test_particles_and_grid_share_coordinates_and_agree_on_the_initial_atmosphere(particle_sim):
    """Deposited particles and the grid baseline on one labelled grid: at the start both hold the
    scene's environment profile, so their temperatures agree away from the walls."""
    pytest.importorskip("jax_cfd")
    from cloudpbf.export import combine_solvers, particles_to_xarray
    from grid_baseline import GridSimulation
    from pbf_cuda import Simulation
    scene = particle_sim.scene
    grid = GridSimulation(scene, resolution=(8, 8, 8), dtype="float64").to_xarray()
    start = Simulation(scene, backend="cpu", seed=2).state()
    parts = particles_to_xarray(start, scene, like=grid, time=0.0, step=0)
    for k in "xyz":
        np.testing.assert_allclose(parts[k].values, grid[k].values)
        assert parts[k].attrs == COORD_ATTRS[k] == grid[k].attrs
    assert grid.temperature.attrs == parts.temperature.attrs == FIELD_ATTRS["temperature"]
    both = combine_solvers({"grid": grid, "particles": parts})
    assert list(both.solver.values) == ["grid", "particles"]
    assert "density" in both and np.isnan(both.density.sel(solver="grid")).all()
    interior = dict(y=slice(400.0, 2800.0))
    diff = (both.temperature.sel(solver="particles") - both.temperature.sel(solver="grid")).sel(**interior)
    assert float(np.abs(diff).max()) < 1.0               # K, out of a 20 K profile
    vap = (both.vapor.sel(solver="particles") / both.vapor.sel(solver="grid")).sel(**interior)
    assert float(np.abs(vap - 1).max()) < 0.05
    # total mass of the deposited density equals the particles' mass
    cell = np.prod([float(grid[k][1] - grid[k][0]) for k in "xyz"])
    assert float(parts.density.sum()) * cell == pytest.approx(float(start["mass"].astype(np.float64).sum()), rel=1e-9)


def _run(tmp_path, *args):
    res = runner.invoke(app, ["run", *args, "--runs-root", str(tmp_path / "runs"), "--quiet"],
                        catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return next(line.split(": ", 1)[1].split("  ")[0] for line in res.output.splitlines()
                if line.startswith("run directory:"))


def test_cli_export_particle_run_all_formats(particle_sim, tmp_path):
    from pathlib import Path
    run_dir = Path(_run(tmp_path, "growing", "--particles", "2000", "--steps", "4", "--snapshot-every", "2"))
    snaps = sorted((run_dir / "snapshots").glob("step_*.npz"))
    assert len(snaps) >= 2
    res = runner.invoke(app, ["export", str(run_dir), "--format", "vtp", "--out", str(tmp_path / "vtk")])
    assert res.exit_code == 0, res.output
    entries = read_pvd(tmp_path / "vtk" / "particles-growing.pvd")  # --out that does not exist: the export itself
    assert len(entries) == len(snaps)
    with np.load(snaps[-1]) as z:
        last = {k: z[k] for k in z.files}
    mesh = pv.read(entries[-1][1])
    np.testing.assert_array_equal(mesh.points, last["position"])
    np.testing.assert_array_equal(mesh.point_data["cloud"], last["cloud"])
    assert entries[-1][0] == pytest.approx(float(last["time_s"]))

    res = runner.invoke(app, ["export", str(run_dir), "--format", "bgeo", "--out", str(tmp_path / "bgeo")])
    assert res.exit_code == 0, res.output
    from cloudpbf_io.bgeo import read_bgeo
    frames = sorted((tmp_path / "bgeo").glob("particles-growing.*.bgeo"))
    assert len(frames) == len(snaps) and frames[0].name == "particles-growing.0001.bgeo"
    back = read_bgeo(frames[-1])
    assert back.points["P"].tobytes() == last["position"].tobytes()
    assert back.points["cloud"].tobytes() == last["cloud"].tobytes()
    assert back.detail["step"] == int(last["step"])

    for fmt, suffix in (("netcdf", ".nc"), ("zarr", ".zarr")):
        res = runner.invoke(app, ["export", str(run_dir), "--format", fmt])
        assert res.exit_code == 0, res.output
        path = run_dir / "export" / f"particles-growing{suffix}"
        assert f"wrote {path}" in res.output
        ds = xr.open_dataset(path, engine="h5netcdf" if fmt == "netcdf" else "zarr").load()
        assert ds.sizes["time"] == len(snaps) and list(ds.step.values) == [int(p.stem[5:]) for p in snaps]
        assert ds.cloud.attrs["standard_name"] == "cloud_liquid_water_mixing_ratio"
        assert ds.attrs["solver"] == "particles" and ds.attrs["scene"] == "growing"
        from cloudpbf.export import particles_to_xarray
        from pbf_cuda.scene import scene_from_dict
        scene = scene_from_dict(json.loads((run_dir / "config.json").read_text())["identity"]["scene"])
        direct = particles_to_xarray(last, scene)
        np.testing.assert_allclose(ds.temperature.isel(time=-1).values, direct.temperature.values, rtol=1e-12)
        np.testing.assert_allclose(ds.density.isel(time=-1).values, direct.density.values, rtol=1e-12)


def test_cli_export_grid_run_netcdf(tmp_path):
    pytest.importorskip("jax_cfd")
    from pathlib import Path
    run_dir = Path(_run(tmp_path, "growing", "--solver", "grid", "--steps", "2", "--snapshot-every", "1",
                        "--cells-per-spacing", "0.5"))
    res = runner.invoke(app, ["export", str(run_dir), "--format", "netcdf", "--out", str(tmp_path / "g.nc")])
    assert res.exit_code == 0, res.output
    ds = xr.open_dataset(tmp_path / "g.nc", engine="h5netcdf").load()
    snaps = sorted((run_dir / "snapshots").glob("step_*.npz"))
    with np.load(snaps[-1]) as z:
        np.testing.assert_array_equal(ds.cloud.isel(time=-1).values, z["cloud"])
        np.testing.assert_array_equal(ds.velocity_x.isel(time=-1).values, z["velocity"][..., 0])
        np.testing.assert_array_equal(ds.y.values, z["y"])
    assert ds.attrs["solver"] == "grid" and ds.potential_temperature.attrs["units"] == "K"
    res = runner.invoke(app, ["export", str(run_dir), "--format", "vtu", "--out", str(tmp_path / "gv")])
    assert res.exit_code == 0, res.output
    mesh = pv.read(read_pvd(tmp_path / "gv" / "grid-growing.pvd")[-1][1])
    assert mesh.n_points == ds.sizes["x"] * ds.sizes["y"] * ds.sizes["z"]


def _stored_run(root, solver, frames, finished=True):
    """A run directory as `cloudpbf run` leaves it (config.json identity, snapshots/step_*.npz), made
    without the solver, so the export path runs where the compiled solver is absent."""
    from pbf_cuda import load_scene
    from cloudpbf_io.files import json_default
    scene = load_scene("growing").to_dict()
    scene["scene"] = {"name": "growing"}
    run_dir = root / f"{solver}-growing-0123456789abcdef"
    (run_dir / "snapshots").mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps({"identity": {"solver": solver, "scene": scene}},
                                                    default=json_default))
    for frame in frames:
        np.savez(run_dir / "snapshots" / f"step_{int(frame['step']):06d}.npz", **frame)
    if finished:
        from cloudpbf.store.manifest import info_checksum, manifest
        info = {"key": None, "stable": True, "step": int(frames[-1]["step"]), "manifest": manifest(run_dir)}
        info["checksum"] = info_checksum(info)
        (run_dir / "result.json").write_text(json.dumps(info))
    return run_dir


def test_cli_export_bgeo_writes_one_houdini_frame_per_snapshot(tmp_path):
    from cloudpbf_io.bgeo import read_bgeo
    rng = np.random.default_rng(6)
    frames = [_fake_state(40, rng, 0, 0.0), _fake_state(45, rng, 10, 20.0), _fake_state(50, rng, 20, 40.0)]
    run_dir = _stored_run(tmp_path, "particles", frames)
    res = runner.invoke(app, ["export", str(run_dir), "--format", "bgeo"])
    assert res.exit_code == 0, res.output
    folder = run_dir / "export" / "particles-growing-bgeo"
    names = [f"particles-growing.000{i}.bgeo" for i in (1, 2, 3)]
    assert res.output.strip() == f"wrote {folder}: 3 frames, {names[0]} .. {names[-1]}"
    assert sorted(p.name for p in folder.glob("*.bgeo")) == names
    for name, frame in zip(names, frames):
        back = read_bgeo(folder / name)
        assert back.points["P"].tobytes() == frame["position"].tobytes()
        assert back.points["v"].tobytes() == frame["velocity"].tobytes() and back.point_types["v"] == "vector"
        for field in ("temperature", "vapor", "cloud", "mass", "kernel_radius"):
            assert back.points[field].tobytes() == frame[field].tobytes()
        np.testing.assert_array_equal(back.points["id"], frame["id"].astype(np.int64))
        np.testing.assert_array_equal(back.points["level"], frame["level"])
        assert back.detail["step"] == int(frame["step"]) and back.detail["time"] == float(frame["time_s"])
        assert back.detail["scene"] == "growing" and back.detail["temperature_unit"] == "K"
    res = runner.invoke(app, ["export", str(run_dir), "--format", "bgeo", "--out", str(tmp_path / "houdini")])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "houdini").glob("*.bgeo")) == names


def test_cli_export_errors(tmp_path):
    res = runner.invoke(app, ["export", str(tmp_path), "--format", "vtp"])
    assert res.exit_code == 2 and "no run folder there" in res.output
    res = runner.invoke(app, ["export", str(tmp_path), "--format", "obj"])
    assert res.exit_code == 2 and "'obj' is not one of" in res.output and "'bgeo'" in res.output
    grid = {"x": np.arange(2.0), "y": np.arange(3.0), "z": np.arange(2.0), "cloud": np.zeros((2, 3, 2)),
            "step": np.int64(0), "time_s": np.float64(0.0)}
    run_dir = _stored_run(tmp_path, "grid", [grid])
    res = runner.invoke(app, ["export", str(run_dir), "--format", "bgeo"])
    assert res.exit_code == 2, res.output
    message = " ".join(res.output.split())
    assert "'--format'" in message and "a grid run exports as vtu, vtp, netcdf, zarr" in message
    assert not (run_dir / "export").exists()
