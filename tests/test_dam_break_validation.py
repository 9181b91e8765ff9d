"""The dam break against a measured flow: the surge front of Martin & Moyce (1952).

A water column of width a and height 2a (n^2 = 2) collapses on a dry horizontal floor; the experiment
recorded the distance x of the surge front from the back wall against time. Non-dimensional as in the
paper: Z = x / a against T = t sqrt(2 g / a). The data (Figure 3 of the paper, the a = 2.25 in case, as
digitised in PySPH) are in tests/data/validation/martin_moyce_1952_surge.csv with their provenance.

The simulation is the scene `dam_break_martin_moyce`: the same column (a = 0.05715 m) in a 20a tank, a
quasi-2D slab with a periodic z axis, `per_width` particles across a. The front is the 99.5th percentile
of the particles' x (a few leading particles that leave the tongue do not move it), plus half a spacing:
a particle centre sits d/2 inside the water's edge (the initial column's particles end at a - d/2).

Run as a script for the table in docs/validation.md: `python tests/test_dam_break_validation.py 10 20 40`.
"""
from __future__ import annotations

import csv
import sys
import time
from pathlib import Path

import numpy as np

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pbf_cuda import Simulation, load_scene  # noqa: E402

DATA = Path(__file__).resolve().parent / "data" / "validation" / "martin_moyce_1952_surge.csv"
COLUMN_WIDTH = 0.05715            # a (m): the experiment's 2.25 in column
GRAVITY = 9.81                    # m/s^2
FRONT_PERCENTILE = 99.5
LAST_T = 9.3                      # the compared range ends at the last data point, T = 9.237

# Tolerances on the front's relative error (Z_sim - Z_exp) / Z_exp over 0.83 <= T <= 9.24.  Measured
# (docs/validation.md): rms 3.3% / max 8.0% at 10 particles per a, 5.6% / 10.4% at 20, 6.6% / 11.3% at
# 40 (the solver runs ahead of the experiment, more so as it converges). The experiment's own spread is
# of the same size: its two columns (a = 1.125 and 2.25 in) differ by up to 8% in Z at equal T. So the
# test asks for the experiment within 10% rms and 15% at any point; half gravity puts the front ~30%
# behind once it runs (fronts scale with sqrt(g)): 29.8% rms, 34.0% max, failing both.
RMS_TOLERANCE = 0.10
MAX_TOLERANCE = 0.15


def experiment(a_inch: float = 2.25) -> tuple[np.ndarray, np.ndarray]:
    """Martin & Moyce's front, n^2 = 2: T = t sqrt(2g/a) and Z = x/a (both dimensionless)."""
    with DATA.open() as f:
        rows = [r for r in csv.DictReader(line for line in f if not line.startswith("#"))]
    pick = [(float(r["T"]), float(r["Z"])) for r in rows if float(r["a_inch"]) == a_inch]
    T, Z = np.array(pick).T
    return T, Z


def column_scene(per_width: int = 10, gravity: float = GRAVITY):
    """The shipped scene at `per_width` particles per column width; the slab 6 spacings thick (3 kernel
    radii, the least a periodic axis allows) and dt = 0.8 d / sqrt(4 g a) (0.8 d per step at the
    free-fall speed from the column top)."""
    a = COLUMN_WIDTH
    base = load_scene("dam_break_martin_moyce")
    d = a / per_width
    size = [base.domain.size[0], base.domain.size[1], 6 * d]
    return base.replace(**{
        "particles.spacing": d, "domain.size": size, "particles.fill_max": [a, 2 * a, size[2]],
        "time.dt": 0.8 * d / np.sqrt(4 * GRAVITY * a), "pbf.gravity": [0.0, -gravity, 0.0]})


def front_position(x: np.ndarray, spacing: float) -> float:
    """Surge front (m): the 99.5th percentile of particle x, moved d/2 out to the water's edge."""
    return float(np.percentile(x, FRONT_PERCENTILE)) + 0.5 * spacing


