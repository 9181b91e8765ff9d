"""Cloud statistics shared by the particle solver and the grid baseline.

Particles are first deposited onto a regular grid with the SPH poly6 kernel
(:func:`cloudpbf.deposition.deposit`, re-exported here); the grid baseline's fields
are already on one.  Both then go through the *same* diagnostics code
(:func:`diagnostics`, :func:`vertical_profiles`), so any difference between the
solvers is physics, not bookkeeping.

Conventions (the project's, see docs/design.md):

* grids are ``(nx, ny, nz)`` arrays on cell centres, ``y`` (axis 1) is up;
  cell ``j`` along y spans ``[origin_y + j dy, origin_y + (j + 1) dy]``;
* x and z are periodic, y has walls (the paper's cloud box);
* units are SI: m, s, K, kg/kg for vapor ``v`` and cloud ``w``, kg/m^3 for
  densities, kg/m^2 for the liquid water path;
* a cell is *cloudy* when ``w > threshold`` (default 1e-5 kg/kg).

Results are plain dicts (one row per snapshot) and pandas DataFrames, written
to CSV or Parquet with :func:`cloudpbf.store.files.save_frame`.
"""
from __future__ import annotations

import math
from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cloudpbf.deposition import (DEFAULT_PERIODIC, checked_vector3, deposit, deposit_state, grid_for_scene,
                              poly6)
from pbf_cuda.initial_state import lattice_mass, lattice_spacings

__all__ = [
    "CLOUD_THRESHOLD",
    "DIAGNOSTIC_COLUMNS",
    "PROFILE_COLUMNS",
    "poly6",
    "deposit",
    "grid_for_scene",
    "deposit_state",
    "cloudy_mask",
    "cloud_fraction_profile",
    "cloud_cover",
    "liquid_water_path",
    "cloud_base_top",
    "cloud_objects",
    "object_volumes",
    "vertical_profiles",
    "diagnostics",
    "particle_diagnostics",
    "particle_profiles",
    "grid_diagnostics",
    "grid_profiles",
    "timeseries_frame",
    "onset_time",
    "onset_times",
]

CLOUD_THRESHOLD = 1e-5
"""Default cloud mixing ratio (kg/kg) above which a cell counts as cloudy."""

DIAGNOSTIC_COLUMNS = (
    "cloud_cover", "lwp_mean", "lwp_max", "cloud_base", "cloud_top", "base_p10", "top_p90",
    "n_objects", "object_volume_mean", "object_volume_max", "cloudy_volume", "cloud_max",
    "total_water", "total_vapor", "total_cloud", "total_heat", "total_mass",
)
"""Keys of the dict returned by :func:`diagnostics`, in order."""

PROFILE_COLUMNS = ("z", "cloud_fraction", "temperature", "vapor", "cloud")
"""Columns of the DataFrame returned by :func:`vertical_profiles`."""

CLOUDY_COVER = 0.01
"""Cover (fraction of columns) above which a snapshot belongs to a run's cloudy period."""

CLOUD_MEANS = (("cloud_base", "cloud_base"), ("cloud_top", "cloud_top"), ("cover", "cloud_cover"),
               ("lwp", "lwp_mean"))
"""(name, diagnostics column) of the statistics averaged over a cloudy period (base, top in m; cover, a
fraction; mean LWP in kg/m^2): particles_vs_grid.csv's metrics, the sweep's <name>_mean columns."""


def relative_l2(values, reference, *, skip_nonfinite: bool = False) -> float:
    """||values - reference||_2 / ||reference||_2 of two equally long samples (series, profiles); NaN where the
    reference's norm is 0. skip_nonfinite: compare only the samples finite in both (series with gaps); else a
    non-finite sample in either makes the result NaN."""
    values, reference = np.asarray(values, dtype=float), np.asarray(reference, dtype=float)
    ok = np.isfinite(values) & np.isfinite(reference)
    if not skip_nonfinite and not ok.all():
        return math.nan
    norm = float(np.linalg.norm(reference[ok]))
    if not ok.any() or norm == 0.0:
        return math.nan
    return float(np.linalg.norm(values[ok] - reference[ok])) / norm


