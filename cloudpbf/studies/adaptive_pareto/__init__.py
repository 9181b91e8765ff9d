"""Adaptive against uniform particles: run time against error, seed means against an independent reference.

For one cloud scene (``growing``; ``cumulus``: one heated patch in a wide domain; ``shallow_cumulus``: separate
cumulus under an inversion), each with its adaptive twin ``<scene>_adaptive``, the study runs

* uniform (non-adaptive) runs at four spacings, e.g. 68, 54, 43 and 34 m at the GPU scale,
* every adaptive variant (refinement criterion ``paper`` = eq. 20 on the cloud water, ``lookahead`` = eq. 20
  on the water a particle would hold after rising ``lookahead_height``, ``thermal`` = eq. 20 on the heat
  excess over the environment as cloud water) at two level-0 spacings (68 and 54 m) with max level 3, and
  the :data:`FURTHER_VARIANTS` of ``thermal``: one level deeper from 68 m (``thermal-68m-L4``, finest 27 m),
  eq. 20's split/merge thresholds times 0.25 (``-t0.25``), splitting and merging every 4 (8, 16) steps instead of
  the adaptive scenes' 2 (``-e4``, ``-e8``, ``-e16``), and the kernel at the pair's mean radius instead of eq. 19
  (``-km``),
* a reference: uniform runs at 27 m (1.69M particles at the GPU scale), never one of the compared runs,

each over ``seeds`` noise seeds (>= 3), all deposited on one 32^3 analysis grid.  Every compared configuration
is reduced to its *seed mean* time series, and the reference to the mean of its seeds, so that neither is one
realisation of a chaotic flow.  Errors of a configuration (relative L2 norms over the snapshot times)::

    e_cover, e_volume, e_lwp      cloud cover, cloudy volume, mean liquid water path
    e_base, e_top                 cloud base and top heights (times where both have cloud)
    e_profile                     the final cloud-fraction profile a_c(z)
    error = (e_cover + e_volume + e_lwp) / 3

``error_seed_spread`` is the standard deviation over seeds of the same error computed per seed (NaN with fewer
than two stable seeds): below it two configurations cannot be told apart; ``noise_floor`` (in the verdict) is
the mean error of a single reference seed against the reference mean.  Time is ms per step of the step loop
(``step_wall_s / steps``) of the same runs; ``pbf_ms_per_particle`` the PBF phase per step divided by the mean
particle count.

Stable seeds.  A run that blows up has no time and no error, so a configuration's seed mean is a mean over the
seeds that survived.  The verdict uses only configurations stable in at least ``min_stable_seeds`` seeds
(default :data:`MIN_STABLE_SEEDS` = None: every seed the study ran), for the uniform front as for the adaptive
variants, and only those with a finite error and time.  Why all seeds by default: a variant that blows up in
one seed of three is not a usable setting whatever its survivors cost, and the survivors are not a fair sample
(a blow-up picks its seeds by their flow, not at random), so a mean over them leans toward the calmer
realisations and its seed spread is understated (one seed has none).  ``--min-stable-seeds 2`` relaxes the rule
for a reader who wants to see what the survivors would say.  Configurations that fail it are listed in the
verdict's ``excluded`` with their stable/total seed counts and the reasons; ``best`` carries the stable seeds it
rests on.  When no adaptive variant qualifies, ``best`` is null and the verdict says so.

How sure the speed-up is.  A variant's speed-up rests on its own seeds, the uniform runs' and the reference's,
all finite samples of a chaotic flow.  The study resamples the seeds (a bootstrap: draw the seed numbers with
replacement, the same draw for every configuration, and redo the whole analysis, :data:`BOOTSTRAP_REPLICATES`
times) and reports each variant's 5-95% interval of the speed-up, the share of resamples where it reaches
:data:`GOAL_SPEEDUP` and the share where it is the best variant.

Outputs (OUT/data): ``adaptive_pareto.csv`` (one row per run, with the configuration's errors repeated on
each of its seeds' rows), ``adaptive_pareto_configs.csv`` (one row per configuration),
``adaptive_pareto_series.csv`` (every run's time series and final profile, long format: what ``--from-data``
needs to redo the errors and the resampling) and ``adaptive_verdict.json``::

    {"scene": ..., "cost_ratio_per_particle": x,       # PBF ms per adaptive particle / per uniform particle
     "min_stable_seeds": n,                             # the rule the verdict applied
     "variants": [{"name", "spacing_m", "criterion", "max_level", "threshold_scale", "adapt_every", "pair_kernel",
                   "speedup_at_equal_error",
                   "error", "ms_per_step",
                   "particles", "cost_ratio_per_particle", "stable_seeds", "seeds",
                   "speedup_interval": [p5, p95], "p_speedup_at_least_goal", "best_share",
                   "uniform_ms_at_equal_particles", "speedup_from_particles", "step_cost_ratio"}],  # qualifying ones
     "excluded": [{"name", "kind", "stable_seeds", "seeds", "reasons", ...}],
     "best": {... one of variants ...} or null, "verdict": "...", "noise_floor": f,
     "resampling": {"replicates", "seeds", "goal_speedup", "no_best_share"} or null, "device": ..., "commit": ...}

where a variant's speed-up is the uniform front's ms/step, interpolated (log-log) at the variant's error,
divided by the variant's own (and split, :func:`speedup_factors`, into what its particle placement buys and what
its step costs beyond a uniform step of its particle count); a variant more accurate than every uniform run, or less than all of them, has
no speed-up (null) and the verdict says so.  The cost ratio is the median over the qualifying variants.

``--from-data`` rebuilds ``adaptive_verdict[_SCENE].json`` from ``adaptive_pareto[_SCENE].csv``,
``adaptive_pareto_configs[_SCENE].csv`` and (where it is there) ``adaptive_pareto_series[_SCENE].csv`` in OUT/data
without running anything (device and commit are kept from
the verdict file already there, else taken from the runs' CSV: they belong to the runs, not to the rebuild).

    cloudpbf adaptive-pareto [--scene growing|cumulus|shallow_cumulus] [--seeds 3] [--min-stable-seeds N] [--resamples 1000]
                             [--scale gpu]
    cloudpbf adaptive-pareto --scene growing --from-data --out reports/gpu

The study is this package: design.py (the configurations and their runs), analysis.py (errors, speed-ups and the
verdict), report.py (its report section and verdict card); here the run, the renders and the command.
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import click
import numpy as np
import pandas as pd
import typer

from cloudpbf import runs
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
# the package's names: its design (design.py) and analysis (analysis.py)
from cloudpbf.render import compact_particles, render_or_note, render_particles
from cloudpbf.store.result import RunResult
from cloudpbf.studies.adaptive_pareto.analysis import (add_verdict_columns, aligned_signatures, analyse,
                                                    bootstrap_speedups, build_verdict, errors, mean_of_rows,
                                                    mean_signature, pbf_cost_at_count, rebuild_verdict,
                                                    required_stable_seeds, seed_groups, series_frame, signature,
                                                    signatures_from_series, speedup_factors, speedup_interval,
                                                    time_at_error, uniform_front, uniform_time_at_count)  # noqa: F401
from cloudpbf.studies.adaptive_pareto.design import (ADAPTIVE_SPACINGS, ANALYSIS_GRID, BOOTSTRAP_REPLICATES, CRITERIA,
                                                  DEFAULT_MAX_LEVEL, FURTHER_VARIANTS, GOAL_SPEEDUP,
                                                  MIN_STABLE_SEEDS, REFERENCE_SPACING, SCENES, SERIES,
                                                  SPACING_FACTOR, UNIFORM_SPACINGS, Config, configs, finest_spacing,
                                                  plan, scene_for, variant_name)  # noqa: F401
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.plans import scene_file_suffix
from cloudpbf.studies.adaptive_pareto.report import _adaptive_pareto, adaptive_front_card
from cloudpbf.studies.registry import GlanceCard, ReportSection, Study, register
from pbf_cuda.scene import load_scene


def run_adaptive_pareto(ctx: StudyContext, scene_name: str = "growing", seeds: int = 3,
                        min_stable_seeds: int | None = MIN_STABLE_SEEDS,
                        replicates: int = BOOTSTRAP_REPLICATES) -> dict:
    """Run (or read) the study for one scene; write adaptive_pareto[_SCENE].csv and the verdict json."""
    if scene_name not in SCENES:
        raise ValueError(f"scene = {scene_name!r}: allowed {', '.join(SCENES)}")
    if not 3 <= int(seeds) <= 100:
        raise ValueError(f"seeds = {seeds}: allowed 3..100 (seed means need at least three)")
    if min_stable_seeds is not None and not 1 <= int(min_stable_seeds) <= int(seeds):
        raise ValueError(f"min_stable_seeds = {min_stable_seeds}: allowed 1..{seeds} (the seeds run)")
    entries = plan(ctx, scene_name, int(seeds))
    results = ctx.run_parallel([e[2] for e in entries], f"adaptive-pareto {scene_name}")
    device = next((r.device for r in results if getattr(r, "device", None)), "unknown")
    sigs = [signature(r) for r in results]      # each run's CSVs read once, for the analysis and the series file
    per_run, per_config, verdict = analyse(entries, results, scene_name, device, ctx.commit, min_stable_seeds,
                                           replicates, sigs)
    suffix = scene_file_suffix(scene_name)
    series = series_frame([(config.name, seed) for config, seed, _ in entries], sigs)
    runs.write_csv(series, ctx.data / f"adaptive_pareto_series{suffix}.csv")
    runs.write_csv(per_run, ctx.data / f"adaptive_pareto{suffix}.csv")
    runs.write_csv(per_config, ctx.data / f"adaptive_pareto_configs{suffix}.csv")
    runs.atomic_write_json(ctx.data / f"adaptive_verdict{suffix}.json", verdict)
    return {"runs": per_run, "configs": per_config, "verdict": verdict}


# ---- renders: the best variant beside the uniform runs at its level-0 and finest spacings ---------------
def render_configs(per_config: pd.DataFrame, verdict: dict) -> list[str]:
    """The configurations drawn side by side: the best adaptive variant (or, without a scored one, the one of
    lowest error among those the verdict kept, else among all), the uniform run at its level-0 spacing, and the
    uniform run nearest its finest spacing."""
    adaptive = per_config[per_config.kind == "adaptive"].dropna(subset=["error"])
    uniform = per_config[per_config.kind == "uniform"]
    if adaptive.empty or uniform.empty:
        return []
    qualified = adaptive[adaptive["config"].isin([v["name"] for v in verdict.get("variants") or []])]
    best = ((verdict.get("best") or {}).get("name")
            or (qualified if len(qualified) else adaptive).sort_values("error")["config"].iloc[0])
    row = per_config.loc[per_config.config == best].iloc[0]
    spacing = float(row["spacing_m"])
    finest = finest_spacing(spacing, float(row.get("max_level", DEFAULT_MAX_LEVEL)))
    names = [best]
    for target in (spacing, finest):          # level 0, and the finest level
        nearest = uniform.iloc[int(np.argmin(np.abs(np.log(uniform["spacing_m"].to_numpy(float) / target))))]
        if nearest["config"] not in names:
            names.append(str(nearest["config"]))
    return names


def pareto_states(per_run: pd.DataFrame, per_config: pd.DataFrame, verdict: dict, out_dir, seed: int = 0) -> list:
    """Compact final states (every cloudy particle, a tenth of the clear ones; position, cloud, level) of seed
    `seed`'s run of each of :func:`render_configs`, for renders where pyvista is: OUT/pareto_<config>.npz."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    kinds = dict(zip(per_config["config"], per_config["kind"]))
    written = []
    for name in render_configs(per_config, verdict):
        rows = per_run[(per_run["config"] == name) & (per_run["seed"] == seed)]
        if rows.empty:
            continue
        try:
            snaps = RunResult.load(rows["run_dir"].iloc[0]).snapshot_paths()
        except FileNotFoundError:     # the run was made on another machine
            continue
        if not snaps:
            continue
        with np.load(snaps[-1]) as z:
            state = {k: z[k] for k in z.files}
        compact = compact_particles(state)
        compact.update(time_s=state["time_s"], step=state["step"], config=np.array(name),
                       kind=np.array(kinds[name]), particles=np.array(len(state["cloud"])))
        target = out_dir / f"pareto_{name}.npz"
        np.savez_compressed(target, **compact)
        written.append(target)
    return written


