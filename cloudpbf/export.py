"""Export runs for ParaView, Houdini and xarray: ``cloudpbf export RUN --format vtu|vtp|bgeo|netcdf|zarr``.

* ``vtp`` / ``vtu``: every stored snapshot of the run as one VTK file (particles: points with every
  per-particle field; grid: the cell centres with every field), plus ``<name>.pvd``, the time series
  ParaView opens (File > Open the .pvd, the time slider steps through the snapshots in simulated
  seconds).  Units are in each file's field data (``<field>_unit``).
* ``bgeo`` (particle runs only): Houdini's classic binary geometry, one ``<name>.0001.bgeo``,
  ``<name>.0002.bgeo``, ... per snapshot in time order (a File SOP reading ``<name>.$F4.bgeo`` plays
  them), written by :mod:`cloudpbf_io.bgeo` (numpy, no partio needed): ``P``, the vector ``v`` (m/s) and
  every other per-particle field under its own name; detail attributes ``time`` (s), ``step``,
  ``scene`` and ``<attribute>_unit``.  A grid run asked for bgeo raises :class:`FormatError`.
* ``netcdf`` / ``zarr``: one ``xarray.Dataset`` with dimensions ``(time, x, y, z)`` on the cell
  centres, CF attributes on every variable.  Grid runs give their own fields; particle runs give
  their particles deposited with the SPH poly6 kernel (``cloudpbf.statistics.deposit``: density,
  temperature, vapor, cloud, velocity) on the grid the grid baseline would use for the scene (one
  cell per particle spacing, or ``--resolution``), so a particle run and a grid run of the same
  scene line up cell by cell: ``xr.open_dataset(a) - xr.open_dataset(b)``.

Where it goes: ``--out`` (default ``RUN/export``).  An existing folder gets the export inside it, named
from the run (``<solver>-<scene name>``, the scene name reduced to letters, digits and ``_ . -``):
``<name>.nc``, ``<name>.zarr``, or a folder ``<name>-vtp`` (``-vtu``, ``-bgeo``) of frames; a path that does not exist
yet is the export itself.  Nothing is ever deleted or replaced that the export did not write: an
existing target is refused with one line naming it; ``force`` replaces it only when it is an earlier
export of the same run (the record every export carries says so), in one rename.  The export is built
under a temporary name beside its target and moved into place at the end (cloudpbf.store.targets), so a
full or read-only disk ends in one :class:`ExportError` naming the path and leaves nothing behind;
the free space is checked first, and so is the memory the export needs (``--resolution`` sets it).

What is exported: the snapshots the run's manifest lists, each checked against its sha256 (a damaged
or unfinished run is refused unless ``unverified``: then every snapshot file there is, as it is).

Python: :func:`run_to_xarray`, :func:`particles_to_xarray`, :func:`combine_solvers` (both solvers'
Datasets along a ``solver`` dimension), :func:`export_run`.
"""
from __future__ import annotations

import io
import json
import math
import os
import re
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np

from cloudpbf.solvers import ADAPTERS, particles_to_xarray  # noqa: F401  (particles_to_xarray: public here too)
from cloudpbf.store.identity import effective_seed
from cloudpbf.store.manifest import read_result, verify_run
from cloudpbf.store.safe import entry_kind, read_bytes, read_json
from cloudpbf.store.targets import (NETCDF_ATTR, ExportError, check_free_space, disk_error, foreign_entries,
                                  marker_of, staged)
from cloudpbf_io.export import FIELD_ATTRS, read_pvd, write_bgeo_series, write_particle_series
from pbf_cuda.memory import available_memory
from pbf_cuda.scene import SceneError, sanitize_name, scene_from_dict

__all__ = ["FORMATS", "PARTICLE_ONLY", "FormatError", "ExportError", "particles_to_xarray", "run_to_xarray",
           "combine_solvers", "export_run", "run_info", "export_name"]