def simulate_front(scene, last_T: float = LAST_T) -> tuple[np.ndarray, np.ndarray, int]:
    """Run `scene` until T = last_T; return T = t sqrt(2 g / a) and Z = front / a at the start and after
    every step, and the particle count.
    T uses g = 9.81 whatever the scene's gravity (a wrong gravity must show as a wrong front)."""
    a = COLUMN_WIDTH
    to_T = np.sqrt(2.0 * GRAVITY / a)
    sim = Simulation(scene, backend="cpu", seed=0)
    d = scene.particles.spacing
    T, Z = [0.0], [front_position(sim.state()["position"][:, 0], d) / a]
    while T[-1] < last_T:
        sim.step(1)
        T.append(sim.time * to_T)
        Z.append(front_position(sim.state()["position"][:, 0], d) / a)
    return np.array(T), np.array(Z), sim.n_particles


def relative_errors(T: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Z_sim - Z_exp) / Z_exp at the experiment's times (the simulated front interpolated linearly)."""
    T_exp, Z_exp = experiment()
    return T_exp, (np.interp(T_exp, T, Z) - Z_exp) / Z_exp


def front_error(per_width: int = 10, gravity: float = GRAVITY) -> dict:
    """rms and max relative error of the front over the experiment's range, with the run's size and time."""
    scene = column_scene(per_width, gravity)
    start = time.perf_counter()
    T, Z, particles = simulate_front(scene)
    seconds = time.perf_counter() - start
    T_exp, rel = relative_errors(T, Z)
    return {"per_width": per_width, "particles": particles, "steps": len(T) - 1,
            "seconds": seconds, "rms": float(np.sqrt(np.mean(rel ** 2))), "max": float(np.abs(rel).max()),
            "T": T_exp, "relative": rel, "tank_end": scene.domain.size[0] / COLUMN_WIDTH, "last_Z": float(Z[-1])}


def test_surge_front_follows_martin_and_moyce():
    """At 10 particles per column width (1200 particles, ~170 steps, a few seconds on one core) the
    front stays within 10% rms and 15% at every point of Martin & Moyce's a = 2.25 in, n^2 = 2 front
    over 0.83 <= T <= 9.24, and never reaches the far wall. Checked to fail for wrong physics: with
    gravity 0.5x (next test) the errors are 29.8% rms and 34.0% max."""
    result = front_error(10)
    assert result["last_Z"] < result["tank_end"] - 2.0          # the far wall plays no part
    assert result["rms"] < RMS_TOLERANCE, result
    assert result["max"] < MAX_TOLERANCE, result


def test_half_gravity_front_falls_outside_the_tolerance():
    """The tolerance discriminates: at half gravity the front lags by ~1 - 1/sqrt(2) = 29% once it runs
    (T >= 2; before, the column has barely moved in either run)."""
    result = front_error(10, gravity=0.5 * GRAVITY)
    running = result["T"] >= 2.0
    assert np.all(result["relative"][running] < -0.2), result
    assert result["rms"] > 2 * RMS_TOLERANCE and result["max"] > MAX_TOLERANCE


if __name__ == "__main__":
    print("| particles per a | particles | steps | run time (s) | rms relative error | max relative error |")
    print("|---|---|---|---|---|---|")
    for k in [int(arg) for arg in sys.argv[1:]] or [10, 20]:
        r = front_error(k)
        print(f"| {k} | {r['particles']} | {r['steps']} | {r['seconds']:.1f} | {100 * r['rms']:.1f}% "
              f"| {100 * r['max']:.1f}% |", flush=True)
        print("<!-- T: " + " ".join(f"{t:.2f}" for t in r["T"]) + " -->")
        print("<!-- rel: " + " ".join(f"{100 * e:+.1f}" for e in r["relative"]) + " -->", flush=True)
