"""Adaptive against uniform particles: run time against error, seed means against an independent reference.

For one cloud scene (``growing``, or ``cumulus``: one heated patch in a wide domain), the study runs

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

    cloudpbf adaptive-pareto [--scene growing|cumulus] [--seeds 3] [--min-stable-seeds N] [--resamples 1000]
                             [--scale gpu]
    cloudpbf adaptive-pareto --scene growing --from-data --out reports/gpu
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import click
import numpy as np
import pandas as pd
import typer

from bench import runs
from bench.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleName,
                              ScaleOpt, SchedulerOpt, WorkersOpt, refusals, study_context)
from bench.pareto import pareto_front
from bench.studies.context import StudyContext
from bench.studies.registry import ReportSection, Study, register
from bench.studies.scales import scale_steps
from pbf_cuda.scene import Scene, load_scene

SCENES = ("growing", "cumulus")
CRITERIA = ("paper", "lookahead", "thermal", "heated")
UNIFORM_SPACINGS = (68.0, 54.0, 43.0, 34.0)      # m at the GPU scale
ADAPTIVE_SPACINGS = (68.0, 54.0)                 # level-0 spacing, m; max_level 3 halves it
FURTHER_VARIANTS = (("thermal", 68.0, 4, 1.0, 0, ""),    # (criterion, level-0 spacing m, max_level, threshold
                    ("thermal", 68.0, 3, 0.25, 0, ""),   # scale, adapt_every, pair kernel): one level deeper (finest
                    ("thermal", 54.0, 3, 0.25, 0, ""),   # 27 m from 68 m), split/merge thresholds at a quarter (eq. 20:
                    ("thermal", 68.0, 4, 0.25, 0, ""),   # more of the warm air fine), splitting and merging every 4
                    ("thermal", 68.0, 4, 0.25, 4, ""),   # steps instead of the scenes' 2 (half the adaptive phases'
                    ("thermal", 68.0, 3, 0.25, 4, ""),   # cost), and the kernel at the pair's mean radius instead
                    ("thermal", 68.0, 4, 0.25, 4, "mean_radius"),   # of eq. 19's mean of kernels (-km); with
                    ("thermal", 68.0, 4, 0.25, 0, "mean_radius"),   # -km, splitting and merging every 8 and
                    ("thermal", 68.0, 4, 0.25, 8, "mean_radius"),   # 16 steps
                    ("thermal", 68.0, 4, 0.25, 16, "mean_radius"))
DEFAULT_MAX_LEVEL = 3
REFERENCE_SPACING = 27.0
ANALYSIS_GRID = (32, 32, 32)
SPACING_FACTOR = {"gpu": 1.0, "cpu": 3.0, "smoke": 6.0}
"""Spacings are multiplied by this at smaller scales (cpu: 27x fewer particles, smoke: 216x)."""
MIN_STABLE_SEEDS: int | None = None
"""Stable seeds a configuration needs to enter the verdict (uniform front and adaptive variants); None: all the
seeds the study ran (see the module's docstring for why)."""
GOAL_SPEEDUP = 1.6
"""The speed-up at equal error the study measures its variants against: the paper's own ratio (Table 1's totals,
1219 against 736 ms per step for the growing cloud, 1.66), rounded down."""
BOOTSTRAP_REPLICATES = 1000
"""Resamples of the seeds behind each variant's speed-up interval (see :func:`bootstrap_speedups`)."""
SERIES = (("cover", "cloud_cover"), ("volume", "cloudy_volume"), ("lwp", "lwp_mean"),
          ("base", "cloud_base"), ("top", "cloud_top"))


def finest_spacing(spacing_m: float, max_level: float) -> float:
    """The finest particles' spacing, m, of level-0 spacing `spacing_m` (h_l = h0 2^(-l/3), section 5.2)."""
    return spacing_m * 2.0 ** (-max_level / 3.0)


@dataclass(frozen=True)
class Config:
    """One configuration of the study (all its seeds share it)."""
    name: str          # uniform-68m, paper-54m, lookahead-68m, reference-27m
    kind: str          # uniform | adaptive | reference
    spacing_m: float   # particle spacing (adaptive: level 0)
    criterion: str     # "" for uniform runs
    max_level: int = 0              # adaptive: the finest level (spacing halves every 3 levels); 0 for uniform
    threshold_scale: float = 1.0    # adaptive: eq. 20's split and merge thresholds (alpha, beta) times this
    adapt_every: int = 0            # adaptive: split and merge every this many steps; 0: the scene's own
    pair_kernel: str = ""           # adaptive: adaptive.pair_kernel; "": the scene's own (eq. 19)
    overrides: tuple = ()           # adaptive: further scene overrides, ((key, value), ...)

    @property
    def finest_spacing_m(self) -> float:
        return finest_spacing(self.spacing_m, self.max_level)

    def adaptive_overrides(self, base: Scene) -> dict:
        """Overrides of `base` (an adaptive scene) for this variant: criterion, finest level, scaled thresholds."""
        if self.kind != "adaptive":
            return {}
        over = {"adaptive.criterion": self.criterion, "adaptive.max_level": self.max_level}
        if self.threshold_scale != 1.0:
            over |= {"adaptive.split_threshold": base.adaptive.split_threshold * self.threshold_scale,
                     "adaptive.merge_threshold": base.adaptive.merge_threshold * self.threshold_scale}
        if self.adapt_every:
            over["adaptive.every"] = self.adapt_every
        if self.pair_kernel:
            over["adaptive.pair_kernel"] = self.pair_kernel
        return over | dict(self.overrides)


def variant_name(criterion: str, spacing: float, max_level: int, threshold_scale: float, adapt_every: int = 0,
                 pair_kernel: str = "") -> str:
    """'thermal-68m', 'thermal-68m-L4' (finest level 4), 'thermal-54m-t0.25' (thresholds times 0.25),
    'thermal-68m-L4-t0.25-e4' (split and merge every 4 steps), '...-km' (the kernel at the pair's mean radius)."""
    name = f"{criterion}-{spacing:g}m"
    if max_level != DEFAULT_MAX_LEVEL:
        name += f"-L{max_level}"
    if threshold_scale != 1.0:
        name += f"-t{threshold_scale:g}"
    if adapt_every:
        name += f"-e{adapt_every}"
    if pair_kernel == "mean_radius":
        name += "-km"
    return name


def configs(scale_name: str) -> list[Config]:
    f = SPACING_FACTOR.get(scale_name, 1.0)
    out = [Config(f"uniform-{s:g}m", "uniform", s * f, "") for s in UNIFORM_SPACINGS]
    variants = [(c, s, DEFAULT_MAX_LEVEL, 1.0, 0, "") for c in CRITERIA for s in ADAPTIVE_SPACINGS] + list(FURTHER_VARIANTS)
    out += [Config(variant_name(c, s, level, t, e, k), "adaptive", s * f, c, level, t, e, k)
            for c, s, level, t, e, k in variants]
    out.append(Config(f"reference-{REFERENCE_SPACING:g}m", "reference", REFERENCE_SPACING * f, ""))
    return out


def scene_for(config: Config, scene_name: str, step_fraction: float) -> Scene:
    base = load_scene(f"{scene_name}_adaptive" if config.kind == "adaptive" else scene_name)
    scene = base.with_spacing(config.spacing_m).replace(**config.adaptive_overrides(base))
    return scale_steps(scene, step_fraction)


def plan(ctx: StudyContext, scene_name: str, seeds: int,
         study_configs: list[Config] | None = None) -> list[tuple[Config, int, runs.RunSpec]]:
    """(config, seed, run) of every run: of `study_configs`, default the study's own (:func:`configs`)."""
    out = []
    for config in configs(ctx.scale.name) if study_configs is None else study_configs:
        scene = scene_for(config, scene_name, ctx.scale.step_fraction)
        for seed in range(seeds):
            # one checkpoint at the end: a study run is short, and full-state writes would dominate its time
            spec = runs.RunSpec("particles", scene, backend=ctx.backend, seed=seed, keep_snapshots=1,
                                checkpoint_every=scene.time.steps, diagnostics_resolution=ANALYSIS_GRID,
                                warmup_steps=5)
            out.append((config, seed, spec))
    return out


# ---- analysis --------------------------------------------------------------------------------------
def _relative_l2(values, reference) -> float:
    values, reference = np.asarray(values, float), np.asarray(reference, float)
    ok = np.isfinite(values) & np.isfinite(reference)
    norm = float(np.linalg.norm(reference[ok]))
    if not ok.any() or norm == 0.0:
        return math.nan
    return float(np.linalg.norm(values[ok] - reference[ok])) / norm


def signature(result: runs.RunResult) -> dict | None:
    """Time series (on the snapshot times) and the final cloud-fraction profile of one run."""
    stats, prof = result.stats(), result.profiles()
    if not result.stable or not len(stats):
        return None
    sig = {"time": stats["time_s"].to_numpy(float)}
    for key, column in SERIES:
        sig[key] = stats[column].to_numpy(float) if column in stats else np.full(len(stats), np.nan)
    if len(prof):
        last = prof[prof["time_s"] == prof["time_s"].max()] if "time_s" in prof else prof
        final = last.groupby("z", sort=True)["cloud_fraction"].mean()
        sig["z"], sig["profile"] = final.index.to_numpy(float), final.to_numpy(float)
    return sig


def aligned_signatures(sigs: list[dict | None]) -> dict | None:
    """The signatures (None ones left out) on the first one's times and heights, one row per signature:
    {"time", "cover": (n, T), ..., and "z", "profile": (n, Z) where every one has a profile}; None without any."""
    sigs = [s for s in sigs if s is not None]
    if not sigs:
        return None
    t = sigs[0]["time"]
    out = {"time": t}
    for key, _ in SERIES:
        out[key] = np.array([_interp_nan(t, s["time"], s[key]) for s in sigs])
    if all("z" in s for s in sigs):
        z = sigs[0]["z"]
        out["z"] = z
        out["profile"] = np.array([np.interp(z, s["z"], s["profile"]) for s in sigs])
    return out


def mean_of_rows(aligned: dict, rows=slice(None)) -> dict:
    """Seed mean of the `rows` of :func:`aligned_signatures`; base/top averaged where defined."""
    out = {"time": aligned["time"]}
    with warnings.catch_warnings():   # a time without cloud in any seed: NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        for key, _ in SERIES:
            out[key] = np.nanmean(aligned[key][rows], axis=0)
    if "z" in aligned:
        out["z"], out["profile"] = aligned["z"], aligned["profile"][rows].mean(axis=0)
    return out


def mean_signature(sigs: list[dict]) -> dict | None:
    """Seed mean of signatures (on the first one's times); base/top averaged where defined."""
    aligned = aligned_signatures(sigs)
    return None if aligned is None else mean_of_rows(aligned)


def _interp_nan(t, ts, values):
    """Linear interpolation that keeps NaN (no cloud) where the nearest sample is NaN."""
    idx = np.clip(np.searchsorted(ts, t), 0, len(ts) - 1)
    out = np.interp(t, ts, np.nan_to_num(values))
    out[~np.isfinite(values[idx])] = np.nan
    return out


def errors(sig: dict | None, ref: dict | None) -> dict:
    keys = [k for k, _ in SERIES] + ["profile"]
    if sig is None or ref is None:
        return {f"e_{k}": math.nan for k in keys} | {"error": math.nan}
    out = {}
    for key, _ in SERIES:
        out[f"e_{key}"] = _relative_l2(_interp_nan(ref["time"], sig["time"], sig[key]), ref[key])
    out["e_profile"] = (_relative_l2(np.interp(ref["z"], sig["z"], sig["profile"]), ref["profile"])
                        if "z" in sig and "z" in ref else math.nan)
    out["error"] = float(np.mean([out["e_cover"], out["e_volume"], out["e_lwp"]]))
    return out


def series_frame(keys: list[tuple[str, int]], sigs: list[dict | None]) -> pd.DataFrame:
    """The runs' signatures as one long table (``adaptive_pareto_series.csv``): config, seed, series (cover,
    volume, lwp, base, top: over time_s; profile: over z), coordinate (s or m) and value; none for a run
    without a signature (unstable, or no snapshot).  :func:`signatures_from_series` reads it back, so that
    ``--from-data`` can redo every error and the seed resampling without the runs."""
    frames = []
    for (config, seed), sig in zip(keys, sigs):
        if sig is None:
            continue
        parts = [(key, sig["time"], sig[key]) for key, _ in SERIES]
        if "z" in sig:
            parts.append(("profile", sig["z"], sig["profile"]))
        for key, x, v in parts:
            frames.append(pd.DataFrame({"config": config, "seed": int(seed), "series": key,
                                        "coordinate": np.asarray(x, float), "value": np.asarray(v, float)}))
    columns = ["config", "seed", "series", "coordinate", "value"]
    return pd.concat(frames, ignore_index=True)[columns] if frames else pd.DataFrame(columns=columns)


def signatures_from_series(frame: pd.DataFrame) -> dict[tuple[str, int], dict]:
    """(config, seed) -> signature, from :func:`series_frame`'s table (the inverse of that function); ValueError
    naming the missing columns of a table that is not one."""
    missing = [c for c in ("config", "seed", "series", "coordinate", "value") if c not in frame.columns]
    if missing:
        raise ValueError(f"missing column(s) {', '.join(missing)}")
    out = {}
    for (config, seed), run in frame.groupby(["config", "seed"], sort=False):
        by = {k: g.sort_values("coordinate") for k, g in run.groupby("series", sort=False)}
        if "cover" not in by:
            continue
        sig = {"time": by["cover"]["coordinate"].to_numpy(float)}
        for key, _ in SERIES:
            sig[key] = (by[key]["value"].to_numpy(float) if key in by else np.full(len(sig["time"]), np.nan))
        if "profile" in by:
            sig["z"], sig["profile"] = by["profile"]["coordinate"].to_numpy(float), by["profile"]["value"].to_numpy(float)
        out[(str(config), int(seed))] = sig
    return out


def seed_groups(per_run: pd.DataFrame, sigs: dict[tuple[str, int], dict]) -> dict[str, dict[int, tuple]]:
    """config -> {seed: (signature or None, ms per step)} from the per-run rows and the runs' signatures; an
    unstable run has no signature (it enters no mean)."""
    out: dict[str, dict[int, tuple]] = {}
    for row in per_run.itertuples():
        stable = _truthy(row.stable)
        key = (str(row.config), int(row.seed))
        out.setdefault(str(row.config), {})[int(row.seed)] = (sigs.get(key) if stable else None,
                                                              float(row.ms_per_step) if stable else math.nan)
    return out


def _ms_per_step(result: runs.RunResult, steps: int) -> float:
    return 1e3 * float(result.step_wall_s) / steps if result.stable and steps else math.nan


def _pbf_ms(result: runs.RunResult) -> float:
    t = result.timings()
    return t["pbf"]["total_ms"] / t["pbf"]["count"] if "pbf" in t and t["pbf"]["count"] else math.nan


def _mean_particles(result: runs.RunResult) -> float:
    stats = result.stats()
    if "n_particles" in stats and len(stats):
        return float(stats["n_particles"].mean())
    return float(result.max_particles)


def uniform_front(uniform: pd.DataFrame) -> pd.DataFrame:
    """The uniform configurations no other uniform one beats in both ms/step and error, by error."""
    return pareto_front(uniform, "ms_per_step", "error").sort_values("error")


def _loglog_within(x: float, xs, ys) -> float:
    """y at `x`, interpolated in log x and log y between the points (xs, ys); NaN with fewer than two points or
    outside their range of x."""
    if len(xs) < 2 or not np.isfinite(x) or x <= 0:
        return math.nan
    lx, ly = np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float))
    if not lx.min() <= math.log(x) <= lx.max():
        return math.nan
    order = np.argsort(lx)
    return float(np.exp(np.interp(math.log(x), lx[order], ly[order])))