FORMATS = ("vtu", "vtp", "bgeo", "netcdf", "zarr")
PARTICLE_ONLY = ("bgeo",)
"""Formats of particle runs only (a grid run has cells, not particles)."""
SUFFIX = {"vtu": "-vtu", "vtp": "-vtp", "bgeo": "-bgeo", "netcdf": ".nc", "zarr": ".zarr"}
"""What follows the name: a file (.nc), a store (.zarr), a folder of frames (-vtu, -vtp, -bgeo)."""
SNAPSHOT = re.compile(r"snapshots/step_\d{6}\.npz")
MAX_CONFIG_BYTES = 16 << 20
GRID_VARIABLES = 8          # density, temperature, vapor, cloud, velocity x/y/z (+ one more grid's worth)
MEMORY_SAFETY = 0.8         # use at most this fraction of the available memory


class FormatError(ValueError):
    """A format the run cannot be exported in (unknown, or bgeo for a grid run)."""


def _scene_from_identity(identity: Mapping):
    data = json.loads(json.dumps(identity["scene"]))
    head = data.get("scene") if isinstance(data.get("scene"), dict) else {}
    head["name"] = sanitize_name(head.get("name", "scene"))      # runs stored before names were restricted
    data["scene"] = {k: v for k, v in head.items() if k in ("name", "description")}
    try:
        return scene_from_dict(data, source=head["name"])
    except SceneError as exc:
        raise ExportError(f"the run's config.json holds an invalid scene: {exc}") from None


def run_info(run_dir: str | Path, unverified: bool = False) -> dict:
    """The run's identity (config.json: solver, scene, seed, ...), its key and the snapshot files to export.

    A finished run must pass verify_run and gives the snapshots its manifest lists (other files in
    snapshots/ are not its own); a run without result.json, or one that fails verification, raises
    ExportError unless `unverified` (then every regular ``snapshots/step_NNNNNN.npz`` is taken as it is).
    FileNotFoundError when `run_dir` is no run directory."""
    run_dir = Path(run_dir)
    if entry_kind(run_dir) != "dir" or entry_kind(run_dir / "config.json") != "file":
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.json); "
                                "`cloudpbf runs` lists the runs")
    try:
        config = read_json(run_dir / "config.json", limit=MAX_CONFIG_BYTES)
        identity = config["identity"]
        solver = identity["solver"]
        if solver not in ADAPTERS or not isinstance(identity.get("scene"), dict):
            raise ValueError(f"solver {str(solver)[:20]!r}")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ExportError(f"{run_dir / 'config.json'}: unreadable ({type(exc).__name__}: {str(exc)[:80]})") from None
    key = config.get("key") if isinstance(config.get("key"), str) else None
    sizes = {}
    if entry_kind(run_dir / "result.json") is None:
        problem = "it has not finished (no result.json)"
    else:
        problems = verify_run(run_dir, key, memo=False)      # every file read now, whatever was read before
        problem = f"it fails verification: {problems[0]}" if problems else None
        if not problems:
            listed = read_result(run_dir)["manifest"]
            sizes = {run_dir / rel: entry["bytes"] for rel, entry in sorted(listed.items()) if SNAPSHOT.fullmatch(rel)}
    if problem is not None:
        if not unverified:
            raise ExportError(f"{run_dir}: {problem}; --unverified exports its snapshots as they are")
        folder = run_dir / "snapshots"
        files = sorted(folder.glob("step_*.npz")) if entry_kind(folder) == "dir" else []
        sizes = {p: None for p in files if entry_kind(p) == "file" and SNAPSHOT.fullmatch(f"snapshots/{p.name}")}
    if not sizes:
        raise FileNotFoundError(f"{run_dir}: no stored snapshots (snapshots/step_*.npz)")
    return {"identity": identity, "solver": solver, "key": key, "snapshots": list(sizes), "sizes": sizes,
            "verified": problem is None}


def export_name(info: dict) -> str:
    """The export's file name stem: <solver>-<scene name>, the name reduced to letters, digits and _ . -."""
    return f"{info['solver']}-{sanitize_name(info['identity']['scene'].get('scene', {}).get('name', 'scene'))}"


