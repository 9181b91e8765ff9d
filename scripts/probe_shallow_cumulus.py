"""Probe: can scene overrides alone put `growing` into a shallow-cumulus regime (separate cumulus, clear sky
between them, cover 0.1-0.4) instead of its overcast box (cover 0.99 at 1000 s)?

    python scripts/probe_shallow_cumulus.py [--candidates baseline,L4,...] [--seeds 0] [--particles 20000]
    python scripts/probe_shallow_cumulus.py --candidates baseline,L3_rh90 --confirm L3_rh90 --confirm-seeds 1,2
    python scripts/probe_shallow_cumulus.py --list
    python scripts/probe_shallow_cumulus.py --backend cuda --particles 0 --candidates L3_rh85_a3 \
        --extra '{"capped": {"atmosphere.inversion_height": 1600.0, ...}}'     # the paper's scale on a GPU

The 14 candidates behind the shipped `shallow_cumulus` scene, and their covers at the paper's scale, are in
docs/validation.md ("Shallow cumulus").

Runs `growing` (--base: another scene; or a candidate's overrides of it) scaled with
bench.studies.scales.scale_scene to --particles (default 20k: 118 m spacing; 50k: 87 m, the CPU scale; 0: the
scene's own spacing) in the full 3.2 km domain (heating layer thickened with the heat flux kept), particle solver
on --backend (default the CPU), seed 0 (--seeds; --confirm reruns candidates with --confirm-seeds),
500 steps of 2 s, diagnostics every `--every` steps on the default deposit grid (one cell per particle
spacing).  For each run it prints one CSV row: cover at the end, its max, its time mean over the cloudy period
(cover > 1%) and the fraction of the cloudy snapshots with cover in [0.1, 0.4]; cloudy-period means of cloud base,
top and mean LWP (bench.studies.sweep.cloud_means); at the end: cloud base/top, 3D cloud objects (stats
n_objects, face-connected cloudy cells, periodic), 2D objects of cloudy columns (periodic x, z) and how many of
them span >= 4 columns, the maximum of the cloud-fraction profile and its height.  Runs are cached in
--runs-root (default /tmp/shallow/runs), so a second call prints at once.  Writes --out/results.csv and
--out/series.csv (cover, base, top, LWP and n_objects of every diagnostic row of every run).
"""
import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from bench import runs
from bench.statistics import CLOUDY_COVER, cloud_objects, cloudy_mask, deposit_state
from bench.studies.context import StudyContext
from bench.studies.scales import SCALES, scale_scene
from bench.studies.sweep import cloud_means
from pbf_cuda import load_scene

# Overrides of growing (before scaling to the CPU particle count: heating_rate / heating_depth are then
# rescaled by scale_scene with the flux S_e * depth kept).
CANDIDATES = {
    "baseline": {},
    "L4": {"atmosphere.lapse_rate": 0.004},
    "L3": {"atmosphere.lapse_rate": 0.003},
    "L4_rh90": {"atmosphere.lapse_rate": 0.004, "atmosphere.initial_vapor_ratio": 0.9},
    "L3_rh90": {"atmosphere.lapse_rate": 0.003, "atmosphere.initial_vapor_ratio": 0.9},
    "L35_rh85": {"atmosphere.lapse_rate": 0.0035, "atmosphere.initial_vapor_ratio": 0.85},
    "L3_rh90_f2": {"atmosphere.lapse_rate": 0.003, "atmosphere.initial_vapor_ratio": 0.9,
                   "atmosphere.noise_frequency": 0.0025},
    "L3_rh90_tau600": {"atmosphere.lapse_rate": 0.003, "atmosphere.initial_vapor_ratio": 0.9,
                       "atmosphere.relaxation_time": 600.0},
    "L3_rh90_a3": {"atmosphere.lapse_rate": 0.003, "atmosphere.initial_vapor_ratio": 0.9,
                   "atmosphere.noise_amplitude": 3.0},
    "L3_rh90_a3_tau1500": {"atmosphere.lapse_rate": 0.003, "atmosphere.initial_vapor_ratio": 0.9,
                           "atmosphere.noise_amplitude": 3.0, "atmosphere.relaxation_time": 1500.0},
    "L25_rh90_a3": {"atmosphere.lapse_rate": 0.0025, "atmosphere.initial_vapor_ratio": 0.9,
                    "atmosphere.noise_amplitude": 3.0},
    "L3_rh85_a3": {"atmosphere.lapse_rate": 0.003, "atmosphere.initial_vapor_ratio": 0.85,
                   "atmosphere.noise_amplitude": 3.0},
}


def parse_overrides(text):
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        sys.exit(f"--extra: not JSON ({exc})")


def column_objects(state, scene, min_columns=4):
    """(objects, objects of >= min_columns columns) of the cloudy columns of a snapshot, periodic in x and z."""
    grid = deposit_state(state, scene)
    columns = cloudy_mask(grid["cloud"]).any(axis=1)           # (nx, nz)
    _, sizes = cloud_objects(columns[:, None, :], (True, False, True))
    return int(sizes.size), int((sizes >= min_columns).sum())