def time_at_error(front: pd.DataFrame, error: float) -> float:
    """ms/step of the uniform front at `error`, log-log interpolated; NaN outside the front's error range."""
    return _loglog_within(error, front["error"].to_numpy(float), front["ms_per_step"].to_numpy(float))


def pbf_cost_at_count(uniform: pd.DataFrame, particles: float) -> float:
    """PBF ms per particle of uniform runs at a particle count, interpolated in log(count)."""
    u = uniform.dropna(subset=["pbf_ms_per_particle", "particles"]).sort_values("particles")
    if len(u) < 2:
        return math.nan
    return float(np.interp(math.log(particles), np.log(u["particles"].to_numpy(float)),
                           u["pbf_ms_per_particle"].to_numpy(float)))


def uniform_time_at_count(uniform: pd.DataFrame, particles: float) -> float:
    """ms/step of a uniform run with `particles` particles, log-log interpolated between the uniform runs; NaN
    outside their range of counts."""
    u = uniform.dropna(subset=["ms_per_step", "particles"])
    return _loglog_within(particles, u["particles"].to_numpy(float), u["ms_per_step"].to_numpy(float))


def speedup_factors(t_at_error: float, t_at_count: float, ms_per_step: float) -> dict:
    """A variant's speed-up at equal error split in two factors whose product it is::

        speedup = t_u(e) / t_a = [t_u(e) / t_u(N_a)] * [t_u(N_a) / t_a]
                =  speedup_from_particles  /  step_cost_ratio

    with t_u(e) the uniform front's time at the variant's error, t_u(N_a) a uniform run's time at the variant's
    mean particle count and t_a the variant's own: what placing the particles adaptively buys (the speed-up if
    an adaptive particle-step cost what a uniform one does), and what the adaptive step costs beyond a
    uniform step of its size (neighbour lists over mixed levels, splitting, merging, the smoothing limiter)."""
    ok = np.isfinite(t_at_count) and t_at_count > 0
    return {"uniform_ms_at_equal_particles": _none_if_nan(t_at_count),
            "speedup_from_particles": _none_if_nan(t_at_error / t_at_count) if ok else None,
            "step_cost_ratio": _none_if_nan(ms_per_step / t_at_count) if ok else None}


