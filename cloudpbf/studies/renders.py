"""The report's pictures, from cached runs (cloudpbf.render draws them; a missing OpenGL context leaves a
NAME.unavailable.txt note with the reason instead of a PNG).

* clouds_particles.png: the last state of the compare study's non-adaptive run (seed 0), particles
  coloured by cloud w;
* clouds_volume.png: the same particles deposited on the analysis grid, volume rendered;
* figure1_unsmoothed.png / figure1_smoothed.png: the paper's Figure 1, the smoothing_slab scene
  without (kappa = 0) and with temperature smoothing, seen from the front (all of the scene's steps at
  every scale, so that clouds have formed);
* figure3_shape_energy.png: the paper's Figure 3, shape energy (eq. 20) of the adaptive run's
  last state beside its cloud w;
* clouds_animation.gif and clouds_strip.png: the clouds developing, every stored state of the compare
  study's non-adaptive seed-0 run (plans.ANIMATION_FRAMES of them), as a looping GIF and as one strip.
"""
from __future__ import annotations

from pathlib import Path

from cloudpbf.report import plots
from cloudpbf.report.common import Inputs, Section, _command, _missing, _render_blocks
from cloudpbf import render, runs, statistics
from cloudpbf.studies.plans import compare_specs
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.registry import ReportSection, Study, register
from cloudpbf.studies.scales import scale_slab
from pbf_cuda.scene import load_scene

RENDERS = ("clouds_particles.png", "clouds_volume.png", "figure1_unsmoothed.png", "figure1_smoothed.png",
           "figure3_shape_energy.png", "clouds_animation.gif", "clouds_strip.png")


def animation_frames(res: runs.RunResult, scene) -> list[tuple[float, dict]]:
    """(time s, state) of every stored state of a run, in time order."""
    frames = []
    for path in res.snapshot_paths():
        step = int(path.stem.split("_")[-1])
        frames.append((step * scene.time.dt, res.snapshot(step)))
    return frames


def slab_specs(ctx: StudyContext) -> tuple[runs.RunSpec, runs.RunSpec]:
    """(unsmoothed, smoothed) runs of the Figure 1 slab at the context's particle count and all of the
    scene's steps at every scale: at the smoke scale's half (200 steps of 2 s) the smoothed slab has no
    cloud yet and the unsmoothed one 8 cloudy particles; at 400 steps 92 and 186 (2,000 particles, seed 0)."""
    scene = scale_slab(load_scene("smoothing_slab"), ctx.scale.slab_particles)
    make = lambda s: runs.RunSpec("particles", s, backend=ctx.backend, seed=0, keep_snapshots=1)  # noqa: E731
    return make(scene.replace(**{"smoothing.kappa": 0.0})), make(scene)


def _last_state(res: runs.RunResult, out_png: Path) -> dict | None:
    """The run's last stored state, or None after writing the render's note (an unstable run may have none)."""
    try:
        return res.snapshot()
    except FileNotFoundError:
        why = f"unstable at step {res.step}: {res.reason}" if not res.stable else "no stored state"
        runs.atomic_write_text(render.note_path(out_png), f"the run {res.path.name} has no state to draw ({why})\n")
        out_png.unlink(missing_ok=True)
        return None


def _draw(draw, out_png: Path, res: runs.RunResult, *args, **kwargs) -> Path | None:
    state = _last_state(res, out_png)
    return None if state is None else render.render_or_note(draw, out_png, state, *args, **kwargs)