def cloudy_period_means(stats: pd.DataFrame) -> dict:
    """{<name>_mean: ...} of CLOUD_MEANS: time means of a run's diagnostics rows over its cloudy period (cover
    above CLOUDY_COVER); NaN without any cloudy row or without the column."""
    out = {f"{name}_mean": math.nan for name, _ in CLOUD_MEANS}
    if not len(stats) or "cloud_cover" not in stats:
        return out
    cloudy = stats[stats["cloud_cover"] > CLOUDY_COVER]
    for name, column in CLOUD_MEANS:
        if len(cloudy) and column in cloudy:
            out[f"{name}_mean"] = float(cloudy[column].mean())
    return out


# ------------------------------------------------------------------------------------------
# diagnostics on gridded fields
# ------------------------------------------------------------------------------------------
def _cell_geometry(fields: Mapping, cell_size, origin):
    dx = checked_vector3("cell_size", fields.get("cell_size") if cell_size is None else cell_size, positive=True)
    org = checked_vector3("origin", fields.get("origin", (0.0, 0.0, 0.0)) if origin is None else origin)
    return dx, org


def _grid(fields: Mapping, name: str) -> np.ndarray:
    if name not in fields:
        raise KeyError(f"fields lack '{name}' (have: {', '.join(sorted(map(str, fields)))})")
    arr = np.asarray(fields[name], dtype=np.float64)
    if arr.ndim != 3:
        raise ValueError(f"fields['{name}']: expected an (nx, ny, nz) grid, got shape {arr.shape}")
    return arr


def _air_density(fields: Mapping, shape, air_density: float) -> np.ndarray:
    """The density grid (kg/m^3): ``fields['density']`` if present, else uniform `air_density`."""
    if "density" in fields and fields["density"] is not None:
        rho = np.asarray(fields["density"], dtype=np.float64)
        if rho.shape != tuple(shape):
            raise ValueError(f"fields['density']: shape {rho.shape} differs from the field grids {tuple(shape)}")
        return rho
    if not (air_density > 0 and math.isfinite(air_density)):
        raise ValueError(f"air_density = {air_density!r}: expected a finite value > 0 kg/m^3")
    return np.full(shape, float(air_density))


def cloudy_mask(cloud: np.ndarray, threshold: float = CLOUD_THRESHOLD) -> np.ndarray:
    """Boolean grid: cloud mixing ratio w (kg/kg) above `threshold`."""
    if not (threshold >= 0 and math.isfinite(threshold)):
        raise ValueError(f"threshold = {threshold!r}: expected a finite value >= 0 kg/kg")
    return np.asarray(cloud) > threshold


def cloud_fraction_profile(cloud: np.ndarray, threshold: float = CLOUD_THRESHOLD) -> np.ndarray:
    """a_c(z): fraction of the cells of each horizontal layer that are cloudy, shape (ny,)."""
    return cloudy_mask(cloud, threshold).mean(axis=(0, 2))


def cloud_cover(cloud: np.ndarray, threshold: float = CLOUD_THRESHOLD) -> float:
    """Projected cloud cover: fraction of (x, z) columns holding at least one cloudy cell."""
    return float(cloudy_mask(cloud, threshold).any(axis=1).mean())


def liquid_water_path(cloud: np.ndarray, density: np.ndarray, dy: float) -> np.ndarray:
    """LWP per column, integral of rho w dy (kg/m^2), shape (nx, nz)."""
    return np.sum(np.asarray(density) * np.asarray(cloud), axis=1) * float(dy)


