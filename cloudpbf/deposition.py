"""Particles deposited onto the analysis grid: the step shared by every particle diagnostic.

A particle snapshot becomes gridded fields with the SPH poly6 kernel (:func:`deposit`,
:func:`deposit_state`) on the grid of :func:`grid_for_scene`, so that the particle solver
and the grid baseline go through the same diagnostics code (:mod:`cloudpbf.statistics`).
The conventions are those of :mod:`cloudpbf.statistics`: ``(nx, ny, nz)`` grids on cell
centres, ``y`` (axis 1) up, x and z periodic by default, SI units (m, kg, kg/m^3).
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Iterable, Mapping, Sequence

import numpy as np

__all__ = [
    "DEFAULT_PERIODIC",
    "checked_vector3",
    "poly6",
    "deposit",
    "grid_for_scene",
    "deposit_state",
]

DEFAULT_PERIODIC = (True, False, True)
"""Periodic axes (x, y, z) of the paper's cloud box: x and z periodic, y between walls."""

_CHUNK_ENTRIES = 1 << 20  # particle x stencil entries per task (~50 MB of temporaries)


# ------------------------------------------------------------------------------------------
# small validation helpers
# ------------------------------------------------------------------------------------------
def checked_vector3(name: str, value, positive: bool = False) -> np.ndarray:
    """`value` as 3 finite float64 numbers (x, y, z; a scalar is repeated); ValueError naming `name`."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(3, float(arr))
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} = {value!r}: expected 3 finite numbers (x, y, z)")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} = {value!r}: every entry must be > 0")
    return arr


def _shape3(shape) -> tuple[int, int, int]:
    try:
        out = tuple(int(s) for s in shape)
    except TypeError:
        raise ValueError(f"shape = {shape!r}: expected 3 cell counts (nx, ny, nz)") from None
    if len(out) != 3 or any(s < 1 for s in out) or any(float(s) != float(t) for s, t in zip(out, shape)):
        raise ValueError(f"shape = {shape!r}: expected 3 integers >= 1 (nx, ny, nz)")
    return out


def _per_particle(name: str, value, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected a scalar or an array of shape ({n},), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise ValueError(f"{name}: non-finite value {arr[bad]} at particle index {bad}")
    return arr


# ------------------------------------------------------------------------------------------
# deposition (particles -> grid)
# ------------------------------------------------------------------------------------------
def poly6(r2, h):
    """Poly6 kernel W(r, h) = 315 / (64 pi h^9) (h^2 - r^2)^3 for r < h, else 0 (1/m^3).

    Takes the squared distance ``r2`` (m^2) and the kernel radius ``h`` (m); the
    density kernel of eq. 1 (Mueller et al. 2003).
    """
    r2 = np.asarray(r2, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    q = np.maximum(h * h - r2, 0.0)
    return (315.0 / (64.0 * math.pi)) / h**9 * (q * q * q)


def deposit(positions, masses, kernel_radius, fields: Mapping[str, np.ndarray], shape, cell_size,
            periodic: Sequence[bool] = DEFAULT_PERIODIC, origin=(0.0, 0.0, 0.0),
            empty_value: float = 0.0, workers: int | None = None) -> dict:
    """Deposit particle fields onto cell centres with the poly6 kernel, Shepard-normalised.

    Parameters
    ----------
    positions : (N, 3) m.  Positions outside a periodic axis are wrapped.
    masses : (N,) kg (or a scalar).
    kernel_radius : (N,) m (or a scalar): per-particle h (adaptive levels differ).
    fields : name -> (N,) per-particle values (e.g. temperature K, vapor and cloud kg/kg).
    shape : (nx, ny, nz) cells; cell_size : (3,) m (or a scalar); origin : (3,) m, the
        corner of cell (0, 0, 0).
    periodic : per axis, True wraps kernel footprints around (periodic images), False
        drops the cells beyond the wall.
    empty_value : value given to a field in a cell that no particle reaches.
    workers : threads (default: CPU count, at most 8).

    Returns
    -------
    dict with ``density`` (nx, ny, nz) kg/m^3, one grid per input field, ``cell_size``
    (3,) m and ``origin`` (3,) m (the same keys as ``GridSimulation.fields()``).

    Method: each particle's kernel weights W(|x_c - x_j|, h_j) over the cells c it
    reaches are normalised so that sum_c W~_jc V = 1 (V the cell volume).  Then
    ``density = sum_j m_j W~_jc`` and ``field = sum_j m_j f_j W~_jc / density`` (Shepard),
    so a constant field is reproduced exactly and every mass-weighted total is
    conserved to rounding: sum_c density f V = sum_j m_j f_j.  Near a wall the
    footprint is cut and renormalised (nothing leaks out of the box).  A particle whose
    kernel reaches no cell centre (h smaller than half a cell) goes wholly into the cell
    that holds it (clamped into the box on wall axes).  Within one kernel radius of a
    wall the Shepard average of a field with a vertical gradient g is biased by up to
    g h (the footprint is one-sided there).
    """
    shape = _shape3(shape)
    dx = checked_vector3("cell_size", cell_size, positive=True)
    origin = checked_vector3("origin", origin)
    periodic = tuple(bool(p) for p in periodic)
    if len(periodic) != 3:
        raise ValueError(f"periodic = {periodic!r}: expected 3 booleans (x, y, z)")
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected shape (N, 3), got {pos.shape}")
    if not np.all(np.isfinite(pos)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(pos), axis=1))[0])
        raise ValueError(f"positions: non-finite value at particle index {bad}: {pos[bad]}")
    n = pos.shape[0]
    mass = _per_particle("masses", masses, n)
    if np.any(mass < 0):
        raise ValueError("masses: must be >= 0 kg")
    h = _per_particle("kernel_radius", kernel_radius, n)
    if np.any(h <= 0):
        raise ValueError("kernel_radius: must be > 0 m")
    values = {}
    for name, val in fields.items():
        if name in ("density", "cell_size", "origin"):
            raise ValueError(f"fields: '{name}' is a reserved output name")
        values[name] = _per_particle(f"fields['{name}']", val, n)

    n_cells = shape[0] * shape[1] * shape[2]
    cell_volume = float(np.prod(dx))
    dims = np.array(shape, dtype=np.int64)

    rel = (pos - origin) / dx                       # position in cell units
    home = np.floor(rel).astype(np.int64)          # the cell holding the particle
    delta = rel - home - 0.5                       # offset from its centre, in [-0.5, 0.5)
    # Cells i + k with |k - delta| < h/dx can be reached: |k| <= floor(h/dx + 0.5).
    # Particles are grouped by that reach (adaptive levels have smaller kernels).
    reach = np.floor(h[:, None] / dx[None, :] + 0.5).astype(np.int64)
    span = int(reach.max()) + 1 if n else 1
    key = (reach[:, 0] * span + reach[:, 1]) * span + reach[:, 2]
    tasks = []
    for k in np.unique(key):
        members = np.flatnonzero(key == k)
        reach_g = reach[members[0]]
        h_max = float(h[members].max())
        ks = np.stack(np.meshgrid(*[np.arange(-r, r + 1) for r in reach_g], indexing="ij"), -1).reshape(-1, 3)
        nearest = np.maximum(np.abs(ks) - 0.5, 0.0) * dx  # closest a centre at offset k can be
        ks = ks[np.sum(nearest**2, axis=1) < h_max**2]
        chunk = max(1, _CHUNK_ENTRIES // max(len(ks), 1))
        tasks += [(members[s:s + chunk], ks, reach_g) for s in range(0, len(members), chunk)]

    def run(share):
        """Deposit a list of tasks into private accumulators (one per thread)."""
        density, sums = np.zeros(n_cells), {name: np.zeros(n_cells) for name in values}
        for idx, ks, reach_g in share:
            d, f = _deposit_chunk(idx, ks, reach_g, home, delta, h, mass, values, dx, dims, periodic,
                                  cell_volume, n_cells)
            density += d
            for name in sums:
                sums[name] += f[name]
        return density, sums

    workers = max(1, min(len(tasks), workers if workers else min(os.cpu_count() or 1, 8)))
    shares = [tasks[i::workers] for i in range(workers)]
    if workers > 1:  # numpy releases the GIL in the heavy loops; threads share the inputs
        with ThreadPoolExecutor(workers) as pool:
            parts = list(pool.map(run, shares))
    else:
        parts = [run(shares[0])]
    acc_density = np.sum([d for d, _ in parts], axis=0) if parts else np.zeros(n_cells)
    acc = {name: (np.sum([f[name] for _, f in parts], axis=0) if parts else np.zeros(n_cells))
           for name in values}

    density = acc_density.reshape(shape)
    out = {"density": density}
    filled = density > 0
    for name, total in acc.items():
        grid = np.full(shape, float(empty_value))
        np.divide(total.reshape(shape), density, out=grid, where=filled)
        out[name] = grid
    out["cell_size"] = dx
    out["origin"] = origin
    return out


def _deposit_chunk(idx, ks, reach, home, delta, h, mass, values, dx, dims, periodic, cell_volume, n_cells):
    """Deposit particles `idx` over stencil offsets `ks`: (density sums, {field: sums}) per cell.

    Distances and cell indices are built per axis over the 2R+1 offsets of that axis,
    then combined for the 3D offsets, so the (particles x offsets) work is a few gathers.
    """
    r2 = 0.0
    flat = 0
    for axis in range(3):
        offsets = np.arange(-reach[axis], reach[axis] + 1)
        # distance from the particle to the centre of cell home + k along this axis: (k - delta) dx
        d2 = ((offsets[None, :] - delta[idx, axis, None]) * dx[axis]) ** 2
        cell = home[idx, axis, None] + offsets[None, :]
        if periodic[axis]:
            cell %= dims[axis]
        else:
            outside = (cell < 0) | (cell >= dims[axis])
            d2[outside] = np.inf                    # beyond the wall: no weight
            np.clip(cell, 0, dims[axis] - 1, out=cell)
        pick = ks[:, axis] + reach[axis]
        r2 = r2 + d2[:, pick]
        flat = flat * dims[axis] + cell[:, pick]
    hj = h[idx, None]
    weight = poly6(np.minimum(r2, hj * hj), hj)
    norm = weight.sum(axis=1) * cell_volume
    lonely = norm <= 0.0
    if np.any(lonely):
        # kernel reaches no centre: all of it goes into the (clamped / wrapped) home cell, k = 0
        zero = int(np.flatnonzero(np.all(ks == 0, axis=1))[0])
        weight[lonely, zero] = 1.0
        norm[lonely] = cell_volume
    weight /= norm[:, None]                         # now sum_c W~ V = 1 per particle
    touched = weight > 0.0
    flat = flat[touched]
    mw = (weight * mass[idx, None])[touched]
    density = np.bincount(flat, weights=mw, minlength=n_cells)
    sums = {}
    for name, val in values.items():
        sums[name] = np.bincount(flat, weights=mw * np.broadcast_to(val[idx, None], touched.shape)[touched],
                                 minlength=n_cells)
    return density, sums


def grid_for_scene(scene, resolution=None) -> tuple[tuple[int, int, int], np.ndarray]:
    """The deposition grid for a scene's domain: ``(shape, cell_size)``.

    ``resolution``: None -> one cell per initial particle spacing (the grid
    baseline's default ``cells_per_spacing = 1``); an int n -> n cells along the
    longest axis and near-cubic cells elsewhere; a tuple (nx, ny, nz) -> exactly
    that.  Cell sizes divide the domain exactly (m).
    """
    size = checked_vector3("scene.domain.size", scene.domain.size, positive=True)
    if resolution is None:
        target = float(scene.particles.spacing)
        shape = tuple(max(1, int(round(s / target))) for s in size)
    elif np.ndim(resolution) == 0:
        n = int(resolution)
        if n < 1 or float(n) != float(resolution):
            raise ValueError(f"resolution = {resolution!r}: expected an integer >= 1 (cells along the longest axis)")
        target = float(size.max()) / n
        shape = tuple(max(1, int(round(s / target))) for s in size)
    else:
        shape = _shape3(resolution)
    return shape, size / np.array(shape, dtype=np.float64)


def deposit_state(state: Mapping[str, np.ndarray], scene, resolution=None,
                  fields: Iterable[str] = ("temperature", "vapor", "cloud")) -> dict:
    """Deposit a ``Simulation.state()`` dict on the scene's grid (see :func:`grid_for_scene`).

    Uses the particles' own ``mass`` (kg) and ``kernel_radius`` (m) and the scene's
    per-axis boundaries.  Returns the dict of :func:`deposit`.
    """
    missing = [k for k in ("position", "mass", "kernel_radius", *fields) if k not in state]
    if missing:
        have = ", ".join(sorted(state))
        raise KeyError(f"particle state lacks {', '.join(missing)} (has: {have}); "
                       "cloud statistics need a scene with an [atmosphere] section")
    shape, cell_size = grid_for_scene(scene, resolution)
    periodic = tuple(b == "periodic" for b in scene.domain.boundary)
    return deposit(state["position"], state["mass"], state["kernel_radius"],
                   {k: state[k] for k in fields}, shape, cell_size, periodic=periodic)