def bootstrap_speedups(groups: dict[str, dict[int, tuple]], kinds: dict[str, str], qualified: set[str],
                       replicates: int = BOOTSTRAP_REPLICATES, seed: int = 0) -> dict:
    """Each qualifying adaptive variant's speed-up at equal error over `replicates` resamples of the seeds.

    A resample draws the study's seeds with replacement, one draw for all configurations (every configuration
    ran the same seeds, so they stay paired), and repeats the whole analysis on it: the reference's seed mean,
    each qualifying configuration's seed mean, its error and ms per step, the uniform front and the speed-ups.
    The spread of a variant's speed-up over the resamples is what the finite number of seeds leaves unknown,
    the reference's seeds included; picking the best of many variants on the same seeds is not corrected for
    (``best_share`` says how often each one wins).

    Returns ``{"speedups": {config: array of speed-ups, NaN where the variant's error is outside the front},
    "best": array of the best variant's name per resample ("" where none is scored), "replicates": n}``."""
    rng = np.random.default_rng(seed)
    seeds = sorted({s for runs_ in groups.values() for s in runs_})
    ref_name = next((c for c, k in kinds.items() if k == "reference"), None)
    uniform = [c for c in groups if kinds.get(c) == "uniform" and c in qualified]
    adaptive = [c for c in groups if kinds.get(c) == "adaptive" and c in qualified]
    speedups = {c: np.full(replicates, np.nan) for c in adaptive}
    best = np.full(replicates, "", dtype=object)
    if ref_name is None or not seeds or not adaptive:
        return {"speedups": speedups, "best": best, "replicates": int(replicates)}

    # each configuration's runs aligned once (as mean_signature aligns them), so that a resample's seed mean is a
    # mean over rows
    aligned = {}
    for config in [ref_name] + uniform + adaptive:
        runs_ = groups[config]
        order = sorted(runs_)
        stable = [s for s in order if runs_[s][0] is not None]
        aligned[config] = ({s: i for i, s in enumerate(order)}, np.array([runs_[s][1] for s in order], float),
                           {s: i for i, s in enumerate(stable)}, aligned_signatures([runs_[s][0] for s in stable]))

    def resampled(config, draw):
        index, ms, row_of, stacks = aligned[config]
        picked = [index[s] for s in draw if s in index]
        rows = [row_of[s] for s in draw if s in row_of]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean_ms = float(np.nanmean(ms[picked])) if picked else math.nan
        return (mean_of_rows(stacks, rows) if rows else None), mean_ms

    for b in range(replicates):
        draw = rng.choice(seeds, size=len(seeds), replace=True)
        reference, _ = resampled(ref_name, draw)
        rows = {}
        for config in uniform + adaptive:
            sig, ms = resampled(config, draw)
            rows[config] = (errors(sig, reference)["error"], ms)
        u = pd.DataFrame([{"config": c, "error": rows[c][0], "ms_per_step": rows[c][1]} for c in uniform])
        u = u[np.isfinite(u["error"]) & np.isfinite(u["ms_per_step"])] if len(u) else u
        front = uniform_front(u) if len(u) else u
        top, top_s = "", -math.inf
        for config in adaptive:
            error, ms = rows[config]
            t = time_at_error(front, error)
            s = t / ms if np.isfinite(t) and np.isfinite(ms) and ms > 0 else math.nan
            speedups[config][b] = s
            if np.isfinite(s) and s > top_s:
                top, top_s = config, s
        best[b] = top
    return {"speedups": speedups, "best": best, "replicates": int(replicates)}


