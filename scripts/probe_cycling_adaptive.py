"""Probe: the adaptive cycling twin with other refinement settings (GPU scale), cover every 50 s."""
import json, sys, time
import numpy as np
from bench.studies.cycling import count_cycles
from bench.statistics import grid_for_scene, particle_diagnostics
from pbf_cuda import Simulation, load_scene
tag, seed = sys.argv[1], int(sys.argv[2])
over = json.loads(sys.argv[3])
base = load_scene("cycling")
scene = load_scene("cycling_adaptive").replace(**over)
shape, _ = grid_for_scene(base)
sim = Simulation(scene, backend="cuda", seed=seed)
t0 = time.time(); cover, n = [], []
for _ in range(scene.time.steps // 25):
    sim.step(25)
    cover.append(float(particle_diagnostics(sim.state(), scene, shape)["cloud_cover"])); n.append(sim.n_particles)
print(json.dumps({"tag": tag, "seed": seed, "over": over, **count_cycles(cover), "max_particles": max(n),
                  "mean_particles": float(np.mean(n)), "wall_s": time.time() - t0,
                  "cover": [round(c, 3) for c in cover[::4]]}), flush=True)
