"""The run plans that more than one study runs, kept below the studies so that no study imports another.

compare's plan (every mode and seed of a cloud scene, :func:`compare_specs`) is also rendered by ``renders``;
its pair of scenes (:func:`scene_pair`) is also cycled by ``cycling``; the sweep's plan (:func:`sweep_plan`) is
also run on several GPUs by ``multigpu``.  This module registers no study.
"""
from __future__ import annotations

from cloudpbf import runs
from cloudpbf.statistics import grid_for_scene
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.scales import scale_scene
from pbf_cuda.scene import Scene, SceneError, list_scenes, load_scene

SOLVER_OF_MODE = {"non-adaptive": "particles", "adaptive": "particles", "grid": "grid"}
MIN_SEEDS = 5
"""The fewest seeds compare runs (its tests between modes need them)."""
SWEEP_SCENE = "growing"
SMOKE_CLOUD_BOX = {"domain.size": [1200.0, 1600.0, 1200.0], "time.dt": 4.0, "time.steps": 120,
                   "time.snapshot_every": 20}
"""The smoke scale's cloud box of compare, sweep and convergence (each adds its spacings): the cloud scene's physics
in a 1.2 x 1.6 x 1.2 km box that forms clouds within 480 s at dt = 4 s (docs/harness.md "Scales")."""


def scene_file_suffix(scene_name: str) -> str:
    """The suffix of a per-scene study's output files (adaptive-pareto, time-to-solution): none for ``growing``,
    each study's first scene, ``_<scene>`` for the others."""
    return "" if scene_name == "growing" else f"_{scene_name}"


# ---- compare -------------------------------------------------------------------------------------------
def scene_pair(name: str) -> tuple[Scene, Scene]:
    """(non-adaptive, adaptive) versions of a cloud scene.

    NAME_adaptive is used when it ships; otherwise adaptivity is switched on with level-0 particles
    twice the spacing (a level-3 particle then matches the non-adaptive size, as in the paper)."""
    base_name = name[: -len("_adaptive")] if name.endswith("_adaptive") and name[:-9] in list_scenes() else name
    base = load_scene(base_name)
    if base.atmosphere is None:
        raise ValueError(f"compare needs a cloud scene (one with an [atmosphere] section); '{name}' has none. "
                         f"Cloud scenes: {', '.join(n for n in list_scenes() if load_scene(n).thermodynamics)}")
    if base.adaptive.enabled:
        base = base.replace(**{"adaptive.enabled": False,
                               "particles.spacing": base.particles.spacing / 2 ** (base.adaptive.max_level / 3)})
    if f"{base_name}_adaptive" in list_scenes():
        adaptive = load_scene(f"{base_name}_adaptive")
    else:
        try:
            adaptive = base.replace(**{"adaptive.enabled": True, "adaptive.max_level": 3,
                                       "particles.spacing": 2.0 * base.particles.spacing})
        except SceneError as exc:
            raise ValueError(f"cannot make an adaptive twin of '{name}' by doubling its spacing ({exc}); "
                             f"write a scene file {base_name}_adaptive.toml") from None
    return base, adaptive


ANIMATION_FRAMES = 8
"""Stored states of the seed-0 non-adaptive run (the report's animation of the clouds developing)."""


def compare_specs(ctx: StudyContext, scene_name: str, seeds: int) -> list[tuple[str, int, runs.RunSpec]]:
    """(mode, seed, spec) for every mode and seed."""
    if seeds < MIN_SEEDS:
        raise ValueError(f"seeds = {seeds}: compare needs at least {MIN_SEEDS} seeds")
    box = getattr(ctx.scale, "compare_box", None)
    if box:
        base, adaptive = (s.replace(**box) for s in scene_pair(scene_name))
    else:
        base, adaptive = (scale_scene(s, ctx.scale.particles, ctx.scale.step_fraction) for s in scene_pair(scene_name))
    shape, _ = grid_for_scene(base)                  # one cell per non-adaptive spacing, for all three
    out = []
    for seed in range(seeds):
        out.append(("non-adaptive", seed, runs.RunSpec("particles", base, backend=ctx.backend, seed=seed,
                                                        diagnostics_resolution=shape,
                                                        keep_snapshots=ANIMATION_FRAMES if seed == 0 else 3)))
        out.append(("adaptive", seed, runs.RunSpec("particles", adaptive, backend=ctx.backend, seed=seed,
                                                    diagnostics_resolution=shape)))
        out.append(("grid", seed, runs.RunSpec("grid", base, seed=seed, resolution=shape)))
    return out


# ---- the sweep -----------------------------------------------------------------------------------------
def sweep_plan(ctx: StudyContext, scene_name: str = SWEEP_SCENE) -> list[dict]:
    """Every run of the sweep: dict(method, parameter, value, mode, spec)."""
    scale = ctx.scale
    base = load_scene(scene_name)
    adaptive = load_scene(f"{scene_name}_adaptive")
    box = getattr(scale, "sweep_box", None)
    if box:   # spacings (m) in a small box; the adaptive level-0 particles at the same spacing
        box = dict(box)
        spacings = box.pop("spacings")
        counts = sorted(spacings, reverse=True)                 # coarse to fine, as the counts
        make = lambda scene, s, adaptive_twin=False: scene.replace(**box, **{"particles.spacing": float(s)})  # noqa: E731
    else:
        counts = sorted(scale.sweep_particles)
        make = lambda scene, n, adaptive_twin=False: scale_scene(scene, n, scale.step_fraction)  # noqa: E731
    middle = counts[len(counts) // 2]
    mid_scene = make(base, middle)
    analysis, _ = grid_for_scene(mid_scene)
    plan = []

    def particles(parameter, value, mode, scene):
        spec = runs.RunSpec("particles", scene, backend=ctx.backend, seed=0, keep_snapshots=1,
                            diagnostics_resolution=analysis)
        plan.append(dict(method="particles", parameter=parameter, value=value, mode=mode, spec=spec))

    for n in counts:
        scene = make(base, n)
        particles("spacing", scene.particles.spacing, "non-adaptive", scene)
        scene = make(adaptive, n, True)
        particles("adaptive_spacing", scene.particles.spacing, "adaptive", scene)
    for it in scale.sweep_iterations:
        particles("iterations", it, "non-adaptive", mid_scene.replace(**{"pbf.iterations": int(it)}))
    mid_adaptive = make(adaptive, middle, True)
    for alpha in scale.sweep_split_thresholds:
        merge = min(mid_adaptive.adaptive.merge_threshold, 0.5 * alpha)
        particles("split_threshold", alpha, "adaptive",
                  mid_adaptive.replace(**{"adaptive.split_threshold": float(alpha),
                                          "adaptive.merge_threshold": float(merge)}))
    size = max(mid_scene.domain.size)
    for n in sorted(scale.sweep_grid_cells):
        shape = tuple(max(2, int(round(n * s / size))) for s in mid_scene.domain.size)
        plan.append(dict(method="grid", parameter="cells", value=n, mode="grid",
                         spec=runs.RunSpec("grid", mid_scene, seed=0, resolution=shape, keep_snapshots=1)))
    return plan