def speedup_interval(samples: np.ndarray, goal: float = GOAL_SPEEDUP) -> dict:
    """The 5th and 95th percentiles of a variant's resampled speed-ups (over the resamples where it has one),
    the share of resamples where it has one, and the share where it reaches `goal`."""
    samples = np.asarray(samples, float)
    ok = np.isfinite(samples)
    if not ok.any():
        return {"speedup_interval": None, "speedup_defined_share": 0.0, "p_speedup_at_least_goal": 0.0}
    lo, hi = np.percentile(samples[ok], [5.0, 95.0])
    return {"speedup_interval": [float(lo), float(hi)], "speedup_defined_share": float(ok.mean()),
            "p_speedup_at_least_goal": float(np.mean(ok & (samples >= goal)))}


def analyse(entries: list[tuple[Config, int, runs.RunSpec]], results: list[runs.RunResult], scene_name: str,
            device: str, commit: str, min_stable_seeds: int | None = MIN_STABLE_SEEDS,
            replicates: int = BOOTSTRAP_REPLICATES, sigs: list[dict | None] | None = None
            ) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """(per-run rows, per-configuration rows, verdict); `replicates` resamples of the seeds give each variant's
    speed-up interval (0: none).  `sigs`: the results' signatures, where the caller has them already."""
    sigs = [signature(r) for r in results] if sigs is None else sigs
    by_config: dict[Config, list[int]] = {}
    for i, (config, _, _) in enumerate(entries):
        by_config.setdefault(config, []).append(i)
    ref_config = next(c for c in by_config if c.kind == "reference")
    reference = mean_signature([sigs[i] for i in by_config[ref_config]])

    run_rows, config_rows = [], []
    for config, idx in by_config.items():
        mean_sig = mean_signature([sigs[i] for i in idx])
        err = errors(mean_sig, reference)
        per_seed = [errors(sigs[i], reference)["error"] for i in idx]
        ms = [_ms_per_step(results[i], entries[i][2].total_steps) for i in idx]
        pbf = [_pbf_ms(results[i]) for i in idx]
        parts = [_mean_particles(results[i]) for i in idx]
        stable = [bool(results[i].stable) for i in idx]
        with np.errstate(all="ignore"):
            row = {"config": config.name, "kind": config.kind, "criterion": config.criterion,
                   "spacing_m": config.spacing_m, "max_level": config.max_level,
                   "threshold_scale": config.threshold_scale, "adapt_every": config.adapt_every,
                   "pair_kernel": config.pair_kernel, "seeds": len(idx), "stable_seeds": int(sum(stable)),
                   "particles": float(np.nanmean(parts)), "ms_per_step": float(np.nanmean(ms)),
                   "ms_per_step_spread": float(np.nanstd(ms)), "pbf_ms": float(np.nanmean(pbf)),
                   **err, "error_seed_spread": (float(np.nanstd(per_seed)) if np.isfinite(per_seed).sum() >= 2
                                                else math.nan)}
        row["pbf_ms_per_particle"] = row["pbf_ms"] / row["particles"] if row["particles"] else math.nan
        config_rows.append(row)
        for i, e_seed in zip(idx, per_seed):
            res = results[i]
            run_rows.append({"config": config.name, "kind": config.kind, "criterion": config.criterion,
                             "spacing_m": config.spacing_m, "max_level": config.max_level,
                             "threshold_scale": config.threshold_scale, "adapt_every": config.adapt_every,
                             "pair_kernel": config.pair_kernel, "seed": entries[i][1], "stable": bool(res.stable),
                             "reason": res.reason, "particles": _mean_particles(res),
                             "max_particles": res.max_particles,
                             "ms_per_step": _ms_per_step(res, entries[i][2].total_steps), "pbf_ms": _pbf_ms(res),
                             "error_this_seed": e_seed, **{f"config_{k}": v for k, v in err.items()},
                             "device": res.device, "commit": commit, "run_dir": str(res.path)})
    per_run, per_config = pd.DataFrame(run_rows), pd.DataFrame(config_rows)
    groups = seed_groups(per_run, {(config.name, seed): sigs[i] for i, (config, seed, _) in enumerate(entries)})
    verdict = build_verdict(per_run, per_config, scene_name, device, commit, min_stable_seeds, groups=groups,
                            replicates=replicates)
    add_verdict_columns(per_config, verdict)
    return per_run, per_config, verdict


