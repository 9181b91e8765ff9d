"""Probe: the heated ground layer of `growing` in a small box (1200 x 1600 x 1200 m, 100 m spacing, dt 8 s,
1000 s), uniform against adaptive particles (docs/validation.md, "Heat input of adaptive runs").

    python scripts/probe_ground_layer_growing.py growing none
    python scripts/probe_ground_layer_growing.py growing_adaptive paper      # or thermal, lookahead

Every 200 s: the ground's heat since the last line (mass-weighted mean warming, K), the mass below 100 m and
the layer-weighted heated mass (eq. 5) as fractions of a full lattice layer, particles below 100 m per level."""
import sys, numpy as np
from pbf_cuda import Simulation, load_scene
name, crit = sys.argv[1], sys.argv[2]
over = {"domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 8.0}
if "adaptive" in name: over["adaptive.criterion"] = crit
scene = load_scene(name).replace(**over)
sim = Simulation(scene, backend="cpu", seed=0)
lx, lz = 1200.0, 1200.0; layer = 100.0 * lx * lz * scene.particles.rest_density
m0 = sim.state()["mass"].max(); prev = 0.0
for k in range(5):
    sim.step(25)
    s, st = sim.state(), sim.stats(); y, m = s["position"][:, 1], s["mass"]
    d = 100.0 * np.cbrt(m / m0); w = np.clip((100.0 - (y - 0.5 * d)) / d, 0, 1)
    print(name, crit, f"t {sim.time:5.0f} heat {st['heat_source_total'] - prev:.3f} mass<100 {m[y < 100].sum() / layer:.2f} heated {np.sum(m * w) / layer:.2f} n {sim.n_particles} levels<100 {np.bincount(s['level'].astype(int)[y < 100], minlength=4).tolist()}", flush=True)
    prev = st["heat_source_total"]
