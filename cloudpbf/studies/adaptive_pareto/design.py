"""The adaptive-pareto study's design: its scenes, the uniform spacings and adaptive variants it compares, the
reference, and the run of every (configuration, seed) (cloudpbf.studies.adaptive_pareto).  Spacings are m at the GPU
scale."""
from __future__ import annotations

from cloudpbf import runs
from cloudpbf.studies.adaptive_variants import DEFAULT_MAX_LEVEL, Config, finest_spacing, variant_name  # noqa: F401
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.scales import scale_steps
from pbf_cuda.scene import Scene, load_scene

SCENES = ("growing", "cumulus", "shallow_cumulus")
"""The study's scenes; each has an adaptive twin ``<scene>_adaptive``. Files of a scene other than growing carry
its name as a suffix (:func:`cloudpbf.studies.plans.scene_file_suffix`)."""
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
