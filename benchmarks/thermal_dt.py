"""How one heated thermal depends on the time step, term by term: which per-step operator keeps the model from
converging as dt shrinks.

The `cumulus` scene (one heated ground patch, eq. 5) shrunk to a 1.2 km x 1.6 km x 1.2 km box at 60 m spacing
(10,800 particles: minutes on one CPU core per run), run to the same simulated time at several dt, once as the
scene states it and once with each term switched off in turn (`pbf.scorr_k = 0`, `pbf.xsph = 0`,
`smoothing.kappa = 0`). Each row: the mean kinetic energy over samples every 50 s, J; the final kinetic energy;
the largest speed, m/s; the summed cloud water mixing ratio of all particles (a proxy of the cloud's water,
kg/kg summed) and the cloudy particles (q_c > 1e-5); the wall time. A term whose rows converge as dt shrinks
with the term off and diverge with it on is what the time-step model has left per step (docs/design.md,
"The time step").

Usage: python benchmarks/thermal_dt.py [--dts 4,2,1,0.5] [--variants default,noscorr] [--seeds 0]
                                       [--duration 600] [--backend cpu] [--out FILE.csv]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import pandas as pd

from cloudpbf.environment import commit, device_description
from cloudpbf.store.files import save_frame
from pbf_cuda import Simulation, load_scene

BOX = {"domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 60.0}
VARIANTS = {"default": {}, "noscorr": {"pbf.scorr_k": 0.0}, "noxsph": {"pbf.xsph": 0.0},
            "nokappa": {"smoothing.kappa": 0.0}, "it8": {"pbf.iterations": 8},
            "keepanomaly": {"pbf.shift_keeps_anomaly": True},
            "gradcorr": {"pbf.gradient_correction": True},
            "gradcorr_noscorr": {"pbf.gradient_correction": True, "pbf.scorr_k": 0.0},
            "scorr_sqrt": {"pbf.scorr_dt_power": 0.5}, "scorr_lin": {"pbf.scorr_dt_power": 1.0}}
SAMPLE_S = 50.0


def run(variant: str, dt: float, seed: int, duration: float, backend: str) -> dict:
    """One run of the shrunk cumulus at step dt with `variant`'s overrides; its row."""
    scene = load_scene("cumulus", **BOX, **VARIANTS[variant], **{"time.dt": dt})
    sim = Simulation(scene, backend=backend, seed=seed)
    every = max(1, int(round(SAMPLE_S / dt)))
    energies, started = [], time.perf_counter()
    for k in range(int(round(duration / dt))):
        sim.step(1)
        if (k + 1) % every == 0:
            energies.append(sim.stats()["kinetic_energy"])
    wall = time.perf_counter() - started
    state, stats = sim.state(), sim.stats()
    cloud = np.asarray(state["cloud"], dtype=np.float64)
    return {"variant": variant, "dt": dt, "seed": seed, "particles": sim.n_particles, "duration_s": duration,
            "kinetic_energy_mean": float(np.mean(energies)), "kinetic_energy_end": float(stats["kinetic_energy"]),
            "max_speed": float(stats["max_speed"]), "cloud_sum": float(cloud.sum()),
            "cloudy_particles": int((cloud > 1e-5).sum()), "wall_s": wall}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dts", default="4,2,1,0.5", help="time steps, s, comma-separated")
    parser.add_argument("--variants", default="default,noscorr", help=f"of {', '.join(VARIANTS)}")
    parser.add_argument("--seeds", default="0", help="noise seeds, comma-separated")
    parser.add_argument("--duration", type=float, default=600.0, help="simulated time of each run, s")
    parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--out", default=None, help="CSV to write (default: print only)")
    args = parser.parse_args(argv)
    if args.out and not args.out.lower().endswith((".csv", ".parquet")):
        parser.error(f"--out {args.out!r}: expected a .csv or .parquet file name")
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; allowed {', '.join(VARIANTS)}")
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        for variant in variants:
            for dt in (float(d) for d in args.dts.split(",")):
                rows.append(run(variant, dt, seed, args.duration, args.backend))
                r = rows[-1]
                print(f"{variant:8s} dt={dt:g} seed={seed}: KE mean {r['kinetic_energy_mean']:.4g} J, "
                      f"cloud {r['cloud_sum']:.4g}, {r['wall_s']:.0f} s", file=sys.stderr, flush=True)
    frame = pd.DataFrame(rows)
    frame["device"], frame["commit"] = device_description(args.backend), commit()
    print(frame.to_string(index=False))
    if args.out:
        save_frame(frame, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
