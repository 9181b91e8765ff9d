"""Probe: particles against the grid (cloud base, top, cover, LWP) at the compare study's `cpu` scale, with
variants of the smoothed fields (docs/validation.md, reports/gpu/data/smoothing_fields_probe.jsonl).

    python scripts/probe_smoothing_fields.py '{"shipped": {}, "TVC": {"smoothing.fields": ["temperature", "vapor", "cloud"]}}' 5

The particles run `growing` scaled to 50k particles for each seed; the grid's series are the committed
5-seed grid runs of reports/gpu/data/compare_timeseries.csv.  BK=cpu runs the particles on the CPU."""
import json, os, sys, time

import pandas as pd
from bench.statistics import grid_for_scene, particle_diagnostics
from bench.studies.compare import particles_vs_grid
from bench.studies.scales import scale_scene
from pbf_cuda import Simulation, load_scene

variants = json.loads(sys.argv[1])
seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 5
ts = pd.read_csv("reports/gpu/data/compare_timeseries.csv")
grid = ts[ts["solver"] == "grid"]
base = scale_scene(load_scene("growing"), 50_000, 1.0)
shape, _ = grid_for_scene(base)                  # the compare study's deposit grid, one cell per spacing
for tag, over in variants.items():
    scene = base.replace(**over) if over else base
    rows = []
    t0 = time.time()
    for seed in range(seeds):
        sim = Simulation(scene, backend=os.environ.get("BK", "cuda"), seed=seed)
        for k in range(scene.time.steps // 50 + 1):
            if k:
                sim.step(50)
            d = particle_diagnostics(sim.state(), scene, shape)
            rows.append({"mode": "non-adaptive", "seed": seed, "time_s": round(sim.time, 6),
                         **{c: d[c] for c in ("cloud_cover", "lwp_mean", "cloud_base", "cloud_top")}})
    part = pd.DataFrame(rows)
    both = pd.concat([part, grid[["mode", "seed", "time_s", "cloud_cover", "lwp_mean", "cloud_base", "cloud_top"]]])
    pvg = particles_vs_grid(both)
    base_t = part.groupby("time_s")[["cloud_cover", "cloud_base", "cloud_top", "lwp_mean"]].mean()
    print(json.dumps({"tag": tag, "over": over, "wall_s": time.time() - t0,
                      "pvg": pvg[["metric", "particles", "grid", "rel_diff"]].round(3).to_dict("records"),
                      "series": base_t.round(3).reset_index().to_dict("list")}), flush=True)