def _load_npz(path: Path, size: int | None = None) -> dict:
    """A snapshot, read as a regular file (links refused) of at most `size` bytes (the manifest's)."""
    limit = size if size is not None else max(0, (entry_kind(path) == "file" and path.lstat().st_size) or 0)
    try:
        raw = read_bytes(path, limit)
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001  (zipfile's BadZipFile, numpy's ValueError, OSError, ...)
        raise ExportError(f"{path}: unreadable snapshot ({type(exc).__name__}: {str(exc)[:80]})") from None


def _frames(info: dict):
    for path in info["snapshots"]:
        yield _load_npz(path, info["sizes"][path])


def run_to_xarray(run_dir: str | Path, resolution=None, like=None, unverified: bool = False, info: dict | None = None):
    """Every snapshot of a run as one Dataset with dimensions (time, x, y, z); ``step`` is a
    coordinate along time.  Particle runs are deposited (see :func:`particles_to_xarray`)."""
    import xarray as xr  # io extra (xarray)
    info = info or run_info(run_dir, unverified)
    scene = _scene_from_identity(info["identity"])
    adapter = ADAPTERS[info["solver"]]
    stacked = []
    for snap in _frames(info):
        f = adapter.snapshot_dataset(snap, scene, resolution=resolution, like=like)
        attrs = dict(f["step"].attrs)
        stacked.append(f.expand_dims("time").assign_coords(step=("time", [int(f["step"])], attrs)))
    ds = xr.concat(stacked, dim="time", data_vars="all", coords="minimal", compat="override",
                   combine_attrs="override")
    ident = info["identity"]
    ds.attrs.update({"run": Path(run_dir).name, "seed": effective_seed(ident),
                     "backend": str(ident.get("backend")), "code": str(ident.get("code")),
                     "steps": int(ident.get("steps", 0))})
    return ds


def combine_solvers(datasets: Mapping[str, object]):
    """Datasets of several solvers on the same coordinates (e.g. ``{"grid": g, "particles": p}``) as one
    Dataset with a leading ``solver`` dimension; variables only one side has are filled with NaN.

    ``ds.cloud.sel(solver="particles") - ds.cloud.sel(solver="grid")`` is then the cell-by-cell
    difference.  Raises ValueError when the coordinates differ."""
    import xarray as xr  # io extra (xarray)
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


def _need_bytes(info: dict, fmt: str, scene, resolution) -> tuple[int, int]:
    """(memory, disk) bytes an export needs, estimated before anything is read: gridded formats hold every
    snapshot's grid (deposited for particles) about three times over (frames, the stacked Dataset, the
    encoded file); point formats one snapshot at a time."""
    sizes = [s if s is not None else p.lstat().st_size for p, s in info["sizes"].items()]
    if fmt in ("netcdf", "zarr"):
        if info["solver"] == "particles":
            from cloudpbf.statistics import grid_for_scene  # harness extra (pandas, scipy)
            shape, _ = grid_for_scene(scene, resolution)
            grid = math.prod(int(n) for n in shape) * 8 * GRID_VARIABLES
        else:
            grid = max(sizes) * 2                 # float32 fields stored, float64 in the Dataset
        data = grid * len(sizes)
        return 3 * data + 4 * max(sizes), data
    return 4 * max(sizes), sum(sizes) * 2         # base64 inline VTK: 4/3 of the raw bytes, and the .pvd


def _check_memory(need: int, resolution) -> None:
    avail = available_memory("cpu")
    if avail is not None and need > MEMORY_SAFETY * avail:
        hint = f"--resolution {','.join(map(str, resolution))}" if resolution else "the export"
        raise ExportError(f"{hint}: needs about {need / 2**30:.2f} GiB of memory, {avail / 2**30:.2f} GiB "
                          "available; lower --resolution (cells per axis) or export fewer snapshots")


def _target(run_dir: Path, out, name: str, fmt: str, record: dict) -> Path:
    """The path the export becomes: OUT/<name><suffix> when OUT is an existing folder (other than an earlier
    export of this run), else OUT itself; RUN/export/<name><suffix> without OUT."""
    filename = f"{name}{SUFFIX[fmt]}"
    if out is None:
        folder = run_dir / "export"
        if entry_kind(folder) not in (None, "dir"):
            raise ExportError(f"{folder}: is not a folder; give --out")
        try:
            folder.mkdir(exist_ok=True)
        except OSError as exc:
            raise ExportError(f"{disk_error(exc, folder)} (give --out)") from None
        return folder / filename
    out = Path(out)
    if out.is_dir() and not _same_export(marker_of(out), record):
        return out / filename
    if not out.parent.is_dir():
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise disk_error(exc, out.parent) from None
    return out