def add_verdict_columns(per_config: pd.DataFrame, verdict: dict) -> None:
    """Each adaptive configuration's speed-up (and, where the seeds were resampled, its 5-95% interval) as
    columns of the per-configuration table; pops the verdict's private ``_speedups``."""
    per_config["speedup_at_equal_error"] = per_config["config"].map(verdict.pop("_speedups"))
    intervals = {v["name"]: v.get("speedup_interval") for v in verdict["variants"] + verdict["excluded"]}
    for k, column in enumerate(("speedup_p05", "speedup_p95")):
        per_config[column] = per_config["config"].map(
            lambda c: (intervals.get(c) or [math.nan, math.nan])[k])


def required_stable_seeds(per_config: pd.DataFrame, min_stable_seeds: int | None = MIN_STABLE_SEEDS) -> int:
    """The stable seeds a configuration needs: `min_stable_seeds`, or (None) every seed the study ran."""
    if min_stable_seeds is not None:
        if int(min_stable_seeds) < 1:
            raise ValueError(f"min_stable_seeds = {min_stable_seeds}: at least 1")
        return int(min_stable_seeds)
    return int(per_config["seeds"].max()) if len(per_config) else 1


def _qualification(per_run: pd.DataFrame | None, per_config: pd.DataFrame, required: int) -> dict[str, list[str]]:
    """config name -> the reasons it is left out of the verdict (empty: it qualifies)."""
    out = {}
    for row in per_config.itertuples():
        reasons = []
        stable, seeds = int(row.stable_seeds), int(row.seeds)
        if stable < required:
            reasons.append(f"stable in {stable} of {seeds} seeds (the verdict needs {required})")
            if per_run is not None and "stable" in per_run:
                bad = per_run[(per_run["config"] == row.config) & ~per_run["stable"].map(_truthy)]
                for r in bad.itertuples():
                    why = getattr(r, "reason", None)
                    why = why if isinstance(why, str) and why else "unstable"
                    reasons.append(f"seed {int(r.seed)}: {why}")
        elif not (np.isfinite(row.error) and np.isfinite(row.ms_per_step)):
            reasons.append("no measurable error or time (no cloud in the seed mean, or no timed step)")
        out[row.config] = reasons
    return out


