"""Probe: the heated ground layer of the CPU cycle, uniform against adaptive particles (docs/cycling.md).

    python scripts/probe_ground_layer.py cycling 0            # uniform, 100 m
    python scripts/probe_ground_layer.py cycling_adaptive 3   # adaptive, 100 m level 0, max level 3

Prints, every half model day (600 s; the ground is heated in the first half of each day): the heat the ground gave since the
last line (stats()["heat_source_total"], mass-weighted mean warming, K), the mass below 100 m as a
fraction of a full lattice layer, the layer-weighted heated mass (eq. 5's weights) as a fraction of the
column's, the rest-density-relative mass in 50 m slabs, and the particles below 100 m per level."""
import sys

import numpy as np

from bench.studies.cycling import CPU_OVERRIDES
from pbf_cuda import Simulation, load_scene

name, max_level = sys.argv[1], int(sys.argv[2])
over = dict(CPU_OVERRIDES)
if max_level:
    over["adaptive.max_level"] = max_level
scene = load_scene(name).replace(**over)
sim = Simulation(scene, backend="cpu", seed=0)
rho0, (lx, _, lz) = scene.particles.rest_density, scene.domain.size
d0, depth = scene.particles.spacing, scene.atmosphere.heating_depth
m0 = sim.state()["mass"].max()
layer = depth * lx * lz * rho0                 # the mass of a full lattice layer below heating_depth
previous = 0.0
for k in range(8):
    sim.step(round(600.0 / scene.time.dt))                 # half a model day (P = 1200 s)
    s, st = sim.state(), sim.stats()
    y, m, level = s["position"][:, 1], s["mass"], s["level"].astype(int)
    d = d0 * np.cbrt(m / m0)
    weight = np.clip((depth - (y - 0.5 * d)) / d, 0.0, 1.0)
    slabs = [float(m[(y >= a) & (y < a + 50.0)].sum() / (50.0 * lx * lz * rho0)) for a in (0, 50, 100, 150)]
    heat = st["heat_source_total"]
    print(f"t {sim.time:6.0f} s  heat {heat - previous:.3f} K  mass below {depth:.0f} m {m[y < depth].sum() / layer:.2f}"
          f"  heated mass {np.sum(m * weight) / layer:.2f}  slabs {np.round(slabs, 2).tolist()}"
          f"  levels below {depth:.0f} m {np.bincount(level[y < depth], minlength=4).tolist()}", flush=True)
    previous = heat
