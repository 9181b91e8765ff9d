"""Fingerprints of the particle solver: sha256 of every state array and of stats() after a few short
fixed-seed runs, for checking that a refactoring leaves the results bit-identical.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/fingerprint.py [--backend cpu|cuda] [CASE ...]

Run it before and after a change on the same backend (and thread count) and compare the output: every
line must be equal. The cases cover a uniform heated, condensing atmosphere with smoothing of every
field, viscosity, vorticity and the cycling forcing (velocity projection); two adaptive ones with splits
and merges (the paper's and the look-ahead criterion, s_corr at mixed levels); a dam break (position
projection, walls, gravity); and the stratified gravity wave.
"""
import argparse
import hashlib
import json
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")   # before the solver's OpenMP runtime starts

import numpy as np  # noqa: E402

from pbf_cuda import Simulation, load_scene  # noqa: E402


def growing_uniform():
    # heating + condensation + smoothing + vorticity + viscosity + cycling forcing, velocity projection
    return load_scene("growing", **{
        "domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 2.0,
        "atmosphere.initial_vapor_ratio": 1.02, "atmosphere.heating_rate": 0.3,
        "atmosphere.relaxation_time": 600.0, "atmosphere.autoconversion_rate": 1e-3,
        "atmosphere.autoconversion_threshold": 1e-4, "atmosphere.diurnal_period": 400.0,
        "pbf.viscosity": 5.0, "smoothing.fields": ["temperature", "vapor", "cloud"]}), 40

def growing_adaptive():
    return load_scene("growing_adaptive", **{
        "domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 2.0,
        "atmosphere.initial_vapor_ratio": 1.03, "adaptive.capacity": 4.0, "atmosphere.heating_rate": 0.2}), 40

def adaptive_lookahead():
    # tensile term, vorticity, viscosity and every smoothed field at mixed levels, lookahead criterion
    return load_scene("growing_adaptive", **{
        "domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0, "time.dt": 2.0,
        "atmosphere.initial_vapor_ratio": 0.97, "adaptive.capacity": 4.0, "atmosphere.heating_rate": 0.3,
        "adaptive.criterion": "lookahead", "adaptive.lookahead_height": 400.0, "pbf.scorr_k": 0.1,
        "pbf.viscosity": 5.0, "pbf.divergence_tolerance": 1e-4,
        "smoothing.fields": ["temperature", "vapor", "cloud"]}), 40

def dam_break():
    return load_scene("dam_break", **{"particles.spacing": 0.04, "pbf.vorticity": 0.01, "pbf.scorr_k": 0.05}), 30

def stratified():
    return load_scene("stratified", **{"pbf.divergence_tolerance": 1e-3}), 25

CASES = [growing_uniform, growing_adaptive, adaptive_lookahead, dam_break, stratified]

def digest(a):
    a = np.ascontiguousarray(a)
    return hashlib.sha256(a.dtype.str.encode() + str(a.shape).encode() + a.tobytes()).hexdigest()[:16]

def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("cases", nargs="*", help=f"run only these ({', '.join(c.__name__ for c in CASES)})")
    args = parser.parse_args()
    total = hashlib.sha256()
    for case in CASES:
        if args.cases and case.__name__ not in args.cases:
            continue
        scene, steps = case()
        sim = Simulation(scene, backend=args.backend, seed=1)
        sim.step(steps)
        st = sim.state()
        if scene.pbf.projection == "velocity":
            st["projection_impulse"] = sim._solver.get_float("projection_impulse")
        st["density"] = sim._solver.get_float("density")
        stats = dict(sim.stats())
        h = {k: digest(v) for k, v in sorted(st.items())}
        h["stats"] = hashlib.sha256(json.dumps(stats, sort_keys=True).encode()).hexdigest()[:16]
        line = hashlib.sha256(json.dumps(h, sort_keys=True).encode()).hexdigest()[:16]
        total.update(line.encode())
        print(f"{case.__name__:20s} n={sim.n_particles:6d} splits={stats['splits']:5d} merges={stats['merges']:5d} "
              f"cloud={float(st.get('cloud', np.zeros(1)).max()):.3e} case={line}")
        for k, v in h.items():
            print(f"    {k:20s} {v}")
    print("ALL", total.hexdigest()[:16])

if __name__ == "__main__":
    main()
