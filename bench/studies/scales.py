"""Study scales: how big every study's runs are on a CI box, a workstation CPU, or a GPU.

``smoke`` (CI, 2 cores, the whole demo in a few minutes), ``cpu`` (~50k particles, a laptop or
workstation), ``gpu`` (the paper's particle counts: the scene files' own spacing).  ``auto`` picks
``gpu`` when the solver sees a CUDA device, else ``cpu``.

Scaling a cloud scene to fewer particles coarsens the lattice spacing by a factor f; the ground
heating layer (eq. 5) is thickened by f and its rate divided by f, so the heat flux S_e * depth
into the atmosphere is unchanged and the layer still holds particles.  The time step is kept;
step counts and snapshot intervals are multiplied by the scale's `step_fraction`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from pbf_cuda.scene import Scene

SCALE_NAMES = ("auto", "smoke", "cpu", "gpu")


@dataclass(frozen=True)
class Scale:
    """Sizes of every study at one scale.  Particle counts are fine-particle equivalents
    (an adaptive scene counts its level-0 particles times 2^max_level)."""
    name: str
    environment_label: str            # environment.json's scale: cpu-smoke | cpu | gpu
    particles: int | None             # cloud scenes' particle count (None: the scene files' spacing)
    step_fraction: float              # of each scene's time.steps
    seeds: int                        # compare: noise seeds per mode
    slab_particles: int | None        # Figure 1 slab
    sweep_particles: tuple            # spacing sweep, coarse to fine (the finest is the reference)
    sweep_iterations: tuple           # PBF iterations at the middle spacing
    sweep_split_thresholds: tuple     # adaptive split threshold alpha at the middle spacing
    sweep_grid_cells: tuple           # grid cells along the longest axis, coarse to fine
    stress_particles: int
    stress_steps: int
    stress_dt: tuple                  # s
    stress_iterations: tuple
    stress_alpha_dt: tuple            # phase_rate * dt (dimensionless)
    scaling_particles: tuple
    scaling_grid_cells: tuple         # n for an n^3 grid
    timing_steps: int                 # timed steps of a scaling run (after 2 warm-up steps)


STRESS_DT = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0)
STRESS_ITERATIONS = (1, 2, 4, 8)
STRESS_ALPHA_DT = (0.1, 1.0, 10.0, 100.0, 1000.0)

SCALES = {
    "smoke": Scale("smoke", "cpu-smoke", particles=3000, step_fraction=0.5, seeds=5, slab_particles=2000,
                   sweep_particles=(2000, 3000, 5000), sweep_iterations=(2, 8),
                   sweep_split_thresholds=(0.15, 0.6), sweep_grid_cells=(8, 12, 16),
                   stress_particles=2000, stress_steps=30, stress_dt=STRESS_DT, stress_iterations=STRESS_ITERATIONS,
                   stress_alpha_dt=STRESS_ALPHA_DT,
                   scaling_particles=(2000, 8000), scaling_grid_cells=(12, 20), timing_steps=5),
    "cpu": Scale("cpu", "cpu", particles=50_000, step_fraction=1.0, seeds=5, slab_particles=25_000,
                 sweep_particles=(12_500, 25_000, 50_000, 100_000), sweep_iterations=(1, 2, 8, 16),
                 sweep_split_thresholds=(0.1, 0.2, 0.5, 1.0), sweep_grid_cells=(16, 24, 32, 48),
                 stress_particles=10_000, stress_steps=100, stress_dt=STRESS_DT, stress_iterations=STRESS_ITERATIONS,
                 stress_alpha_dt=STRESS_ALPHA_DT,
                 scaling_particles=(10_000, 50_000, 250_000), scaling_grid_cells=(16, 32, 48), timing_steps=10),
    "gpu": Scale("gpu", "gpu", particles=None, step_fraction=1.0, seeds=5, slab_particles=None,
                 sweep_particles=(100_000, 250_000, 840_000, 2_000_000), sweep_iterations=(1, 2, 8, 16),
                 sweep_split_thresholds=(0.1, 0.2, 0.5, 1.0), sweep_grid_cells=(32, 48, 64, 96),
                 stress_particles=100_000, stress_steps=200, stress_dt=STRESS_DT,
                 stress_iterations=STRESS_ITERATIONS, stress_alpha_dt=STRESS_ALPHA_DT,
                 scaling_particles=(250_000, 1_000_000, 4_000_000), scaling_grid_cells=(32, 64, 96),
                 timing_steps=20),
}


def resolve_scale(name: str) -> Scale:
    """The Scale for 'smoke' | 'cpu' | 'gpu' | 'auto' (gpu when the solver sees a CUDA device)."""
    if name not in SCALE_NAMES:
        raise ValueError(f"scale = {name!r}: allowed {', '.join(SCALE_NAMES)}")
    if name == "auto":
        from pbf_cuda.simulation import available_backends
        name = "gpu" if "cuda" in available_backends() else "cpu"
    return SCALES[name]


def fine_particles(scene: Scene) -> int:
    """Initial particle count, adaptive scenes counted at their finest level (x 2^max_level)."""
    n = scene.estimated_particles()
    return n * 2 ** scene.adaptive.max_level if scene.adaptive.enabled else n


def _coarsen(scene: Scene, factor: float, extra: dict | None = None) -> Scene:
    changes = {"particles.spacing": scene.particles.spacing * factor, **(extra or {})}
    if scene.thermodynamics and factor > 1.0:
        # keep the heat flux S_e * depth (eq. 5); the thicker layer still holds particles
        changes["atmosphere.heating_depth"] = scene.atmosphere.heating_depth * factor
        changes["atmosphere.heating_rate"] = scene.atmosphere.heating_rate / factor
    return scene.replace(**changes)


def scale_steps(scene: Scene, step_fraction: float) -> Scene:
    """time.steps and time.snapshot_every multiplied by step_fraction (at least 1 each)."""
    if step_fraction == 1.0:
        return scene
    steps = max(1, int(round(scene.time.steps * step_fraction)))
    every = max(1, min(steps, int(round(scene.time.snapshot_every * step_fraction))))
    return scene.replace(**{"time.steps": steps, "time.snapshot_every": every})


def scale_scene(scene: Scene, particles: int | None, step_fraction: float = 1.0) -> Scene:
    """`scene` with about `particles` fine-particle equivalents (None: unchanged) and scaled steps."""
    if particles is not None:
        factor = (fine_particles(scene) / float(particles)) ** (1.0 / 3.0)
        scene = _coarsen(scene, factor)
    return scale_steps(scene, step_fraction)


def scale_slab(scene: Scene, particles: int | None, step_fraction: float = 1.0) -> Scene:
    """A quasi-2D slab (periodic z, a few particles thick) at about `particles` particles.

    The lattice keeps its layer count along z (z size = layers * spacing, slightly padded so the
    periodic axis stays >= 3 kernel radii), x and y are refined or coarsened."""
    if particles is not None:
        nx, ny, nz = scene.lattice_shape()
        size = scene.domain.size
        spacing = math.sqrt(nz * size[0] * size[1] / float(particles))
        factor = spacing / scene.particles.spacing
        depth = max(nz, 3.0 * scene.particles.kernel_ratio) * spacing * (1.0 + 1e-9)
        scene = _coarsen(scene, factor, {"domain.size": [size[0], size[1], depth]})
    return scale_steps(scene, step_fraction)
