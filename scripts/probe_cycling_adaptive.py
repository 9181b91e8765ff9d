"""Probe: a cycling scene (adaptive or not) with overrides, at GPU scale: cover every 50 s, cycles by the
study's rule, and the lowest 400 m's state every 200 s (particles per level, mass-weighted T and vapor).

    python scripts/probe_cycling_adaptive.py TAG SCENE SEED '{"particles.spacing": 52.07, "adaptive.max_level": 2}'

One JSON line per run (docs/cycling.md, reports/gpu/data/cycling_adaptive_probe.jsonl); BK=cpu for the CPU."""
import json, os, sys, time
import numpy as np
from bench.studies.cycling import count_cycles
from bench.statistics import grid_for_scene, particle_diagnostics
from pbf_cuda import Simulation, load_scene
tag, name, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
over = json.loads(sys.argv[4])
base = load_scene("cycling")
scene = load_scene(name).replace(**over)
shape, _ = grid_for_scene(base)
sim = Simulation(scene, backend=os.environ.get("BK", "cuda"), seed=seed)
t0 = time.time(); cover, n, diag = [], [], []
for k in range(scene.time.steps // 25):
    sim.step(25)
    st = sim.state()
    cover.append(float(particle_diagnostics(st, scene, shape)["cloud_cover"])); n.append(sim.n_particles)
    if k % 4 == 3:
        y = st["position"][:, 1]; m = st["mass"]; low = y < 400.0
        lv = np.bincount(st["level"].astype(int), minlength=4)[:4].tolist() if "level" in st else []
        diag.append({"t": round(sim.time), "levels": lv,
                     "T_low": float(np.average(st["temperature"][low], weights=m[low])),
                     "v_low": float(np.average(st["vapor"][low], weights=m[low])),
                     "w_tot": float(np.sum(m * st["cloud"])), "vmax": float(np.abs(st["velocity"]).max())})
c = count_cycles(cover)
print(json.dumps({"tag": tag, "scene": name, "seed": seed, "over": over, **c, "max_particles": max(n),
                  "mean_particles": float(np.mean(n)), "wall_s": time.time() - t0,
                  "cover": [round(x, 3) for x in cover[::4]], "diag": diag}), flush=True)