def summarize(name, seed, scene, result):
    row = {"candidate": name, "seed": seed, "stable": bool(result.stable),
           "wall_s": round(float(result.info.get("wall_s") or math.nan), 1)}
    stats = result.stats()
    if not result.stable or not len(stats):
        return row, pd.DataFrame()
    stats = stats.sort_values("step")
    cover = stats["cloud_cover"].to_numpy()
    cloudy = cover > CLOUDY_COVER
    end = stats.iloc[-1]
    row.update(cover_end=float(end["cloud_cover"]), cover_max=float(cover.max()),
               onset_s=float(stats["time_s"][cloudy].iloc[0]) if cloudy.any() else math.nan,
               in_target=float(((cover >= 0.1) & (cover <= 0.4))[cloudy].mean()) if cloudy.any() else 0.0)
    row.update(cloud_means(result))
    row.update(base_end=float(end["cloud_base"]), top_end=float(end["cloud_top"]),
               base_p10_end=float(end["base_p10"]), top_p90_end=float(end["top_p90"]),
               lwp_end=float(end["lwp_mean"]), n_objects3d_end=int(end["n_objects"]))
    state = result.snapshot()
    row["n_colobj_end"], row["n_colobj4_end"] = column_objects(state, scene)
    prof = result.profiles()
    if len(prof):
        last = prof[prof["step"] == prof["step"].max()]
        i = int(np.argmax(last["cloud_fraction"].to_numpy()))
        row["cf_max_end"] = float(last["cloud_fraction"].iloc[i])
        row["z_cf_max_end"] = float(last["z"].iloc[i])
    series = stats[["step", "time_s", "cloud_cover", "cloud_base", "cloud_top", "lwp_mean", "n_objects"]].copy()
    series.insert(0, "seed", seed)
    series.insert(0, "candidate", name)
    return row, series


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--candidates", default=",".join(CANDIDATES), help="names from CANDIDATES, comma separated")
    parser.add_argument("--extra", default="{}", help='more candidates as JSON {"name": {overrides}}')
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--confirm", default="", help="candidates also run with --confirm-seeds (comma separated)")
    parser.add_argument("--confirm-seeds", default="1,2")
    parser.add_argument("--particles", type=int, default=20_000, help="0: the scene's own spacing (paper scale)")
    parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--base", default="growing", help="the scene the candidates override")
    parser.add_argument("--every", type=int, default=25, help="steps between diagnostic rows")
    parser.add_argument("--runs-root", type=Path, default=Path("/tmp/shallow/runs"))
    parser.add_argument("--out", type=Path, default=Path("/tmp/shallow"))
    parser.add_argument("--list", action="store_true")
    args = parser.parse_args()
    table = {**CANDIDATES, **parse_overrides(args.extra)}
    if args.list:
        for k, v in table.items():
            print(k, v)
        return
    names = [n.strip() for n in args.candidates.split(",") if n.strip()]
    names += [n for n in parse_overrides(args.extra) if n not in names]
    unknown = [n for n in names if n not in table]
    if unknown:
        sys.exit(f"unknown candidates {unknown}; known: {', '.join(table)}")
    seeds = [int(s) for s in args.seeds.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    ctx = StudyContext(out=args.out / "study", scale=SCALES["cpu"], runs_root=args.runs_root, backend=args.backend,
                       quiet=False, scheduler="inline")
    confirm = [n.strip() for n in args.confirm.split(",") if n.strip()]
    unknown = [n for n in confirm if n not in table]
    if unknown:
        sys.exit(f"unknown --confirm candidates {unknown}")
    plan = [(n, seeds) for n in names] + [(n, [int(s) for s in args.confirm_seeds.split(",")]) for n in confirm]
    rows, series = [], []
    for name, run_seeds in plan:
        scene = scale_scene(load_scene(args.base, **table[name]), args.particles or None)
        for seed in run_seeds:
            spec = runs.RunSpec("particles", scene, backend=args.backend, seed=seed, keep_snapshots=1,
                                snapshot_every=args.every)
            t0 = time.perf_counter()
            (result,) = ctx.run_parallel([spec], f"{name} seed {seed}")
            print(f"# {name} seed {seed}: {time.perf_counter() - t0:.0f} s here (cached={result.cached}), "
                  f"{result.info.get('particles', '')} {result.path}", file=sys.stderr, flush=True)
            row, ser = summarize(name, seed, scene, result)
            row["particles"] = scene.estimated_particles()
            row["spacing_m"] = round(scene.particles.spacing, 1)
            row["overrides"] = json.dumps(table[name], sort_keys=True)
            rows.append(row)
            if len(ser):
                series.append(ser)
    frame = pd.DataFrame(rows)
    frame.to_csv(args.out / "results.csv", index=False, float_format="%.4g")
    if series:
        pd.concat(series).to_csv(args.out / "series.csv", index=False, float_format="%.4g")
    frame.to_csv(sys.stdout, index=False, float_format="%.4g")


if __name__ == "__main__":
    main()