def _same_export(marker: dict | None, record: dict) -> bool:
    return marker is not None and all(marker.get(k) == record[k] for k in ("run", "key", "format"))


def export_run(run_dir: str | Path, fmt: str, out: str | Path | None = None, resolution=None, *,
               force: bool = False, unverified: bool = False) -> Path:
    """Write a run's snapshots in `fmt` (see :data:`FORMATS`); returns what was written (the .pvd for
    vtu/vtp, the folder of ``<name>.NNNN.bgeo`` files for bgeo, the file or store for netcdf/zarr).
    Where it goes and what it never touches: see the module docstring.

    Raises :class:`FormatError` (unknown format, bgeo of a grid run), :class:`ExportError` (the target
    exists, the run is damaged or unfinished, too little memory or disk, a disk error: one line naming
    the path), FileNotFoundError (no run directory, no snapshots)."""
    if fmt not in FORMATS:
        raise FormatError(f"format {fmt!r}: allowed {', '.join(FORMATS)}")
    run_dir = Path(run_dir)
    info = run_info(run_dir, unverified)
    if fmt in PARTICLE_ONLY and info["solver"] != "particles":
        allowed = ", ".join(f for f in FORMATS if f not in PARTICLE_ONLY)
        raise FormatError(f"format {fmt!r} holds particles; a {info['solver']} run exports as {allowed}")
    scene = _scene_from_identity(info["identity"])
    name = export_name(info)
    record = {"run": run_dir.resolve().name, "key": info["key"], "format": fmt}
    memory, disk = _need_bytes(info, fmt, scene, resolution)
    _check_memory(memory, resolution)
    target = _target(run_dir, out, name, fmt, record)
    kind = entry_kind(target)
    replace = False
    if kind is not None:
        ours = _same_export(marker_of(target), record)
        if kind == "link" or not ours:
            raise ExportError(f"{target}: exists and is not an export of this run; refusing to replace it "
                              "(choose another --out)")
        if not force:
            raise ExportError(f"{target}: exists (an earlier export of this run); --force replaces it")
        foreign = foreign_entries(target, marker_of(target))
        if foreign:
            raise ExportError(f"{target}: holds {len(foreign)} file(s) the export did not write ({foreign[0][:60]}); "
                              "refusing to replace it")
        replace = True
    check_free_space(target.parent, disk)
    folder = fmt != "netcdf"
    with staged(target, record, folder=folder, replace=replace) as stage:
        if fmt == "bgeo":
            write_bgeo_series(_frames(info), stage, name=name, scene_name=scene.name)
        elif fmt in ("vtu", "vtp"):
            adapter = ADAPTERS[info["solver"]]
            write_particle_series((adapter.snapshot_points(f) for f in _frames(info)), stage, fmt=fmt, name=name,
                                  scene_name=scene.name)
        else:
            ds = run_to_xarray(run_dir, resolution=resolution, info=info)
            ds.attrs[NETCDF_ATTR] = json.dumps(record)
            if fmt == "netcdf":
                data = bytes(ds.to_netcdf(engine="h5netcdf"))   # in memory: the disk is written by Python
                with open(stage, "xb") as fh:
                    fh.write(data)
                    fh.flush()
                    os.fsync(fh.fileno())
            else:
                with warnings.catch_warnings():      # zarr 3 notes that consolidated metadata is its own extension
                    warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
                    ds.to_zarr(stage, mode="w")
    return target / f"{name}.pvd" if fmt in ("vtu", "vtp") else target


def load_series(pvd: str | Path) -> list:
    """The meshes of a .pvd series (pyvista), in time order."""
    import pyvista as pv  # viz extra (pyvista)
    return [pv.read(f) for _, f in read_pvd(pvd)]