def _truthy(value) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes")
    return bool(value) and not (isinstance(value, float) and math.isnan(value))


def _none_if_nan(x):
    return None if x is None or not np.isfinite(x) else float(x)


def build_verdict(per_run: pd.DataFrame | None, per_config: pd.DataFrame, scene_name: str, device: str, commit: str,
                  min_stable_seeds: int | None = MIN_STABLE_SEEDS, groups: dict | None = None,
                  replicates: int = BOOTSTRAP_REPLICATES) -> dict:
    """The verdict from the per-configuration rows (``adaptive_pareto_configs.csv``) and the per-run rows
    (``adaptive_pareto.csv``: failure reasons and the reference seeds' errors, for the noise floor).

    Only configurations stable in at least :func:`required_stable_seeds` seeds, with a finite error and time,
    enter the uniform front and compete for ``best``; the others are listed under ``excluded``.  With `groups`
    (:func:`seed_groups`: every run's signature and time) and `replicates` > 0, the seeds are resampled
    (:func:`bootstrap_speedups`) and each qualifying variant gets its speed-up's 5-95% interval, the share of
    resamples where it reaches :data:`GOAL_SPEEDUP` and the share where it is the best variant.  The result has
    a private ``_speedups`` (config -> speed-up of every adaptive configuration with an error, for the CSV)."""
    required = required_stable_seeds(per_config, min_stable_seeds)
    reasons = _qualification(per_run, per_config, required)
    ok = per_config["config"].map(lambda c: not reasons[c])
    uniform = per_config[(per_config.kind == "uniform") & ok]
    front = uniform_front(uniform) if len(uniform) else uniform
    variants, excluded, speedups = [], [], {}
    for row in per_config[per_config.kind != "reference"].itertuples():
        pair_kernel = getattr(row, "pair_kernel", "")    # "" (read back as NaN): the scene's own, eq. 19
        entry = {"name": row.config, "criterion": row.criterion if isinstance(row.criterion, str) else "",
                 "spacing_m": float(row.spacing_m),
                 # CSVs written before these columns existed: every variant then had max_level 3, thresholds x1
                 "max_level": int(getattr(row, "max_level", DEFAULT_MAX_LEVEL if row.kind == "adaptive" else 0)),
                 "threshold_scale": float(getattr(row, "threshold_scale", 1.0)),
                 "adapt_every": int(getattr(row, "adapt_every", 0) or 0),   # 0: the scene's own (older CSVs)
                 "pair_kernel": pair_kernel if isinstance(pair_kernel, str) else "",
                 "stable_seeds": int(row.stable_seeds), "seeds": int(row.seeds),
                 "error": _none_if_nan(row.error), "ms_per_step": _none_if_nan(row.ms_per_step)}
        if row.kind == "adaptive":
            t_uniform = time_at_error(front, row.error)
            speedup = t_uniform / row.ms_per_step if np.isfinite(t_uniform) else math.nan
            speedups[row.config] = _none_if_nan(speedup)
            base = pbf_cost_at_count(uniform, row.particles) if row.particles else math.nan
            entry |= {"speedup_at_equal_error": _none_if_nan(speedup),
                      "uniform_ms_at_equal_error": _none_if_nan(t_uniform),
                      # one stable seed has no spread (older CSVs wrote 0 for it)
                      "error_seed_spread": _none_if_nan(row.error_seed_spread) if row.stable_seeds >= 2 else None,
                      "particles": float(row.particles),
                      "cost_ratio_per_particle": _none_if_nan(row.pbf_ms_per_particle / base)
                      if np.isfinite(base) and base else None,
                      **speedup_factors(t_uniform, uniform_time_at_count(uniform, row.particles), row.ms_per_step)}
        if reasons[row.config]:
            excluded.append({"name": row.config, "kind": row.kind, **{k: v for k, v in entry.items() if k != "name"},
                             "reasons": reasons[row.config]})
        elif row.kind == "adaptive":
            variants.append(entry)
    resampling = None
    if groups and replicates > 0:
        kinds = dict(zip(per_config["config"].astype(str), per_config["kind"].astype(str)))
        boot = bootstrap_speedups(groups, kinds, {c for c, why in reasons.items() if not why}, int(replicates))
        for entry in variants:
            entry |= speedup_interval(boot["speedups"][entry["name"]])
            entry["best_share"] = float(np.mean(boot["best"] == entry["name"]))
        resampling = {"replicates": boot["replicates"], "seeds": int(per_config["seeds"].max()),
                      "goal_speedup": GOAL_SPEEDUP, "no_best_share": float(np.mean(boot["best"] == ""))}
    costs = [v["cost_ratio_per_particle"] for v in variants if v["cost_ratio_per_particle"] is not None]
    verdict = {"scene": scene_name, "cost_ratio_per_particle": float(np.median(costs)) if costs else None,
               "min_stable_seeds": required, "variants": variants, "excluded": excluded,
               "noise_floor": _noise_floor(per_run),
               "reference_stable_seeds": _reference_seeds(per_config),
               "uniform_front": front[["config", "error", "ms_per_step"]].to_dict("records"),
               "resampling": resampling, "device": device, "commit": commit}
    verdict["best"], verdict["verdict"] = _verdict_text(variants, excluded, front, verdict["noise_floor"],
                                                        scene_name, required, resampling)
    verdict["_speedups"] = speedups
    return verdict


