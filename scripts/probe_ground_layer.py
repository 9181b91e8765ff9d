"""Probe: the heated ground layer of a scene, uniform against adaptive particles (docs/cycling.md, the adaptive
twin; docs/validation.md, heat input of adaptive runs).

    # the CPU cycle of example 2 (bench.studies.cycling.CPU_OVERRIDES), every half model day:
    python scripts/probe_ground_layer.py cycling --cpu-cycle --every 600 --count 8
    python scripts/probe_ground_layer.py cycling_adaptive --cpu-cycle --set '{"adaptive.max_level": 3}' --every 600 --count 8
    # growing in a small box, every 200 s for 1000 s:
    python scripts/probe_ground_layer.py growing_adaptive --set '{"domain.size": [1200, 1600, 1200], "particles.spacing": 100, "time.dt": 8, "adaptive.criterion": "thermal"}'

Prints, every --every seconds: the heat the ground gave since the last line (stats()["heat_source_total"],
mass-weighted mean warming, K), the mass below heating_depth as a fraction of a full lattice layer, the
heated mass with eq. 5's layer weights (bench.statistics.heated_mass_fraction) as the same fraction, the
rest-density-relative mass of 50 m slabs, and the particles below heating_depth per level."""
import argparse
import json

import numpy as np

from bench.statistics import heated_mass_fraction
from bench.studies.cycling import CPU_OVERRIDES
from pbf_cuda import Simulation, load_scene
from pbf_cuda.scene import SceneError

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("scene")
parser.add_argument("--cpu-cycle", action="store_true", help="apply the CPU cycle's overrides first")
parser.add_argument("--set", default="{}", help="scene overrides as JSON, e.g. '{\"adaptive.max_level\": 3}'")
parser.add_argument("--every", type=float, default=200.0, help="s between lines")
parser.add_argument("--count", type=int, default=5, help="lines")
parser.add_argument("--backend", default="cpu", help="cpu (default) or cuda")
args = parser.parse_args()
try:
    extra = json.loads(args.set)
except json.JSONDecodeError as exc:
    parser.error(f"--set: not JSON ({exc})")
if not isinstance(extra, dict):
    parser.error("--set: expected a JSON object of dotted scene fields")
over = {**(CPU_OVERRIDES if args.cpu_cycle else {}), **extra}
try:
    scene = load_scene(args.scene).replace(**over)
except SceneError as exc:
    parser.error(str(exc))
sim = Simulation(scene, backend=args.backend, seed=0)
rho0, (lx, _, lz) = scene.particles.rest_density, scene.domain.size
depth = scene.atmosphere.heating_depth
full_layer = depth * lx * lz * rho0              # the mass of a full lattice layer below heating_depth
previous = 0.0
for _ in range(args.count):
    sim.step(round(args.every / scene.time.dt))
    s, heat = sim.state(), sim.stats()["heat_source_total"]
    y, m, level = s["position"][:, 1], s["mass"], s["level"].astype(int)
    slabs = [float(m[(y >= a) & (y < a + 50.0)].sum() / (50.0 * lx * lz * rho0)) for a in (0, 50, 100, 150)]
    below = y < depth
    print(f"t {sim.time:6.0f} s  heat {heat - previous:.3f} K  mass below {depth:.0f} m {m[below].sum() / full_layer:.2f}"
          f"  heated mass {heated_mass_fraction(s, scene):.2f}  slabs {np.round(slabs, 2).tolist()}"
          f"  levels below {depth:.0f} m {np.bincount(level[below], minlength=4).tolist()}", flush=True)
    previous = heat
