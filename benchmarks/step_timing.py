"""Step time of a few scenes with whichever pbf_cuda is first on sys.path, one JSON line per case; with
--table FILE, a table of several builds' lines (the fastest of each build's repeats) with their ratios to the
first build: the before/after measurement of a solver change on one machine, in one run
(benchmarks/compare_builds.sh; docs/benchmarks.md, "Before and after on one machine").

    python benchmarks/step_timing.py TAG [--backend cuda] [--lists 0|1] >> timing.jsonl
    python benchmarks/step_timing.py --table timing.jsonl

Cases: the stratified gravity wave (4,800 particles), the dam break (12k and 96k), `growing` at 68, 54 and 34 m
(104k, 205k, 831k particles), the 831k-particle run once more after 200 steps (convection under way, where the
density iterations move particles most) and the two adaptive scenes at their level-0 lattice (104k); 5 warm-up
steps (200 for the convective case), then the mean wall time per step of 30-40 steps (ms) and the solver's
per-phase means.
"""
import argparse
import collections
import json
import time


def cases():
    from pbf_cuda import load_scene
    return [("stratified", load_scene("stratified"), 5, 40),
            ("dam_break", load_scene("dam_break"), 5, 40),
            ("dam_break-96k", load_scene("dam_break", **{"particles.spacing": 0.01}), 5, 40),
            ("growing-68m", load_scene("growing", **{"particles.spacing": 68.0}), 5, 40),
            ("growing-54m", load_scene("growing", **{"particles.spacing": 54.0}), 5, 40),
            ("growing-34m", load_scene("growing"), 5, 30),
            ("growing-34m-convective", load_scene("growing"), 200, 30),
            ("growing_adaptive-68m", load_scene("growing_adaptive"), 5, 40),
            ("cumulus_adaptive-68m", load_scene("cumulus_adaptive"), 5, 40)]


def measure(tag, backend, lists):
    from pbf_cuda import Simulation
    for name, scene, warmup, steps in cases():
        if lists is not None:
            scene = scene.replace(**{"pbf.neighbor_list": bool(lists)})
        sim = Simulation(scene, backend=backend, seed=0)
        sim.step(warmup)
        sim.reset_timings()
        t = time.perf_counter()
        sim.step(steps)
        wall = (time.perf_counter() - t) / steps * 1e3
        row = {"tag": tag, "case": name, "particles": int(sim.stats()["n_particles"]), "wall_ms": wall,
               **{k + "_ms": v["mean_ms"] for k, v in sim.timings().items()}}
        print(json.dumps(row), flush=True)


def table(path):
    rows = [json.loads(line) for line in open(path) if line.startswith("{")]
    best = {}
    for r in rows:
        key = (r["case"], r["tag"])
        if key not in best or r["wall_ms"] < best[key]["wall_ms"]:
            best[key] = r
    tags = list(dict.fromkeys(r["tag"] for r in rows))
    print("case".ljust(22), "particles".rjust(9), *[t.rjust(12) for t in tags], "  ms per step; x: first / last")
    for case in dict.fromkeys(r["case"] for r in rows):
        b = [best.get((case, t)) for t in tags]
        if any(x is None for x in b):
            continue
        print(case.ljust(22), str(b[-1]["particles"]).rjust(9), *[f"{x['wall_ms']:12.2f}" for x in b],
              f"  x{b[0]['wall_ms'] / b[-1]['wall_ms']:.2f}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tag", nargs="?")
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--lists", type=int, choices=(0, 1), default=None, help="force pbf.neighbor_list")
    ap.add_argument("--table", help="print the table of a JSON-lines file instead of measuring")
    a = ap.parse_args()
    if a.table:
        table(a.table)
    else:
        measure(a.tag or "build", a.backend, a.lists)