def _noise_floor(per_run: pd.DataFrame | None) -> float:
    """Mean error of a single reference seed against the reference mean (NaN without reference rows)."""
    if per_run is None or "error_this_seed" not in per_run:
        return math.nan
    ref = per_run.loc[per_run["kind"] == "reference", "error_this_seed"].to_numpy(float)
    return float(np.nanmean(ref)) if np.isfinite(ref).any() else math.nan


def _reference_seeds(per_config: pd.DataFrame) -> str | None:
    ref = per_config[per_config.kind == "reference"]
    return f"{int(ref['stable_seeds'].iloc[0])} of {int(ref['seeds'].iloc[0])}" if len(ref) else None


def _verdict_text(variants: list[dict], excluded: list[dict], front: pd.DataFrame, noise_floor: float,
                  scene_name: str, required: int, resampling: dict | None = None):
    left_out = [e for e in excluded if e["kind"] == "adaptive"]
    left_uniform = [e for e in excluded if e["kind"] == "uniform"]
    note = ""
    if left_out or left_uniform:
        note = " Left out (stable in fewer than {} seeds, or no error): {}.".format(
            required, ", ".join(f"{e['name']} ({e['stable_seeds']}/{e['seeds']} stable)"
                                for e in left_uniform + left_out))
    scored = [v for v in variants if v["speedup_at_equal_error"] is not None]
    if scored:
        best = max(scored, key=lambda v: v["speedup_at_equal_error"])
        s = best["speedup_at_equal_error"]
        word = "faster" if s >= 1 else "slower"
        text = (f"{scene_name}: the best adaptive variant, {best['name']} (stable in {best['stable_seeds']} of "
                f"{best['seeds']} seeds), is {s if s >= 1 else 1 / s:.2f}x {word} than uniform particles at its "
                f"error {best['error']:.3f} (seed-noise floor {noise_floor:.3f}).")
        if best.get("speedup_from_particles") is not None:
            text += (f" Its {best['particles']:,.0f} particles would give {best['speedup_from_particles']:.2f}x if "
                     f"they cost what uniform particles do (a uniform run of that size takes "
                     f"{best['uniform_ms_at_equal_particles']:.2f} ms per step); its step costs "
                     f"{best['step_cost_ratio']:.2f}x that.")
        if resampling and best.get("speedup_interval"):
            lo, hi = best["speedup_interval"]
            text += (f" Over {resampling['replicates']} resamples of its {resampling['seeds']} seeds the speed-up "
                     f"lies between {lo:.2f}x and {hi:.2f}x (5-95%), reaches {resampling['goal_speedup']:g}x in "
                     f"{100 * best['p_speedup_at_least_goal']:.0f}% of them, and this variant is the best in "
                     f"{100 * best['best_share']:.0f}%.")
        return best, text + note
    if not variants:
        what = "adaptive variant" if left_out else "adaptive run"
        return None, (f"{scene_name}: no best variant: no {what} is stable in at least {required} seeds with a "
                      f"measurable error." + note)
    if len(front) < 2:
        return None, (f"{scene_name}: no best variant: fewer than two uniform configurations are stable in at "
                      f"least {required} seeds with a measurable error, so there is no uniform front to compare "
                      f"with." + note)
    lo, hi = front["error"].min(), front["error"].max()
    errs = ", ".join(f"{v['name']} {v['error']:.3f}" for v in variants)
    return None, (f"{scene_name}: no best variant: no adaptive variant lies within the uniform front's error range "
                  f"[{lo:.3f}, {hi:.3f}] (adaptive errors: {errs}; seed-noise floor {noise_floor:.3f})." + note)


