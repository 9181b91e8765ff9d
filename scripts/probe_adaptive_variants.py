"""Probe: adaptive variants with any scene overrides, scored as the adaptive-pareto study scores its own
(the same uniform front, reference, seed means and verdict), before a variant joins the study.

    python scripts/probe_adaptive_variants.py --scene cumulus --backend cuda \\
        --variant heated-68m-tau120:heated:68:3:1:'{"adaptive.heating_time": 120}' [--variant ...] [--seeds 3]

Each --variant is NAME:CRITERION:LEVEL0_SPACING_M:MAX_LEVEL:THRESHOLD_SCALE[:OVERRIDES_JSON].  Prints the
configuration table and the verdict's speed-ups; --out DIR also writes the study's three files there with
the scene's suffix.  Spacings are the GPU scale's (--scale cpu|smoke multiplies them as the study does)."""
import argparse
import json
from pathlib import Path

import pandas as pd

from bench import runs
from bench.studies import adaptive_pareto as ap
from bench.studies.context import StudyContext
from bench.studies.scales import SCALES

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--scene", default="cumulus", choices=ap.SCENES)
parser.add_argument("--variant", action="append", default=[], help="NAME:CRITERION:SPACING:MAX_LEVEL:SCALE[:JSON]")
parser.add_argument("--seeds", type=int, default=3)
parser.add_argument("--scale", default="gpu", choices=("gpu", "cpu", "smoke"))
parser.add_argument("--backend", default="cuda", choices=("cpu", "cuda"))
parser.add_argument("--runs-root", type=Path, default=None)
parser.add_argument("--out", type=Path, default=None)
parser.add_argument("--commit", default="unknown")
args = parser.parse_args()

factor = ap.SPACING_FACTOR[args.scale]
custom = []
for text in args.variant:
    name, criterion, spacing, level, scale, *rest = text.split(":", 5)
    over = tuple(sorted(json.loads(rest[0]).items())) if rest else ()
    custom.append(ap.Config(name, "adaptive", float(spacing) * factor, criterion, int(level), float(scale), overrides=over))
configs = [c for c in ap.configs(args.scale) if c.kind != "adaptive"] + custom
ctx = StudyContext(out=args.out or Path("/tmp/probe_adaptive_variants"), scale=SCALES[args.scale],
                   runs_root=args.runs_root or runs.default_root(), backend=args.backend, quiet=False,
                   scheduler="inline")
entries = ap.plan(ctx, args.scene, args.seeds, configs)
results = ctx.run_parallel([e[2] for e in entries], f"probe {args.scene}")
device = next((r.device for r in results if getattr(r, "device", None)), "unknown")
per_run, per_config, verdict = ap.analyse(entries, results, args.scene, device, args.commit, None)
pd.set_option("display.width", 250)
cols = ["config", "stable_seeds", "particles", "ms_per_step", "pbf_ms", "e_cover", "e_volume", "e_lwp", "error",
        "error_seed_spread", "speedup_at_equal_error"]
print(per_config[cols].to_string(index=False, float_format=lambda x: f"{x:.4g}"))
print(json.dumps({k: verdict.get(k) for k in ("verdict", "noise_floor", "cost_ratio_per_particle", "device")}, default=str))
if args.out:
    suffix = "" if args.scene == "growing" else f"_{args.scene}"
    args.out.mkdir(parents=True, exist_ok=True)
    per_run.to_csv(args.out / f"probe_pareto{suffix}.csv", index=False)
    per_config.to_csv(args.out / f"probe_pareto_configs{suffix}.csv", index=False)
    (args.out / f"probe_verdict{suffix}.json").write_text(json.dumps(verdict, indent=1, default=str))
