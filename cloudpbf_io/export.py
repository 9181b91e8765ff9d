"""Exports for the tools of the field: ParaView (VTK through pyvista), Houdini (.bgeo) and xarray
(NetCDF, zarr).

Pure Python + numpy at import time; pyvista and xarray are imported when a function needs them
(``pip install "cloudpbf[viz]"`` for VTK, ``"cloudpbf[io]"`` for xarray, NetCDF and zarr).

* :func:`state_to_pyvista` turns a particle state (``Simulation.state()`` or a stored snapshot) into a
  ``pyvista.PolyData`` (``.vtp``) or ``pyvista.UnstructuredGrid`` (``.vtu``) of points with every
  per-particle field as point data; each field's unit is in the field data (``<name>_unit``), and so
  are the simulated time (``TimeValue``, s) and the step.
* :func:`write_pvd` writes a ParaView collection (``.pvd``) that makes a series of such files one
  time series (ParaView's time slider reads the ``timestep`` attribute: simulated seconds).
* :func:`state_to_bgeo` and :func:`write_bgeo_series` write particle states as Houdini's classic
  binary geometry (:mod:`cloudpbf_io.bgeo`, numpy only): one ``name.0001.bgeo`` per frame, the frame
  number Houdini's ``$F4`` expands to (1, 2, ... in time order), positions as ``P``, ``velocity``
  as the vector attribute ``v``, every other per-particle field under its own name (``id`` and
  ``level`` as int), and detail attributes ``time`` (s), ``step``, ``scene`` and ``<attribute>_unit``.
* :func:`fields_to_xarray` turns gridded fields (the grid baseline's ``fields()`` or particles
  deposited by ``cloudpbf.statistics.deposit``) into an ``xarray.Dataset`` on cell-centre coordinates
  ``x``, ``y``, ``z`` (m) with CF attributes (``units``, ``standard_name``, ``long_name``, ``axis``),
  so both solvers' fields line up in xarray.

Coordinates: the model's y is up.  In CF terms y is the vertical axis (``axis = "Z"``,
``standard_name = "height"``, ``positive = "up"``), x and z are the horizontal axes
(``axis = "X"`` and ``axis = "Y"``).  Units are SI (m, s, K, kg/kg, kg/m^3).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Mapping
from glob import escape as glob_escape
from xml.sax.saxutils import quoteattr

import numpy as np

from .files import atomic_write_bytes, atomic_write_text

__all__ = ["PARTICLE_UNITS", "FIELD_ATTRS", "COORD_ATTRS", "BGEO_NAMES", "state_to_pyvista", "write_pvd",
           "write_particle_series", "read_pvd", "vtk_xml_bytes", "state_to_bgeo", "write_bgeo_series", "fields_to_xarray",
           "CONVENTIONS"]

CONVENTIONS = "CF-1.11"

PARTICLE_UNITS = {
    "position": "m", "velocity": "m/s", "temperature": "K", "vapor": "kg/kg", "cloud": "kg/kg",
    "mass": "kg", "level": "1", "kernel_radius": "m", "id": "1",
    "potential_temperature": "K", "density": "kg/m^3",
}
"""Unit of every per-particle field of ``Simulation.state()`` (UDUNITS spelling)."""

COORD_ATTRS = {
    "x": {"units": "m", "axis": "X", "standard_name": "projection_x_coordinate",
          "long_name": "x of the cell centre (horizontal, periodic in the cloud scenes)"},
    "y": {"units": "m", "axis": "Z", "standard_name": "height", "positive": "up",
          "long_name": "height of the cell centre above the ground (the model's y axis)"},
    "z": {"units": "m", "axis": "Y", "standard_name": "projection_y_coordinate",
          "long_name": "z of the cell centre (horizontal, periodic in the cloud scenes)"},
}
"""CF attributes of the cell-centre coordinates.  The model's y is up, hence CF axis Z."""

TIME_ATTRS = {"units": "s", "axis": "T", "long_name": "simulated time since the start of the run"}
STEP_ATTRS = {"units": "1", "long_name": "solver step"}

