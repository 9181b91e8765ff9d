"""Sections of pictures: the cloud renders, Figure 1 and Figure 3."""
from __future__ import annotations

from . import plots
from .common import Inputs, Section, _command, _missing

def _render_blocks(inp: Inputs, sec: Section, names_captions) -> None:
    for name, caption in names_captions:
        png, reason = inp.render(name)
        if png is not None:
            sec.add("image", plots.png_file_uri(png), caption=caption, source=png)
        elif reason is not None:
            sec.add("note", f"{name}: render unavailable: {reason}", level="warn", command=_command("renders", inp.out))
        else:
            _missing(sec, f"render {name}.png", "renders", inp.out)


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
                command=_command("renders", inp.out))
    else:
        _missing(sec, "the animation of the clouds developing (renders/clouds_animation.gif)", "renders", inp.out)


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