def render_pareto_states(states_dir, out_dir, scene_name: str) -> list:
    """Render the compact states of :func:`pareto_states` as cloud points, one PNG per configuration
    (OUT/pareto_<scene>_<config>.png); none where pyvista cannot render (a note is left instead)."""
    written = []
    for path in sorted(Path(states_dir).glob("pareto_*.npz")):
        with np.load(path) as z:
            state = {k: z[k] for k in z.files}
        name, kind = str(state.pop("config")), str(state.pop("kind"))
        scene = load_scene(f"{scene_name}_adaptive" if kind == "adaptive" else scene_name)
        title = f"{scene_name}, {name} ({int(state.pop('particles')):,} particles), t = {float(state['time_s']):.0f} s"
        done = render_or_note(render_particles, Path(out_dir) / f"pareto_{scene_name}_{name}.png", state, scene,
                              title=title)
        if done is not None:
            written.append(done)
    return written


def adaptive_pareto_command(
    scene: Annotated[str, typer.Option(help="growing (the paper's example 1), cumulus (one heated patch) or "
                                            "shallow_cumulus (separate cumulus under an inversion)")] = "growing",
    seeds: Annotated[int, typer.Option(min=3, max=100, help="noise seeds per configuration (>= 3)")] = 3,
    min_stable_seeds: Annotated[Optional[int], typer.Option(
        "--min-stable-seeds", min=1, max=100,
        help="stable seeds a configuration needs to enter the verdict (uniform front and best variant); "
             "default: every seed run")] = None,
    resamples: Annotated[int, typer.Option(
        min=0, max=100000, help="resamples of the seeds behind each variant's speed-up interval (0: none)")
    ] = BOOTSTRAP_REPLICATES,
    from_data: Annotated[bool, typer.Option(
        "--from-data", help="run nothing: rebuild OUT/data/adaptive_verdict[_SCENE].json from the study's CSVs "
                            "there (device and commit stay those of the runs)")] = False,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
) -> None:
    """Adaptive variants against uniform runs at four spacings: seed-mean errors against a finer reference."""
    if scene not in SCENES:
        raise click.UsageError(f"--scene {scene!r}: allowed {', '.join(SCENES)}")
    if from_data:
        try:
            verdict = rebuild_verdict(Path(out) / "data", scene, min_stable_seeds, replicates=resamples)
        except (FileNotFoundError, ValueError) as exc:
            raise click.UsageError(str(exc)) from None
        _echo_verdict(verdict)
        return
    if min_stable_seeds is not None and min_stable_seeds > seeds:
        raise typer.BadParameter(f"{min_stable_seeds}: more than --seeds {seeds}", param_hint="'--min-stable-seeds'")
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        with refusals():
            result = run_adaptive_pareto(ctx, scene, seeds, min_stable_seeds, resamples)
    cols = ["config", "stable_seeds", "seeds", "particles", "ms_per_step", "error", "error_seed_spread", "e_base",
            "e_top", "e_profile", "speedup_at_equal_error", "speedup_p05", "speedup_p95"]
    typer.echo(result["configs"][cols].to_string(index=False))
    _echo_verdict(result["verdict"])


def _echo_verdict(verdict: dict) -> None:
    """The verdict, the variants it left out and why, and the cost ratio, as the command prints them."""
    typer.echo(verdict["verdict"])
    if verdict.get("best") is None:
        typer.echo("best variant: none")
    for e in verdict.get("excluded", []):
        typer.echo(f"  left out: {e['name']} ({e['stable_seeds']}/{e['seeds']} seeds stable): "
                   + "; ".join(e["reasons"]))
    typer.echo(f"PBF cost per adaptive particle / per uniform particle: {verdict['cost_ratio_per_particle']}")


register(Study("adaptive-pareto", order=45, sections=("adaptive_pareto",),
               report=(ReportSection("adaptive_pareto", "Adaptive mode at equal error", _adaptive_pareto, 70,
                                     "Adaptive front"),),
               glance=(GlanceCard(adaptive_front_card, 20, slot="adaptive_front"),),
               produces={"adaptive_pareto": "cloudpbf adaptive-pareto --scene growing --out {out}"},
               outputs=("adaptive_pareto.csv", "adaptive_pareto_configs.csv", "adaptive_pareto_series.csv",
                        "adaptive_verdict.json"),
               command=adaptive_pareto_command))
