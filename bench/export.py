"""Export runs for ParaView and xarray: ``cloudpbf export RUN --format vtu|vtp|netcdf|zarr``.

* ``vtp`` / ``vtu``: every stored snapshot of the run as one VTK file (particles: points with every
  per-particle field; grid: the cell centres with every field), plus ``<name>.pvd``, the time series
  ParaView opens (File > Open the .pvd, the time slider steps through the snapshots in simulated
  seconds).  Units are in each file's field data (``<field>_unit``).
* ``netcdf`` / ``zarr``: one ``xarray.Dataset`` with dimensions ``(time, x, y, z)`` on the cell
  centres, CF attributes on every variable.  Grid runs give their own fields; particle runs give
  their particles deposited with the SPH poly6 kernel (``bench.statistics.deposit``: density,
  temperature, vapor, cloud, velocity) on the grid the grid baseline would use for the scene (one
  cell per particle spacing, or ``--resolution``), so a particle run and a grid run of the same
  scene line up cell by cell: ``xr.open_dataset(a) - xr.open_dataset(b)``.

Python: :func:`run_to_xarray`, :func:`particles_to_xarray`, :func:`combine_solvers` (both solvers'
Datasets along a ``solver`` dimension), :func:`export_run`.

Houdini's ``.bgeo``: no maintained writer exists on PyPI (``partio``'s Python wrapper there dates
from 2021 and has no wheels for current Pythons), so it is not offered; Houdini reads the ``.vtu`` /
``.vtp`` files through its VTK importers or the NetCDF through Python SOPs.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from pbf_cuda.export import FIELD_ATTRS, fields_to_xarray, write_pvd, write_particle_series

__all__ = ["FORMATS", "particles_to_xarray", "run_to_xarray", "combine_solvers", "export_run", "run_info"]

FORMATS = ("vtu", "vtp", "netcdf", "zarr")
SUFFIX = {"vtu": "", "vtp": "", "netcdf": ".nc", "zarr": ".zarr"}
DEPOSITED = ("temperature", "vapor", "cloud")


def _scene_from_identity(identity: Mapping):
    from pbf_cuda.scene import scene_from_dict
    data = json.loads(json.dumps(identity["scene"]))
    return scene_from_dict(data, source=str(identity["scene"].get("scene", {}).get("name", "scene")))


def run_info(run_dir: str | Path) -> dict:
    """The run's ``config.json`` identity (solver, scene, seed, ...) and its snapshot files."""
    run_dir = Path(run_dir)
    config = run_dir / "config.json"
    if not config.exists():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.json); "
                                "run directories are printed by `cloudpbf run`")
    identity = json.loads(config.read_text())["identity"]
    snapshots = sorted((run_dir / "snapshots").glob("step_*.npz"))
    if not snapshots:
        raise FileNotFoundError(f"{run_dir}: no stored snapshots (snapshots/step_*.npz)")
    return {"identity": identity, "solver": identity["solver"], "snapshots": snapshots}