def cloud_base_top(cloud: np.ndarray, dy: float, y0: float = 0.0,
                   threshold: float = CLOUD_THRESHOLD) -> dict:
    """Cloud base and top heights (m).

    ``cloud_base`` / ``cloud_top``: lower face of the lowest and upper face of the
    highest cloudy cell; ``base_p10`` / ``top_p90``: 10th percentile of per-column
    bases and 90th percentile of per-column tops over cloudy columns.  All NaN
    when there is no cloud.
    """
    mask = cloudy_mask(cloud, threshold)
    ny = mask.shape[1]
    columns = mask.any(axis=1)
    if not columns.any():
        return dict(cloud_base=math.nan, cloud_top=math.nan, base_p10=math.nan, top_p90=math.nan)
    lowest = np.argmax(mask, axis=1)[columns]                     # first cloudy j per column
    highest = ny - 1 - np.argmax(mask[:, ::-1, :], axis=1)[columns]
    bases = y0 + lowest * dy
    tops = y0 + (highest + 1) * dy
    return dict(cloud_base=float(bases.min()), cloud_top=float(tops.max()),
                base_p10=float(np.percentile(bases, 10)), top_p90=float(np.percentile(tops, 90)))


def cloud_objects(mask: np.ndarray, periodic: Sequence[bool] = DEFAULT_PERIODIC) -> tuple[np.ndarray, np.ndarray]:
    """Connected cloudy regions (face connectivity), merged across periodic faces.

    Returns ``(labels, sizes)``: an int grid with 0 for clear air and 1..n for the
    objects, and the cell count of each object (length n, ordered by label).
    """
    mask = np.asarray(mask, dtype=bool)
    labels, n = ndimage.label(mask)
    if n == 0:
        return labels, np.zeros(0, dtype=np.int64)
    a_parts, b_parts = [], []
    for axis, wrap in enumerate(periodic):
        if not wrap:
            continue
        first = np.take(labels, 0, axis=axis)
        last = np.take(labels, -1, axis=axis)
        touch = (first > 0) & (last > 0)
        a_parts.append(first[touch])
        b_parts.append(last[touch])
    if a_parts:
        a = np.concatenate(a_parts)
        b = np.concatenate(b_parts)
        graph = coo_matrix((np.ones(a.size), (a, b)), shape=(n + 1, n + 1))
        _, component = connected_components(graph, directed=False)
        # renumber components of labels 1..n densely as 1..m (label 0 stays 0)
        _, dense = np.unique(component[1:], return_inverse=True)
        lut = np.concatenate([[0], dense.reshape(-1) + 1])
        labels = lut[labels]
        n = int(lut.max())
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    return labels, sizes


def object_volumes(fields: Mapping, cell_size=None, threshold: float = CLOUD_THRESHOLD,
                   periodic: Sequence[bool] = DEFAULT_PERIODIC) -> np.ndarray:
    """Volumes (m^3) of the cloud objects of gridded fields, largest first (the size distribution)."""
    dx, _ = _cell_geometry(fields, cell_size, None)
    _, sizes = cloud_objects(cloudy_mask(_grid(fields, "cloud"), threshold), periodic)
    return np.sort(sizes)[::-1] * float(np.prod(dx))