FIELD_ATTRS = {
    "temperature": {"units": "K", "standard_name": "air_temperature", "long_name": "temperature"},
    "potential_temperature": {"units": "K", "standard_name": "air_potential_temperature",
                              "long_name": "potential temperature T + Gamma_d y"},
    "vapor": {"units": "kg kg-1", "standard_name": "humidity_mixing_ratio",
              "long_name": "water vapour mixing ratio"},
    "cloud": {"units": "kg kg-1", "standard_name": "cloud_liquid_water_mixing_ratio",
              "long_name": "cloud water mixing ratio"},
    "velocity_x": {"units": "m s-1", "standard_name": "x_wind", "long_name": "velocity along x"},
    "velocity_y": {"units": "m s-1", "standard_name": "upward_air_velocity",
                   "long_name": "velocity along y (up)"},
    "velocity_z": {"units": "m s-1", "standard_name": "y_wind", "long_name": "velocity along z"},
    "density": {"units": "kg m-3", "standard_name": "air_density",
                "long_name": "particle mass density deposited with the poly6 kernel"},
}
"""CF attributes of the gridded fields (both solvers use the same names)."""


# ---- particles -> VTK ------------------------------------------------------------------------------
def state_to_pyvista(state: Mapping[str, np.ndarray], kind: str = "polydata", time: float | None = None,
                     step: int | None = None, scene_name: str | None = None):
    """A particle state as a pyvista dataset of points.

    ``state``: ``position`` (N, 3) m and any per-particle arrays of length N (``Simulation.state()``
    or a stored snapshot; scalars such as ``step`` are skipped).  ``kind``: ``"polydata"`` (one
    vertex cell per particle, written as .vtp) or ``"unstructured"`` (.vtu).  Every array becomes
    point data under its own name (``velocity`` stays a 3-vector); its unit goes into the field data
    as ``<name>_unit``.  ``time`` (s) becomes ``TimeValue`` in the field data, ``step`` ``step``.
    """
    import pyvista as pv
    if kind not in ("polydata", "unstructured"):
        raise ValueError(f"kind = {kind!r}: allowed 'polydata', 'unstructured'")
    if "position" not in state:
        raise KeyError(f"particle state lacks 'position' (has: {', '.join(sorted(state))})")
    pos = np.asarray(state["position"], dtype=np.float32).reshape(-1, 3)
    n = len(pos)
    cloud = pv.PolyData(pos)            # one vertex cell per point
    if kind == "unstructured":
        cloud = cloud.cast_to_unstructured_grid()
    for name, value in state.items():
        arr = np.asarray(value)
        if name == "position" or arr.ndim == 0 or len(arr) != n:
            continue
        if arr.dtype == np.uint32:      # VTK readers are happiest with signed ids
            arr = arr.astype(np.int64)
        cloud.point_data[name] = arr
        cloud.field_data[f"{name}_unit"] = [PARTICLE_UNITS.get(name, "")]
    cloud.field_data["position_unit"] = ["m"]
    if time is not None:
        cloud.field_data["TimeValue"] = np.array([float(time)])
    if step is not None:
        cloud.field_data["step"] = np.array([int(step)], dtype=np.int64)
    if scene_name:
        cloud.field_data["scene"] = [str(scene_name)]
    return cloud