def run_renders(ctx: StudyContext, scene_name: str = "growing") -> dict[str, Path | None]:
    """Draw every render from cached runs (running what is missing); returns name -> PNG or None (a note)."""
    out = ctx.data / "renders"
    out.mkdir(parents=True, exist_ok=True)
    plan = compare_specs(ctx, scene_name, ctx.scale.seeds)
    fixed = next(spec for mode, seed, spec in plan if mode == "non-adaptive" and seed == 0)
    adaptive = next(spec for mode, seed, spec in plan if mode == "adaptive" and seed == 0)
    unsmoothed, smoothed = slab_specs(ctx)
    res_fixed, res_adaptive, res_raw, res_smooth = ctx.run_parallel([fixed, adaptive, unsmoothed, smoothed],
                                                                    "renders")
    done = {"clouds_particles.png": _draw(render.render_particles, out / "clouds_particles.png", res_fixed,
                                          fixed.scene, color_by="cloud")}
    state = _last_state(res_fixed, out / "clouds_volume.png")
    if state is not None:
        grid = statistics.deposit_state(state, fixed.scene, fixed.diagnostics_resolution)
        done["clouds_volume.png"] = render.render_or_note(render.render_volume, out / "clouds_volume.png",
                                                          grid["cloud"], grid["cell_size"], origin=grid["origin"])
    else:
        done["clouds_volume.png"] = None
    for name, res, spec in (("figure1_unsmoothed.png", res_raw, unsmoothed),
                            ("figure1_smoothed.png", res_smooth, smoothed)):
        kappa = spec.scene.smoothing.kappa
        done[name] = _draw(render.render_particles, out / name, res, spec.scene, color_by="cloud", view="front",
                           title=f"smoothing_slab, kappa = {kappa:g}, step {res.step}")
    gif = out / "clouds_animation.gif"
    frames = animation_frames(res_fixed, fixed.scene)
    if frames:
        done["clouds_animation.gif"] = render.render_or_note(render.render_animation, gif, frames, fixed.scene,
                                                             out_strip=out / "clouds_strip.png")
    else:
        runs.atomic_write_text(render.note_path(gif), f"the run {res_fixed.path.name} stored no states\n")
        done["clouds_animation.gif"] = None
    strip = out / "clouds_strip.png"
    if done["clouds_animation.gif"] is None:      # the strip says why, as the animation does
        runs.atomic_write_text(render.note_path(strip), render.note_path(gif).read_text())
        strip.unlink(missing_ok=True)
    else:
        render.note_path(strip).unlink(missing_ok=True)
    done["clouds_strip.png"] = strip if strip.is_file() else None
    done["figure3_shape_energy.png"] = _draw(render.render_shape_energy, out / "figure3_shape_energy.png",
                                             res_adaptive, adaptive.scene)
    for name, path in done.items():
        ctx.say(f"renders: {name}: {'written' if path else 'unavailable (see ' + render.note_path(out / name).name + ')'}")
    return done


# ---- report: renders, Figures 1 and 3 ------------------------------------------------------------
def _renders(inp: Inputs, sec: Section, env: dict | None) -> None:
    _render_blocks(inp, sec, [
        ("clouds_particles", "particles with w > 1e-5 kg/kg, opacity rising with cloud density (clear air transparent)"),
        ("clouds_volume", "volume render of the particles' cloud field deposited on the statistics grid"),
    ])
    gif, reason = inp.render("clouds_animation", ".gif")
    if gif is not None:
        sec.add("image", plots.file_uri(gif, "image/gif"), source=gif, caption=(
            "The clouds developing: every stored state of the non-adaptive seed-0 compare run, looping "
            "(particles with w > 1e-5 kg/kg)."))
        _render_blocks(inp, sec, [("clouds_strip", "the same states side by side, time increasing to the right")])
    elif reason is not None:
        sec.add("note", f"clouds_animation: render unavailable: {reason}", level="warn",
                command=_command("renders", inp))
    else:
        _missing(sec, "the animation of the clouds developing (renders/clouds_animation.gif)", "renders", inp)


def _figure1(inp: Inputs, sec: Section, env: dict | None) -> None:
    combined, _ = inp.render("figure1")
    if combined is not None:
        _render_blocks(inp, sec, [("figure1", "smoothing_slab scene seen from the front: (a) kappa = 0, (b) smoothed")])
        return
    _render_blocks(inp, sec, [
        ("figure1_unsmoothed", "(a) smoothing_slab without temperature smoothing (kappa = 0): particles turn to "
                               "cloud in isolation, no coherent shape"),
        ("figure1_smoothed", "(b) the same with temperature smoothing (eq. 12-17, kappa = 0.1)"),
    ])


def _figure3(inp: Inputs, sec: Section, env: dict | None) -> None:
    _render_blocks(inp, sec, [
        ("figure3_shape_energy", "shape energy E = k_p (1 - exp(-k_c w)) (eq. 20) of an adaptive run beside the "
                                 "cloud density w: E marks thin cloud edges as split candidates where w alone is small"),
    ])


register(Study("renders", order=60, run=lambda ctx, scene: run_renders(ctx, scene),
                sections=("renders", "figure1", "figure3"),
                report=(ReportSection("renders", "Cloud renders", _renders, 90, "Renders"),
                        ReportSection("figure1", "Figure 1: temperature smoothing", _figure1, 100, "Fig. 1"),
                        ReportSection("figure3", "Figure 3: shape energy", _figure3, 110, "Fig. 3"),),
                produces={"renders": "cloudpbf demo --out {out}"},
                outputs=tuple(f"renders/{name}" for name in RENDERS),
                scale={"slab_particles": {"smoke": 2000, "cpu": 25_000, "gpu": None}}))     # Figure 1 slab