def diagnostics(fields: Mapping, cell_size=None, origin=None, threshold: float = CLOUD_THRESHOLD,
                air_density: float = 1.0, periodic: Sequence[bool] = DEFAULT_PERIODIC) -> dict:
    """One row of cloud statistics from gridded fields (both solvers).

    ``fields`` holds ``cloud`` w and ``vapor`` v (kg/kg), ``temperature`` T (K) on an
    (nx, ny, nz) grid, optionally ``density`` (kg/m^3, from :func:`deposit`; else the
    uniform `air_density`, the scene's rest density), ``cell_size`` and ``origin``
    (used when the arguments are None).

    Keys (:data:`DIAGNOSTIC_COLUMNS`): cloud_cover (fraction of columns); lwp_mean,
    lwp_max (kg/m^2, mean over all columns, max); cloud_base, cloud_top, base_p10,
    top_p90 (m, see :func:`cloud_base_top`); n_objects, object_volume_mean,
    object_volume_max (m^3, periodic-aware objects); cloudy_volume (m^3); cloud_max
    (kg/kg); total_water = sum rho (v + w) dV, total_vapor, total_cloud (kg);
    total_heat = sum rho T dV (K kg); total_mass = sum rho dV (kg).
    """
    dx, org = _cell_geometry(fields, cell_size, origin)
    w = _grid(fields, "cloud")
    v = _grid(fields, "vapor")
    t = _grid(fields, "temperature")
    for name, arr in (("vapor", v), ("temperature", t)):
        if arr.shape != w.shape:
            raise ValueError(f"fields['{name}']: shape {arr.shape} differs from fields['cloud'] {w.shape}")
    rho = _air_density(fields, w.shape, air_density)
    dv = float(np.prod(dx))
    mask = cloudy_mask(w, threshold)
    lwp = liquid_water_path(w, rho, dx[1])
    _, sizes = cloud_objects(mask, periodic)
    volumes = sizes * dv
    row = dict(
        cloud_cover=float(mask.any(axis=1).mean()),
        lwp_mean=float(lwp.mean()),
        lwp_max=float(lwp.max()),
        **cloud_base_top(w, dx[1], org[1], threshold),
        n_objects=int(sizes.size),
        object_volume_mean=float(volumes.mean()) if sizes.size else 0.0,
        object_volume_max=float(volumes.max()) if sizes.size else 0.0,
        cloudy_volume=float(mask.sum() * dv),
        cloud_max=float(w.max()),
        total_water=float(np.sum(rho * (v + w)) * dv),
        total_vapor=float(np.sum(rho * v) * dv),
        total_cloud=float(np.sum(rho * w) * dv),
        total_heat=float(np.sum(rho * t) * dv),
        total_mass=float(np.sum(rho) * dv),
    )
    return {k: row[k] for k in DIAGNOSTIC_COLUMNS}


def vertical_profiles(fields: Mapping, cell_size=None, origin=None, threshold: float = CLOUD_THRESHOLD,
                      air_density: float = 1.0) -> pd.DataFrame:
    """Horizontal-mean profiles against height: one row per layer (:data:`PROFILE_COLUMNS`).

    ``z`` is the layer's centre height (m); ``cloud_fraction`` is a_c(z); T (K),
    v and w (kg/kg) are density-weighted horizontal means (plain means on a uniform
    density grid; cells no particle reaches carry no weight).
    """
    dx, org = _cell_geometry(fields, cell_size, origin)
    w = _grid(fields, "cloud")
    rho = _air_density(fields, w.shape, air_density)
    layer_mass = rho.sum(axis=(0, 2))
    safe = np.where(layer_mass > 0, layer_mass, 1.0)

    def mean(name):
        out = np.sum(rho * _grid(fields, name), axis=(0, 2)) / safe
        return np.where(layer_mass > 0, out, np.nan)

    ny = w.shape[1]
    return pd.DataFrame({
        "z": org[1] + (np.arange(ny) + 0.5) * dx[1],
        "cloud_fraction": cloud_fraction_profile(w, threshold),
        "temperature": mean("temperature"),
        "vapor": mean("vapor"),
        "cloud": mean("cloud"),
    })



# ------------------------------------------------------------------------------------------
# the particles' own diagnostics
# ------------------------------------------------------------------------------------------
def heated_mass_fraction(state: Mapping[str, np.ndarray], scene) -> float:
    """The mass the ground heats (eq. 5) over rho0 times the volume below heating_depth H (dimensionless).
    As the solver does (csrc/thermodynamics.h, heated_fraction), a particle of mass m stands for the slab of
    its level's lattice spacing d = d_0 (m / m_0)^(1/3) centred on its height y, and counts by the part of
    that slab below H: min(1, max(0, (H - y + d / 2) / d)).  A lattice at rest reads m_0 / (rho0 d_x d_y d_z)
    at any spacing and H (0.990 at 100 m in `growing`: the lattice mass is set so that the SPH density is
    rho0)."""
    y = np.asarray(state["position"], dtype=np.float64)[:, 1]
    m = np.asarray(state["mass"], dtype=np.float64)
    depth = float(scene.atmosphere.heating_depth)
    d = float(lattice_spacings(scene)[1]) * np.cbrt(m / lattice_mass(scene))
    weight = np.clip((depth - (y - 0.5 * d)) / d, 0.0, 1.0)
    lx, _, lz = scene.domain.size
    return float(np.sum(m * weight) / (depth * lx * lz * scene.particles.rest_density))