def rebuild_verdict(data_dir, scene_name: str = "growing", min_stable_seeds: int | None = MIN_STABLE_SEEDS,
                    write: bool = True, replicates: int = BOOTSTRAP_REPLICATES) -> dict:
    """The verdict again from DATA's ``adaptive_pareto[_SCENE].csv`` and ``adaptive_pareto_configs[_SCENE].csv``,
    without running anything; device and commit stay those of the verdict already there (else the runs' CSV).
    Where ``adaptive_pareto_series[_SCENE].csv`` is there too (studies from 2026-11-26 on), the seeds are
    resampled as in the study.  Writes ``adaptive_verdict[_SCENE].json`` (and the configurations' speed-up
    columns) unless `write` is False."""
    if scene_name not in SCENES:
        raise ValueError(f"scene = {scene_name!r}: allowed {', '.join(SCENES)}")
    data_dir = Path(data_dir)
    suffix = "" if scene_name == "growing" else f"_{scene_name}"
    runs_path = data_dir / f"adaptive_pareto{suffix}.csv"
    configs_path = data_dir / f"adaptive_pareto_configs{suffix}.csv"
    for path in (runs_path, configs_path):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (run `cloudpbf adaptive-pareto --scene {scene_name}` first)")
    per_run, per_config = _read_data_csv(runs_path), _read_data_csv(configs_path)
    verdict_path = data_dir / f"adaptive_verdict{suffix}.json"
    old = json.loads(verdict_path.read_text()) if verdict_path.is_file() else {}
    device = old.get("device") or _first(per_run, "device") or "unknown"
    commit = old.get("commit") or _first(per_run, "commit") or "unknown"
    series_path = data_dir / f"adaptive_pareto_series{suffix}.csv"
    groups = None
    if series_path.is_file():
        try:
            sigs = signatures_from_series(_read_data_csv(series_path))
        except ValueError as exc:
            raise ValueError(f"{series_path}: {exc}") from None
        lacking = [f"{r.config} seed {int(r.seed)}" for r in per_run.itertuples()
                   if _truthy(r.stable) and (str(r.config), int(r.seed)) not in sigs]
        if lacking:
            raise ValueError(f"{series_path}: no series for {len(lacking)} stable run(s) of {runs_path.name} "
                             f"({', '.join(lacking[:3])}{', ...' if len(lacking) > 3 else ''}); it belongs to "
                             "another study, or was cut short (delete it to rebuild the verdict without resampling)")
        groups = seed_groups(per_run, sigs)
    verdict = build_verdict(per_run, per_config, scene_name, device, commit, min_stable_seeds, groups=groups,
                            replicates=replicates)
    add_verdict_columns(per_config, verdict)
    if write:
        runs.atomic_write_json(verdict_path, verdict)
        runs.write_csv(per_config, configs_path)
    return verdict


def _read_data_csv(path: Path) -> pd.DataFrame:
    """One of the study's CSVs; ValueError naming the file when it cannot be parsed."""
    try:
        return pd.read_csv(path, float_precision="round_trip")
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{path}: not a readable CSV ({why})") from None


def _first(frame: pd.DataFrame, column: str) -> str | None:
    values = frame[column].dropna() if column in frame else []
    return str(values.iloc[0]) if len(values) else None


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
    suffix = "" if scene_name == "growing" else f"_{scene_name}"
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
    from pathlib import Path
    from bench.render import compact_particles
    from bench.store.result import RunResult
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
    from pathlib import Path
    from bench.render import render_or_note, render_particles
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
    scene: Annotated[str, typer.Option(help="growing (the paper's example 1) or cumulus (one heated patch)")] = "growing",
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
               report=(ReportSection("adaptive_pareto", "Adaptive mode at equal error", "bench.report.build:_adaptive_pareto", 70),),
               outputs=("adaptive_pareto.csv", "adaptive_pareto_configs.csv", "adaptive_pareto_series.csv",
                        "adaptive_verdict.json"),
               command=adaptive_pareto_command))
