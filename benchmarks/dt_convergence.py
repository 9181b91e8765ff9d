"""The model's convergence in the time step: one scene at several dt, with the per-step coefficients stated at
time.reference_dt (rates per unit time, the default) and stated per step (time.reference_dt = dt, the model before
rates), seed means of the cover, cloudy volume and mean LWP series, each run's error against the smallest step's
run of the same mode (relative L2 as cloudpbf/studies/adaptive_pareto.py defines it), and the wall time per simulated
second.

Usage: python benchmarks/dt_convergence.py [--scene growing] [--spacing 68] [--seeds 3] [--dts 0.5,1,2,4]
                                           [--duration 1000] [--every 50] [--modes rate,per_step] [--backend auto]
                                           [--out FILE.csv]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import pandas as pd

from cloudpbf.environment import commit, device_description
from cloudpbf.store.files import save_frame
from cloudpbf.statistics import particle_diagnostics
from cloudpbf.statistics import relative_l2
from cloudpbf.studies.adaptive_pareto.design import SERIES
from pbf_cuda import InstabilityError, Simulation, load_scene

SERIES_USED = [(k, c) for k, c in SERIES if k in ("cover", "volume", "lwp")]
# The models compared, as scene overrides at step dt: the per-step coefficients as rates stated at
# time.reference_dt (the default); stated per step (the model before rates); rates with s_corr's k scaled by
# (dt / reference_dt)^0.5 (pbf.scorr_dt_power, docs/design.md "The time step").
MODES = {"rate": lambda dt: {}, "per_step": lambda dt: {"time.reference_dt": dt},
         "scorr_sqrt": lambda dt: {"pbf.scorr_dt_power": 0.5}}


def series(scene, backend: str, seed: int, duration: float, every: float) -> tuple[dict, float]:
    """The run's cover, cloudy volume and mean LWP every `every` s, and its wall time in s (steps only)."""
    sim = Simulation(scene, backend=backend, seed=seed)
    chunk = max(1, int(round(every / scene.time.dt)))
    out = {k: [] for k, _ in SERIES_USED} | {"time": []}
    wall = 0.0
    while sim.time < duration - 1e-6:
        t0 = time.perf_counter()
        sim.step(chunk)
        sim.stats()                      # waits for the device
        wall += time.perf_counter() - t0
        row = particle_diagnostics(sim.state(), scene)
        out["time"].append(sim.time)
        for key, column in SERIES_USED:
            out[key].append(row[column])
    return {k: np.asarray(v, float) for k, v in out.items()}, wall


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="growing")
    ap.add_argument("--spacing", type=float, default=68.0)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--dts", default="0.5,1,2,4")
    ap.add_argument("--duration", type=float, default=1000.0)
    ap.add_argument("--every", type=float, default=50.0)
    ap.add_argument("--modes", default="rate,per_step")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    dts = sorted(float(x) for x in a.dts.split(","))
    means = {}
    modes = a.modes.split(",")
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        ap.error(f"--modes: unknown {', '.join(unknown)}; allowed {', '.join(MODES)}")
    rows = []
    for mode in modes:
        for dt in dts:                   # ascending: the smallest step, each mode's reference, first
            per_seed, walls = [], []
            for seed in range(a.seeds):
                overrides = {"particles.spacing": a.spacing, "time.dt": dt}
                overrides.update(MODES[mode](dt))
                scene = load_scene(a.scene, **overrides)
                try:
                    s, wall = series(scene, a.backend, seed, a.duration, a.every)
                except InstabilityError as err:
                    print(f"{mode} dt {dt:g} s seed {seed}: unstable ({err})", flush=True)
                    continue
                per_seed.append(s)
                walls.append(wall / a.duration)
            row = {"scene": a.scene, "spacing_m": a.spacing, "mode": mode, "dt_s": dt, "seeds": a.seeds,
                   "stable_seeds": len(per_seed)}
            reference = means.get((mode, dts[0]))
            if per_seed:
                n = min(len(s["time"]) for s in per_seed)
                mean = {k: np.mean([s[k][:n] for s in per_seed], axis=0) for k in per_seed[0]}
                means[(mode, dt)] = mean
                reference = reference if reference is not None else mean
                errs = [relative_l2(np.interp(reference["time"], mean["time"], mean[k]), reference[k],
                                    skip_nonfinite=True) for k, _ in SERIES_USED]
                row.update({"wall_s_per_simulated_s": float(np.median(walls)),
                            "cover_end": float(mean["cover"][-1]), "lwp_end": float(mean["lwp"][-1])})
                row.update({f"e_{k}": e for (k, _), e in zip(SERIES_USED, errs)})
                row["error"] = float(np.mean(errs))
                print(f"{mode:9s} dt {dt:5g} s: cover {mean['cover'][-1]:.3f}, LWP {mean['lwp'][-1]:.3f} kg/m^2, "
                      f"error {row['error']:.3f}, {np.median(walls) * 1e3:.3f} ms per simulated s", flush=True)
            rows.append(row)
            frame = pd.DataFrame(rows)
            frame["device"], frame["commit"] = device_description(a.backend), commit()
            if a.out:                    # after every step size: a run stopped by a time limit keeps its rows
                save_frame(frame, a.out)
    print(frame.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