# ------------------------------------------------------------------------------------------
# one entry point per solver, the same code behind both
# ------------------------------------------------------------------------------------------
def _periodic_of(scene) -> tuple[bool, bool, bool]:
    if scene is None:
        return DEFAULT_PERIODIC
    return tuple(b == "periodic" for b in scene.domain.boundary)


def _rest_density(scene) -> float:
    return 1.0 if scene is None else float(scene.particles.rest_density)


def particle_diagnostics(state: Mapping[str, np.ndarray], scene, resolution=None,
                         threshold: float = CLOUD_THRESHOLD) -> dict:
    """Diagnostics of a particle snapshot: :func:`deposit_state` then :func:`diagnostics`.

    The deposited density grid is the air density, so the water and heat budgets
    equal the particles' mass-weighted sums.
    """
    grid = deposit_state(state, scene, resolution)
    return diagnostics(grid, threshold=threshold, periodic=_periodic_of(scene))


def particle_profiles(state: Mapping[str, np.ndarray], scene, resolution=None,
                      threshold: float = CLOUD_THRESHOLD) -> pd.DataFrame:
    """Vertical profiles of a particle snapshot (deposited as in :func:`particle_diagnostics`)."""
    return vertical_profiles(deposit_state(state, scene, resolution), threshold=threshold)


def grid_diagnostics(fields: Mapping, scene=None, threshold: float = CLOUD_THRESHOLD) -> dict:
    """Diagnostics of ``GridSimulation.fields()`` (cell_size and origin are in the dict).

    Air density: ``fields['density']`` if present, else the scene's rest density
    (1 kg/m^3 without a scene).
    """
    return diagnostics(fields, threshold=threshold, air_density=_rest_density(scene),
                       periodic=_periodic_of(scene))


def grid_profiles(fields: Mapping, scene=None, threshold: float = CLOUD_THRESHOLD) -> pd.DataFrame:
    """Vertical profiles of ``GridSimulation.fields()``."""
    return vertical_profiles(fields, threshold=threshold, air_density=_rest_density(scene))


# ------------------------------------------------------------------------------------------
# time series
# ------------------------------------------------------------------------------------------
def timeseries_frame(rows: Iterable[Mapping], **labels) -> pd.DataFrame:
    """A DataFrame from diagnostics rows (each should carry ``time_s``), label columns first.

    ``timeseries_frame(rows, solver="particles", mode="adaptive", seed=3)`` gives the
    layout of ``compare_timeseries.csv``.  Rows are sorted by time when ``time_s`` exists.
    """
    df = pd.DataFrame(list(rows))
    for i, (key, value) in enumerate(labels.items()):
        df.insert(i, key, value)
    if "time_s" in df.columns:
        df = df.sort_values("time_s", kind="stable").reset_index(drop=True)
    return df


def onset_time(df: pd.DataFrame, cover_column: str = "cloud_cover", time_column: str = "time_s") -> float:
    """First time (s) with cloud cover > 0 in a time series; NaN if cloud never forms."""
    for col in (cover_column, time_column):
        if col not in df.columns:
            raise KeyError(f"time series lacks column '{col}' (has: {', '.join(map(str, df.columns))})")
    ordered = df.sort_values(time_column, kind="stable")
    cloudy = ordered[ordered[cover_column] > 0]
    return float(cloudy[time_column].iloc[0]) if len(cloudy) else math.nan


def onset_times(df: pd.DataFrame, by: Sequence[str] = ("solver", "mode", "seed"),
                cover_column: str = "cloud_cover", time_column: str = "time_s") -> pd.DataFrame:
    """Onset time per group (e.g. per solver, mode and seed): columns ``*by, onset_s``."""
    by = [b for b in by if b in df.columns]
    if not by:
        return pd.DataFrame({"onset_s": [onset_time(df, cover_column, time_column)]})
    rows = []
    for key, group in df.groupby(by, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        rows.append({**dict(zip(by, key)), "onset_s": onset_time(group, cover_column, time_column)})
    return pd.DataFrame(rows)
