"""Study scales: how big every study's runs are on a CI box, a workstation CPU, or a GPU.

``smoke`` (CI and any machine without a GPU: the whole demo in a few minutes on 2 cores, clouds forming
in a small box), ``cpu`` (~50k particles in the scenes' 3.2 km domain, a workstation: hours on 2 cores),
``gpu`` (the paper's particle counts: the scene files' own spacing).  ``auto`` picks ``gpu`` when the
solver sees a CUDA device, else ``smoke`` (AUTO_WITHOUT_GPU); ``cpu`` is chosen by name only.

Scaling a cloud scene to fewer particles coarsens the lattice spacing by a factor f; the ground
heating layer (eq. 5) is thickened by f and its rate divided by f, so the heat flux S_e * depth
into the atmosphere is unchanged and the layer still holds particles.  The time step is kept;
step counts and snapshot intervals are multiplied by the scale's `step_fraction`.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

from cloudpbf.studies.registry import studies
from pbf_cuda import simulation
from pbf_cuda.scene import Scene

SCALE_NAMES = ("auto", "smoke", "cpu", "gpu")
AUTO_WITHOUT_GPU = "smoke"
"""What ``auto`` picks where the solver sees no CUDA device: the scale whose demo finishes in minutes on a CPU
and still forms clouds (the ``cpu`` scale's demo takes hours on 2 cores)."""


@dataclass(frozen=True)
class Scale:
    """Sizes of every study at one scale: the fields every study shares, here, and each study's own
    fields, declared in its file (Study.scale) and added to the class that SCALES holds.  Particle
    counts are fine-particle equivalents (an adaptive scene counts its level-0 particles times 2^max_level)."""
    name: str
    environment_label: str            # environment.json's scale: cpu-smoke | cpu | gpu
    particles: int | None             # cloud scenes' particle count (None: the scene files' spacing)
    step_fraction: float              # of each scene's time.steps


BASE = {
    "smoke": Scale("smoke", "cpu-smoke", particles=3000, step_fraction=0.5),
    "cpu": Scale("cpu", "cpu", particles=50_000, step_fraction=1.0),
    "gpu": Scale("gpu", "gpu", particles=None, step_fraction=1.0),
}


class _ScaleTable(Mapping):
    """{'smoke' | 'cpu' | 'gpu': Scale}: the shared sizes with every registered study's own, assembled
    on first use (the studies register when cloudpbf.studies.registry discovers them)."""

    def __init__(self):
        self._table = None

    def _build(self) -> dict:
        if self._table is None:
            declared = {}
            for study in studies():
                for name, values in study.scale.items():
                    if name in declared or any(f.name == name for f in dataclasses.fields(Scale)):
                        raise ValueError(f"scale field {name!r} is declared twice (study {study.name!r})")
                    declared[name] = values
            full = dataclasses.make_dataclass("Scale", [(name, object) for name in declared], bases=(Scale,),
                                              frozen=True)
            full.__doc__ = Scale.__doc__
            self._table = {key: full(**dataclasses.asdict(base), **{n: v[key] for n, v in declared.items()})
                           for key, base in BASE.items()}
        return self._table

    def __getitem__(self, key):
        return self._build()[key]

    def __iter__(self):
        return iter(self._build())

    def __len__(self):
        return len(self._build())


SCALES = _ScaleTable()


def resolve_scale(name: str) -> Scale:
    """The Scale for 'smoke' | 'cpu' | 'gpu' | 'auto' (gpu when the solver sees a CUDA device, else
    AUTO_WITHOUT_GPU)."""
    if name not in SCALE_NAMES:
        raise ValueError(f"scale = {name!r}: allowed {', '.join(SCALE_NAMES)}")
    if name == "auto":
        name = "gpu" if "cuda" in simulation.available_backends() else AUTO_WITHOUT_GPU
    return SCALES[name]


def fine_particles(scene: Scene) -> int:
    """Initial particle count, adaptive scenes counted at their finest level (x 2^max_level)."""
    n = scene.estimated_particles()
    return n * 2 ** scene.adaptive.max_level if scene.adaptive.enabled else n


def _coarsen(scene: Scene, factor: float, extra: dict | None = None) -> Scene:
    changes = {"particles.spacing": scene.particles.spacing * factor, **(extra or {})}
    if scene.thermodynamics and factor > 1.0:
        # a layer as many particles deep as at the scene's spacing, with the same heat flux S_e * depth (eq. 5;
        # the layer weighting of eq. 5 keeps the flux at any depth, this keeps where the heat goes)
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
