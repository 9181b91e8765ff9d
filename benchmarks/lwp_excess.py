"""What makes the particles' liquid water path exceed the grid's: a cloud scene (`growing` by default) in a
1.2 x 3.2 x 1.2 km column at 60 m (particle spacing and grid cells alike; 21,200 particles, minutes on a CPU
core per run) or in its own domain (--paper-scale, at any --spacing), each seed's cover, mean LWP, cloud base
and top every 100 s as the harness deposits and measures them (cloudpbf.statistics), for these variants:
the grid baseline on the same scene; the particles as the scene states them (`default`); s_corr at half its k
and without it; eq. 17 mixing temperature and vapour but not cloud water (`cloud_unmixed`, the cloud scenes'
default before 267231a: rows labelled `default` from earlier commits are this variant); eq. 17 mixing all three
(`mix_all`, the default since) and the same at twice kappa. docs/validation.md, "What makes the LWP excess",
has the measurements.

Usage: python benchmarks/lwp_excess.py [--variants grid,default,cloud_unmixed,...] [--seeds 0,1] [--duration 1000]
                                       [--paper-scale] [--scene NAME] [--spacing M] [--backend cpu|cuda]
                                       [--out FILE.csv]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import pandas as pd

from cloudpbf.environment import commit, device_description
from cloudpbf.statistics import grid_diagnostics, particle_diagnostics
from cloudpbf.store.files import save_frame
from pbf_cuda import Simulation, load_scene
from pbf_cuda.scene import list_scenes

BOX = {"domain.size": [1200.0, 3200.0, 1200.0], "particles.spacing": 60.0}
VARIANTS = {"grid": {}, "default": {}, "scorr_half": {"pbf.scorr_k": 0.05}, "scorr0": {"pbf.scorr_k": 0.0},
            "cloud_unmixed": {"smoothing.fields": ["temperature", "vapor"]},
            "mix_all": {"smoothing.fields": ["temperature", "vapor", "cloud"]},
            "mix_all_k2": {"smoothing.fields": ["temperature", "vapor", "cloud"], "smoothing.kappa": 0.2}}
SAMPLE_S = 100.0
KEYS = ("cloud_cover", "lwp_mean", "cloud_base", "cloud_top")


def run(variant: str, seed: int, duration: float, paper_scale: bool = False, backend: str = "cpu",
        spacing: float | None = None, scene_name: str = "growing") -> list[dict]:
    """Rows every SAMPLE_S of one run: the grid baseline for 'grid', else the particles with the overrides;
    in the CPU column (BOX) or, with paper_scale, in the scene's own domain at its own spacing (or `spacing`, m:
    particle spacing and grid cell alike)."""
    size = {} if paper_scale else BOX
    if spacing:
        size = {**size, "particles.spacing": float(spacing)}
    scene = load_scene(scene_name, **size, **VARIANTS[variant])
    steps = int(round(SAMPLE_S / scene.time.dt))
    started, rows = time.perf_counter(), []
    if variant == "grid":
        from grid_baseline import GridSimulation  # grid extra (jax-cfd)
        sim = GridSimulation(scene, seed=seed)
    else:
        sim = Simulation(scene, backend=backend, seed=seed)
    for k in range(int(round(duration / SAMPLE_S))):
        sim.step(steps)
        if variant == "grid":
            fields = {key: np.asarray(v) for key, v in sim.fields().items()}
            fields["cell_size"], fields["origin"] = np.asarray(sim.cell_size, float), np.zeros(3)
            d = grid_diagnostics(fields, scene)
        else:
            d = particle_diagnostics(sim.state(), scene)
        rows.append({"scene": scene_name, "variant": variant, "seed": seed, "time_s": (k + 1) * SAMPLE_S,
                     "spacing_m": scene.particles.spacing, **{key: d.get(key) for key in KEYS}})
    wall = time.perf_counter() - started
    for row in rows:
        row["wall_s"] = wall
    return rows


def labelled(rows: list[dict], args) -> pd.DataFrame:
    """The rows with their device, commit and scale."""
    frame = pd.DataFrame(rows)
    frame["device"], frame["commit"] = device_description(args.backend), commit()
    frame["scale"] = "paper" if args.paper_scale else "column"
    return frame


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default="grid,default,scorr_half,scorr0", help=f"of {', '.join(VARIANTS)}")
    parser.add_argument("--seeds", default="0,1", help="noise seeds, comma-separated")
    parser.add_argument("--duration", type=float, default=1000.0, help="simulated time of each run, s")
    parser.add_argument("--out", default=None, help="CSV of every sample")
    parser.add_argument("--paper-scale", action="store_true", help="the scene's own 3.2 km domain and spacing")
    parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--scene", default="growing", help="a cloud scene (growing, cumulus, shallow_cumulus, ..)")
    parser.add_argument("--spacing", type=float, default=None,
                        help="particle spacing = grid cell, m (default: the column's; the scene's with --paper-scale)")
    args = parser.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; allowed {', '.join(VARIANTS)}")
    if args.spacing is not None and not args.spacing > 0.0:
        parser.error(f"--spacing: {args.spacing}: expected a spacing in m above 0")
    if args.scene not in list_scenes():
        parser.error(f"--scene: unknown {args.scene!r}; shipped scenes: {', '.join(list_scenes())}")
    rows = []
    for variant in variants:
        for seed in (int(s) for s in args.seeds.split(",")):
            rows += run(variant, seed, args.duration, args.paper_scale, args.backend, args.spacing, args.scene)
            print(f"{variant} seed {seed}: LWP {rows[-1]['lwp_mean']:.3f} kg/m^2 at {args.duration:g} s", flush=True)
            if args.out:                 # after every run: a run cut by a time limit keeps the rows before it
                save_frame(labelled(rows, args), args.out)
    frame = labelled(rows, args)
    late = frame[frame["time_s"] >= args.duration / 2]
    print(late.groupby(["scene", "variant", "spacing_m"])[list(KEYS)].mean().to_string())
    if args.out:
        save_frame(frame, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
