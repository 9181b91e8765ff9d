"""Export runs for ParaView, Houdini and xarray: ``cloudpbf export RUN --format vtu|vtp|bgeo|netcdf|zarr``.

* ``vtp`` / ``vtu``: every stored snapshot of the run as one VTK file (particles: points with every
  per-particle field; grid: the cell centres with every field), plus ``<name>.pvd``, the time series
  ParaView opens (File > Open the .pvd, the time slider steps through the snapshots in simulated
  seconds).  Units are in each file's field data (``<field>_unit``).
* ``bgeo`` (particle runs only): Houdini's classic binary geometry, one ``<name>.0001.bgeo``,
  ``<name>.0002.bgeo``, ... per snapshot in time order (a File SOP reading ``<name>.$F4.bgeo`` plays
  them), written by :mod:`pbf_cuda.bgeo` (numpy, no partio needed): ``P``, the vector ``v`` (m/s) and
  every other per-particle field under its own name; detail attributes ``time`` (s), ``step``,
  ``scene`` and ``<attribute>_unit``.  A grid run asked for bgeo raises :class:`FormatError`.
* ``netcdf`` / ``zarr``: one ``xarray.Dataset`` with dimensions ``(time, x, y, z)`` on the cell
  centres, CF attributes on every variable.  Grid runs give their own fields; particle runs give
  their particles deposited with the SPH poly6 kernel (``bench.statistics.deposit``: density,
  temperature, vapor, cloud, velocity) on the grid the grid baseline would use for the scene (one
  cell per particle spacing, or ``--resolution``), so a particle run and a grid run of the same
  scene line up cell by cell: ``xr.open_dataset(a) - xr.open_dataset(b)``.

Python: :func:`run_to_xarray`, :func:`particles_to_xarray`, :func:`combine_solvers` (both solvers'
Datasets along a ``solver`` dimension), :func:`export_run`.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Mapping

import numpy as np

from bench.solvers import ADAPTERS, particles_to_xarray  # noqa: F401  (particles_to_xarray: public here too)
from pbf_cuda.export import FIELD_ATTRS, write_bgeo_series, write_particle_series

__all__ = ["FORMATS", "PARTICLE_ONLY", "FormatError", "particles_to_xarray", "run_to_xarray", "combine_solvers",
           "export_run", "run_info"]

FORMATS = ("vtu", "vtp", "bgeo", "netcdf", "zarr")
PARTICLE_ONLY = ("bgeo",)
"""Formats of particle runs only (a grid run has cells, not particles)."""
SUFFIX = {"vtu": "", "vtp": "", "bgeo": "", "netcdf": ".nc", "zarr": ".zarr"}


class FormatError(ValueError):
    """A format the run cannot be exported in (unknown, or bgeo for a grid run)."""


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


def run_to_xarray(run_dir: str | Path, resolution=None, like=None):
    """Every snapshot of a run as one Dataset with dimensions (time, x, y, z); ``step`` is a
    coordinate along time.  Particle runs are deposited (see :func:`particles_to_xarray`)."""
    import xarray as xr
    info = run_info(run_dir)
    scene = _scene_from_identity(info["identity"])
    adapter = ADAPTERS[info["solver"]]
    frames = [adapter.snapshot_dataset(_load_npz(p), scene, resolution=resolution, like=like)
              for p in info["snapshots"]]
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
    vtu/vtp, the folder of ``<name>.NNNN.bgeo`` files for bgeo, the file or store for netcdf/zarr).
    Default `out`: ``RUN/export/<run name>`` plus the format's suffix (``.nc``, ``.zarr``; a folder for
    vtu/vtp/bgeo).  Raises :class:`FormatError` for an unknown format or bgeo of a grid run."""
    if fmt not in FORMATS:
        raise FormatError(f"format {fmt!r}: allowed {', '.join(FORMATS)}")
    run_dir = Path(run_dir)
    info = run_info(run_dir)
    if fmt in PARTICLE_ONLY and info["solver"] != "particles":
        allowed = ", ".join(f for f in FORMATS if f not in PARTICLE_ONLY)
        raise FormatError(f"format {fmt!r} holds particles; a {info['solver']} run exports as {allowed}")
    scene = _scene_from_identity(info["identity"])
    name = f"{info['solver']}-{scene.name}"
    out = Path(out) if out is not None else run_dir / "export" / f"{name}{SUFFIX[fmt]}"
    if fmt == "bgeo":
        write_bgeo_series((_load_npz(p) for p in info["snapshots"]), out, name=name, scene_name=scene.name)
        return out
    if fmt in ("vtu", "vtp"):
        frames = [ADAPTERS[info["solver"]].snapshot_points(_load_npz(p)) for p in info["snapshots"]]
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


def load_series(pvd: str | Path) -> list:
    """The meshes of a .pvd series (pyvista), in time order."""
    import pyvista as pv
    from pbf_cuda.export import read_pvd
    return [pv.read(f) for _, f in read_pvd(pvd)]