def write_pvd(entries: Iterable[tuple[float, str | Path]], path: str | Path) -> Path:
    """A ParaView collection: ``entries`` are (time in s, data file); files are stored relative to
    the .pvd's folder.  Written atomically."""
    path = Path(path)
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
    for time, file in entries:
        rel = os.path.relpath(Path(file).resolve(), path.parent.resolve())
        lines.append(f'    <DataSet timestep="{float(time)!r}" group="" part="0" file={quoteattr(rel)}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    return atomic_write_text(path, "\n".join(lines))


def read_pvd(path: str | Path) -> list[tuple[float, Path]]:
    """The (time, file) entries of a .pvd collection, files resolved against its folder."""
    import xml.etree.ElementTree as ET
    path = Path(path)
    root = ET.parse(path).getroot()
    return [(float(ds.get("timestep")), path.parent / ds.get("file")) for ds in root.iter("DataSet")]


def write_particle_series(frames: Iterable[Mapping[str, np.ndarray]], out_dir: str | Path, fmt: str = "vtp",
                          name: str = "particles", scene_name: str | None = None) -> Path:
    """Write particle states as ``out_dir/name_NNNNNN.vtp|vtu`` plus ``out_dir/name.pvd`` (the series).

    Each frame is a state dict with ``step`` and ``time_s`` (as stored in a run's snapshots) or
    without them (then its index and 0 s).  Returns the path of the .pvd."""
    if fmt not in ("vtp", "vtu"):
        raise ValueError(f"fmt = {fmt!r}: allowed 'vtp', 'vtu'")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, frame in enumerate(frames):
        step = int(np.asarray(frame.get("step", i)))
        time = float(np.asarray(frame.get("time_s", frame.get("time", 0.0))))
        mesh = state_to_pyvista(frame, "polydata" if fmt == "vtp" else "unstructured", time=time, step=step,
                                scene_name=scene_name)
        file = out / f"{name}_{step:06d}.{fmt}"
        atomic_write_bytes(file, vtk_xml_bytes(mesh))
        entries.append((time, file))
    return write_pvd(entries, out / f"{name}.pvd")


def vtk_xml_bytes(mesh) -> bytes:
    """A pyvista PolyData or UnstructuredGrid as the bytes of a VTK XML file (.vtp / .vtu), made in memory
    (binary data base64-encoded inline, zlib-compressed, as pyvista's own save writes it), so the file is
    then written by Python: a full or read-only disk is an OSError, never a crash inside VTK's writer."""
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter, vtkXMLUnstructuredGridWriter
    writer = vtkXMLPolyDataWriter() if mesh.GetDataObjectType() == 0 else vtkXMLUnstructuredGridWriter()
    writer.SetInputData(mesh)
    writer.SetDataModeToBinary()
    writer.SetCompressorTypeToZLib()
    writer.WriteToOutputStringOn()
    if not writer.Write():
        raise ValueError(f"VTK could not encode a {type(mesh).__name__}")
    return writer.GetOutputString().encode("ascii")


# ---- particles -> Houdini .bgeo ------------------------------------------------------------------
BGEO_NAMES = {"position": "P", "velocity": "v"}
"""Houdini's names for the state's fields; every other field keeps its own name."""


def state_to_bgeo(state: Mapping[str, np.ndarray], time: float | None = None, step: int | None = None,
                  scene_name: str | None = None):
    """(position, point attributes, detail attributes) of a particle state, as
    :func:`cloudpbf_io.bgeo.write_bgeo` takes them.

    ``velocity`` becomes the vector ``v``; every other per-particle array keeps its name (scalars such as
    ``step`` and arrays of another length are skipped); ``id`` (uint32) is stored as int, the format's
    only integer.  The detail holds ``<attribute>_unit`` for ``P`` and every attribute
    (:data:`PARTICLE_UNITS`), and ``time`` (s, float32), ``step`` and ``scene`` when given."""
    if "position" not in state:
        raise KeyError(f"particle state lacks 'position' (has: {', '.join(sorted(state))})")
    pos = np.asarray(state["position"]).reshape(-1, 3)
    n = len(pos)
    attributes, detail = {}, {"P_unit": PARTICLE_UNITS["position"]}
    for name, value in state.items():
        arr = np.asarray(value)
        if name == "position" or arr.ndim == 0 or len(arr) != n:
            continue
        houdini = BGEO_NAMES.get(name, name)
        attributes[houdini] = arr
        detail[f"{houdini}_unit"] = PARTICLE_UNITS.get(name, "")
    if time is not None:
        detail["time"] = float(time)
    if step is not None:
        detail["step"] = int(step)
    if scene_name:
        detail["scene"] = str(scene_name)
    return pos, attributes, detail


def write_bgeo_series(frames: Iterable[Mapping[str, np.ndarray]], out_dir: str | Path, name: str = "particles",
                      scene_name: str | None = None) -> list[Path]:
    """Write particle states as ``out_dir/name.0001.bgeo``, ``name.0002.bgeo``, ... (frames numbered
    from 1 in the given order, four digits or more, the names Houdini's ``$F4`` expands to
    name them); each file's detail holds the frame's ``time`` (s) and ``step``.  Frames are state dicts
    as for :func:`write_particle_series`.  Frames of an earlier, longer series of the same name in
    `out_dir` are removed, so Houdini plays this series only.  Returns the paths written."""
    import re
    from .bgeo import write_bgeo
    frames = list(frames)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    width = max(4, len(str(len(frames))))
    paths = []
    for i, frame in enumerate(frames):
        step = int(np.asarray(frame.get("step", i)))
        time = float(np.asarray(frame.get("time_s", frame.get("time", 0.0))))
        pos, attributes, detail = state_to_bgeo(frame, time=time, step=step, scene_name=scene_name)
        paths.append(write_bgeo(out / f"{name}.{i + 1:0{width}d}.bgeo", pos, attributes, detail))
    frame_name = re.compile(re.escape(name) + r"\.\d{4,}\.bgeo")
    for stale in set(out.glob(f"{glob_escape(name)}.*.bgeo")) - set(paths):
        if frame_name.fullmatch(stale.name):
            stale.unlink()
    return paths


# ---- grids -> xarray ---------------------------------------------------------------------------
def _grid_field_items(fields: Mapping[str, np.ndarray]):
    """(name, (nx, ny, nz) array) pairs; (nx, ny, nz, 3) velocity is split into velocity_x/y/z."""
    for name, value in fields.items():
        arr = np.asarray(value)
        if name == "velocity" and arr.ndim == 4 and arr.shape[-1] == 3:
            for a, axis in enumerate("xyz"):
                yield f"velocity_{axis}", arr[..., a]
        elif arr.ndim == 3:
            yield name, arr


def fields_to_xarray(fields: Mapping[str, np.ndarray], cell_size=None, origin=(0.0, 0.0, 0.0),
                     time: float | None = None, step: int | None = None, attrs: Mapping | None = None):
    """Gridded fields as an ``xarray.Dataset`` on cell-centre coordinates with CF attributes.

    ``fields``: (nx, ny, nz) arrays (``temperature``, ``vapor``, ``cloud``, ``density``, ...) and
    optionally ``velocity`` (nx, ny, nz, 3), split into ``velocity_x``/``_y``/``_z``; 1-D ``x``,
    ``y``, ``z`` (m) when present are used as the coordinates, otherwise they are built from
    ``cell_size`` (or ``fields["cell_size"]``) and ``origin``.  ``time`` (s) and ``step`` become
    scalar coordinates (expand with ``ds.expand_dims("time")`` to stack a series).  Names in
    :data:`FIELD_ATTRS` get its CF attributes; other 3-D arrays keep their name without a unit.
    """
    import xarray as xr
    items = list(_grid_field_items(fields))
    if not items:
        raise ValueError(f"no (nx, ny, nz) field among {', '.join(sorted(fields))}")
    shape = items[0][1].shape
    coords = {}
    if all(k in fields for k in "xyz"):
        for k in "xyz":
            coords[k] = np.asarray(fields[k], dtype=np.float64)
    else:
        size = cell_size if cell_size is not None else fields.get("cell_size")
        if size is None:
            raise ValueError("cell_size is needed when fields have no x, y, z coordinates")
        size = np.broadcast_to(np.asarray(size, dtype=np.float64), (3,))
        org = np.broadcast_to(np.asarray(fields.get("origin", origin), dtype=np.float64), (3,))
        for a, k in enumerate("xyz"):
            coords[k] = org[a] + (np.arange(shape[a]) + 0.5) * size[a]
    for a, k in enumerate("xyz"):
        if len(coords[k]) != shape[a]:
            raise ValueError(f"coordinate {k} has {len(coords[k])} values, the fields {shape[a]} cells")
    data_vars = {}
    for name, arr in items:
        if arr.shape != shape:
            raise ValueError(f"field {name} has shape {arr.shape}, expected {shape}")
        data_vars[name] = (("x", "y", "z"), arr, dict(FIELD_ATTRS.get(name, {"long_name": name})))
    ds = xr.Dataset(data_vars, coords={k: (k, v, dict(COORD_ATTRS[k])) for k, v in coords.items()})
    if time is not None:
        ds = ds.assign_coords(time=((), float(time), dict(TIME_ATTRS)))
    if step is not None:
        ds = ds.assign_coords(step=((), int(step), dict(STEP_ATTRS)))
    ds.attrs.update({"Conventions": CONVENTIONS, **dict(attrs or {})})
    return ds