def _load_npz(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def particles_to_xarray(state: Mapping[str, np.ndarray], scene, resolution=None, like=None,
                        time: float | None = None, step: int | None = None, attrs: Mapping | None = None):
    """Particles deposited on a grid as an ``xarray.Dataset`` (the grid baseline's layout).

    The grid: ``like`` (a Dataset whose ``x``, ``y``, ``z`` are cell centres of a regular grid from
    the origin, e.g. ``GridSimulation.to_xarray()``), else ``bench.statistics.grid_for_scene(scene,
    resolution)`` (default: one cell per particle spacing, the grid baseline's default).  Variables:
    ``density`` (kg/m^3) and the Shepard averages of temperature, vapor, cloud and velocity_x/y/z,
    with the CF attributes of :data:`pbf_cuda.export.FIELD_ATTRS`."""
    from bench import statistics
    origin = np.zeros(3)
    if like is not None:
        shape = tuple(int(like.sizes[k]) for k in "xyz")
        centres = [np.asarray(like[k].values, dtype=np.float64) for k in "xyz"]
        cell_size = np.array([c[1] - c[0] if len(c) > 1 else 2 * c[0] for c in centres])
        origin = np.array([c[0] for c in centres]) - cell_size / 2
        for k, c, d in zip("xyz", centres, cell_size):
            if not np.allclose(np.diff(c), d, rtol=1e-9, atol=0):
                raise ValueError(f"like: coordinate {k} is not a regular grid of cell centres")
    else:
        shape, cell_size = statistics.grid_for_scene(scene, resolution)
    fields = {k: state[k] for k in DEPOSITED if k in state}
    vel = np.asarray(state["velocity"], dtype=np.float64)
    for a, axis in enumerate("xyz"):
        fields[f"velocity_{axis}"] = vel[:, a]
    periodic = tuple(b == "periodic" for b in scene.domain.boundary)
    grid = statistics.deposit(state["position"], state["mass"], state["kernel_radius"], fields, shape, cell_size,
                              periodic=periodic, origin=origin)
    org = grid.pop("origin")
    size = grid.pop("cell_size")
    return fields_to_xarray(grid, cell_size=size, origin=org, time=time, step=step, attrs={
        "source": "cloudpbf particles (PBF) deposited with the poly6 kernel", "solver": "particles",
        "scene": scene.name, **dict(attrs or {})})


def _snapshot_dataset(solver: str, snap: dict, scene, resolution, like):
    step = int(snap.get("step", 0))
    time = float(snap.get("time_s", 0.0))
    if solver == "grid":
        fields = {k: v for k, v in snap.items() if k not in ("step", "time_s", "origin")}
        return fields_to_xarray(fields, time=time, step=step, attrs={
            "source": "cloudpbf grid_baseline (Eulerian, jax-cfd)", "solver": "grid", "scene": scene.name})
    if not scene.thermodynamics:
        raise ValueError(f"{scene.name}: NetCDF/zarr export deposits cloud fields and needs a scene with an "
                         "[atmosphere] section; use --format vtu or vtp for plain-fluid runs")
    return particles_to_xarray(snap, scene, resolution=resolution, like=like, time=time, step=step)


def run_to_xarray(run_dir: str | Path, resolution=None, like=None):
    """Every snapshot of a run as one Dataset with dimensions (time, x, y, z); ``step`` is a
    coordinate along time.  Particle runs are deposited (see :func:`particles_to_xarray`)."""
    import xarray as xr
    info = run_info(run_dir)
    scene = _scene_from_identity(info["identity"])
    frames = [_snapshot_dataset(info["solver"], _load_npz(p), scene, resolution, like) for p in info["snapshots"]]
    stacked = []
    for f in frames:
        attrs = dict(f["step"].attrs)
        f = f.expand_dims("time").assign_coords(step=("time", [int(f["step"])], attrs))
        stacked.append(f)
    ds = xr.concat(stacked, dim="time", data_vars="all", coords="minimal", compat="override",
                   combine_attrs="override")
    ident = info["identity"]
    ds.attrs.update({"run": Path(run_dir).name, "seed": -1 if ident.get("seed") is None else int(ident["seed"]),
                     "backend": str(ident.get("backend")), "code": str(ident.get("code")),
                     "steps": int(ident.get("steps", 0))})
    return ds


def combine_solvers(datasets: Mapping[str, object]):
    """Datasets of several solvers on the same coordinates (e.g. ``{"grid": g, "particles": p}``) as one
    Dataset with a leading ``solver`` dimension; variables only one side has are filled with NaN.

    ``ds.cloud.sel(solver="particles") - ds.cloud.sel(solver="grid")`` is then the cell-by-cell
    difference.  Raises ValueError when the coordinates differ."""
    import xarray as xr
    names = list(datasets)
    items = [datasets[n] for n in names]
    for other, name in zip(items[1:], names[1:]):
        for k in "xyz":
            if other.sizes.get(k) != items[0].sizes.get(k) or not np.allclose(other[k].values, items[0][k].values):
                raise ValueError(f"{name}: coordinate {k} differs from {names[0]}'s; deposit the particles "
                                 f"with like=<the grid Dataset>")
    out = xr.concat([d.drop_vars([c for c in ("step",) if c in d.coords]) for d in items],
                    dim=xr.Variable("solver", names), join="outer", combine_attrs="drop_conflicts",
                    data_vars="all", coords="minimal", compat="override")
    for name in out.data_vars:
        if name in FIELD_ATTRS:
            out[name].attrs = dict(FIELD_ATTRS[name])
    out["solver"].attrs["long_name"] = "which solver produced the field"
    return out


def export_run(run_dir: str | Path, fmt: str, out: str | Path | None = None, resolution=None) -> Path:
    """Write a run's snapshots in `fmt` (see :data:`FORMATS`); returns what was written (the .pvd for
    vtu/vtp, the file or store for netcdf/zarr).  Default `out`: ``RUN/export/<run name>`` plus the
    format's suffix (``.nc``, ``.zarr``; a folder for vtu/vtp)."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: allowed {', '.join(FORMATS)}")
    run_dir = Path(run_dir)
    info = run_info(run_dir)
    scene = _scene_from_identity(info["identity"])
    name = f"{info['solver']}-{scene.name}"
    out = Path(out) if out is not None else run_dir / "export" / f"{name}{SUFFIX[fmt]}"
    if fmt in ("vtu", "vtp"):
        frames = [_load_npz(p) for p in info["snapshots"]]
        if info["solver"] == "grid":
            frames = [_grid_points(f) for f in frames]
        return write_particle_series(frames, out, fmt=fmt, name=name, scene_name=scene.name)
    ds = run_to_xarray(run_dir, resolution=resolution)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    if tmp.exists():
        shutil.rmtree(tmp) if tmp.is_dir() else tmp.unlink()
    if fmt == "netcdf":
        ds.to_netcdf(tmp, engine="h5netcdf")
    else:
        ds.to_zarr(tmp, mode="w")
    if out.is_dir():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out


def _grid_points(snap: dict) -> dict:
    """A grid snapshot as 'particles' at its cell centres (for .vtp/.vtu point series)."""
    x, y, z = (np.asarray(snap[k]) for k in "xyz")
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    out = {"position": np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1),
           "step": snap.get("step", 0), "time_s": snap.get("time_s", 0.0)}
    for k, v in snap.items():
        arr = np.asarray(v)
        if arr.ndim == 3:
            out[k] = arr.ravel()
        elif arr.ndim == 4 and k == "velocity":
            out[k] = arr.reshape(-1, 3)
    return out


def load_series(pvd: str | Path) -> list:
    """The meshes of a .pvd series (pyvista), in time order."""
    import pyvista as pv
    from pbf_cuda.export import read_pvd
    return [pv.read(f) for _, f in read_pvd(pvd)]
