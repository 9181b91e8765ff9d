"""Initial particles of a scene (section 5 and 5.1 of the paper).

Fluid particles sit on a lattice filling `particles.fill_min..fill_max`; boundary particles
continue the same lattice for one kernel radius beyond each wall (eq. 18), so a fluid particle
next to a wall has a full neighbourhood. Periodic axes need no boundary particles.

Per axis the lattice spacing is the domain length divided by a whole number of sites
(the closest to `particles.spacing`), so the lattice closes across periodic boundaries.
"""
from __future__ import annotations

import math

import numpy as np

from .kernels import poly6
from .scene import Scene


def lattice_counts(scene: Scene) -> tuple[int, int, int]:
    """Sites per axis of the global lattice covering the domain."""
    d = scene.particles.spacing
    return tuple(max(1, int(round(L / d))) for L in scene.domain.size)


def lattice_spacings(scene: Scene) -> np.ndarray:
    """Per-axis lattice spacing (m): domain length / sites."""
    counts = lattice_counts(scene)
    return np.array([L / n for L, n in zip(scene.domain.size, counts)], dtype=np.float64)


def lattice_mass(scene: Scene) -> float:
    """m0 (kg) such that a particle with a full lattice neighbourhood has density rho0 (eq. 1)."""
    h = scene.kernel_radius
    ds = lattice_spacings(scene)
    r = [int(math.ceil(h / dd)) + 1 for dd in ds]
    grids = np.meshgrid(*[np.arange(-k, k + 1) * dd for k, dd in zip(r, ds)], indexing="ij")
    dist = np.sqrt(sum(g.astype(np.float64) ** 2 for g in grids)).ravel()
    total = float(np.sum(poly6(dist.astype(np.float32), h), dtype=np.float64))
    return scene.particles.rest_density / total


def _axis_sites(scene: Scene, axis: int, extend: int) -> np.ndarray:
    n = lattice_counts(scene)[axis]
    d = lattice_spacings(scene)[axis]
    return (np.arange(-extend, n + extend) + 0.5) * d


def fluid_particles(scene: Scene) -> dict[str, np.ndarray]:
    """Fluid particles: positions (N,3) m, velocities (N,3) m/s, T K, vapor/cloud kg/kg, mass kg, id."""
    lo, hi = scene.fill_box()
    axes = []
    for a in range(3):
        sites = _axis_sites(scene, a, 0)
        axes.append(sites[(sites >= lo[a] - 1e-9) & (sites <= hi[a] + 1e-9)])
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pos = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1).astype(np.float32)
    n = len(pos)
    rng = np.random.default_rng(scene.particles.seed)
    vel = np.zeros((n, 3), dtype=np.float64)
    if scene.particles.max_speed > 0.0:
        direction = rng.normal(size=(n, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        speed = rng.uniform(0.0, scene.particles.max_speed, size=(n, 1))
        vel += direction * speed
    if scene.wave is not None and scene.wave.amplitude > 0.0:
        vel += wave_velocity(scene, pos.astype(np.float64))
    out = {
        "position": pos,
        "velocity": np.ascontiguousarray(vel, dtype=np.float32),
        "mass": np.full(n, lattice_mass(scene), dtype=np.float32),
        "id": np.arange(n, dtype=np.uint32),
    }
    if scene.thermodynamics:
        T, v = environment_state(scene, pos[:, 1].astype(np.float64))
        out["temperature"] = T.astype(np.float32)
        out["vapor"] = v.astype(np.float32)
        out["cloud"] = np.zeros(n, dtype=np.float32)
    else:
        zeros = np.zeros(n, dtype=np.float32)
        out.update(temperature=zeros, vapor=zeros, cloud=zeros)
    return out


def environment_state(scene: Scene, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Initial temperature T0(y) (K) and vapor (kg/kg) of section 5."""
    from .environment import EnvironmentProfile, vapor_ratio
    a = scene.atmosphere
    T = scene.environment_temperature(y)
    reference = T if a.vapor_profile == "relative" else np.full_like(y, a.ground_temperature)
    k = vapor_ratio(EnvironmentProfile.of(a), a.initial_vapor_ratio, a.vapor_ratio_above, y)
    return T, k * scene.saturation(reference)


def wave_velocity(scene: Scene, pos: np.ndarray) -> np.ndarray:
    """Velocity of one internal-wave mode, stream function psi = a sin(kx x) sin(ky y) (m/s)."""
    w = scene.wave
    Lx, Ly = scene.domain.size[0], scene.domain.size[1]
    kx = 2.0 * math.pi * w.modes_x / Lx
    ky = math.pi * w.modes_y / Ly
    a = w.amplitude / kx   # peak vertical velocity = a kx
    x, y = pos[:, 0], pos[:, 1]
    u = np.zeros_like(pos)
    u[:, 0] = a * ky * np.sin(kx * x) * np.cos(ky * y)
    u[:, 1] = -a * kx * np.cos(kx * x) * np.sin(ky * y)
    return u


def boundary_particles(scene: Scene) -> dict[str, np.ndarray]:
    """Boundary particles: the lattice continued one kernel radius beyond each wall (eq. 18).

    Only the shell is built (one slab of lattice indices per wall axis, disjoint), never the lattice of
    the whole domain, so a large walled box with few fluid particles stays cheap.  The sites come in the
    order of the extended lattice (x index, then y, then z)."""
    h = scene.kernel_radius
    ds = lattice_spacings(scene)
    counts = lattice_counts(scene)
    walls = [b == "wall" for b in scene.domain.boundary]
    if not any(walls):
        empty = np.zeros((0, 3), dtype=np.float32)
        return {"position": empty, "temperature": np.zeros(0, np.float32), "vapor": np.zeros(0, np.float32)}
    ext = [int(math.ceil(h / ds[a])) if walls[a] else 0 for a in range(3)]
    full = [np.arange(-ext[a], counts[a] + ext[a]) for a in range(3)]
    pieces = []
    for a in range(3):
        if not walls[a]:
            continue
        # Sites outside the walls of axis a, inside the walls of the wall axes before it (disjoint slabs).
        ranges = []
        for b in range(3):
            if b == a:
                ranges.append(np.concatenate([np.arange(-ext[a], 0), np.arange(counts[a], counts[a] + ext[a])]))
            elif b < a and walls[b]:
                ranges.append(np.arange(counts[b]))
            else:
                ranges.append(full[b])
        grids = np.meshgrid(*ranges, indexing="ij")
        pieces.append(np.stack([g.ravel() for g in grids], axis=1))
    idx = np.concatenate(pieces)
    idx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
    pos = (idx + 0.5) * ds
    out = {"position": np.ascontiguousarray(pos, dtype=np.float32)}
    if scene.thermodynamics:
        # Boundary particles carry the environment profile at their own height (linear
        # continuation of T0), so smoothing leaves the resting atmosphere unchanged at the walls.
        T, v = environment_state(scene, pos[:, 1])
        out["temperature"] = T.astype(np.float32)
        out["vapor"] = v.astype(np.float32)
    else:
        out["temperature"] = np.zeros(len(pos), np.float32)
        out["vapor"] = np.zeros(len(pos), np.float32)
    return out
