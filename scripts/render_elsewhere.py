"""The report's renders for a machine without OpenGL: record them where the runs are, draw them where pyvista is.

    python scripts/render_elsewhere.py record --scale cpu --backend cuda --out reports/gpu   # e.g. the GPU machine
    python scripts/render_elsewhere.py draw reports/gpu/data/renders/pending_renders.pkl.gz reports/gpu

``record`` runs the renders study (cloudpbf.studies.renders: its runs from the run cache, or run now) with every
draw call captured instead of drawn: the call's function, its PNG/GIF name and its arguments, the particle
states cut to the fields the renders read (clear particles thinned to 10% in the animation frames, as
cloudpbf.render.compact_particles does), written to OUT/data/renders/pending_renders.pkl.gz.  ``draw`` makes
each captured call with pyvista into OUT/data/renders/ (a note instead of a picture where pyvista cannot
draw, as the study itself does).  The pickle is made and read by this project only: draw only files you
recorded.
"""
from __future__ import annotations

import argparse
import gzip
import pickle
import sys
from pathlib import Path

import numpy as np

KEYS = ("position", "cloud", "level", "kernel_radius", "mass", "temperature")
PENDING = "pending_renders.pkl.gz"


def _cut(value, thin: bool):
    """A state dict cut to KEYS (thinned to the cloudy and 10% of the clear particles when `thin`)."""
    from cloudpbf.render import compact_particles
    if isinstance(value, dict) and "position" in value:
        if thin and "cloud" in value:
            return compact_particles(value, keys=KEYS)
        return {k: np.asarray(value[k]) for k in KEYS if k in value}
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, tuple) and len(v) == 2 for v in value):
        return [(t, _cut(s, True)) for t, s in value]          # animation frames: (time s, state)
    return value


def record(argv) -> int:
    from cloudpbf import render
    from cloudpbf.cli_common import Backend, ScaleName, study_context
    from cloudpbf.studies import renders
    parser = argparse.ArgumentParser(prog="render_elsewhere.py record")
    parser.add_argument("--scale", default="auto", choices=[s.value for s in ScaleName])
    parser.add_argument("--backend", default="auto", choices=[b.value for b in Backend])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--scene", default="growing")
    args = parser.parse_args(argv)
    calls = []

    def capture(draw, out_png, *a, **kw):
        calls.append({"draw": draw.__name__, "name": Path(out_png).name,
                      "args": [_cut(v, False) for v in a], "kwargs": {k: _cut(v, False) for k, v in kw.items()}})
        note = render.note_path(Path(out_png))
        note.parent.mkdir(parents=True, exist_ok=True)
        note.write_text(f"recorded for drawing elsewhere ({PENDING})\n")
        return None

    render.render_or_note = capture
    ctx = study_context(args.out, None, ScaleName(args.scale), Backend(args.backend), None, "inline", False)
    renders.run_renders(ctx, args.scene)
    target = ctx.data / "renders" / PENDING
    target.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(target, "wb") as fh:
        pickle.dump({"calls": calls, "scale": args.scale, "backend": args.backend}, fh)
    print(f"recorded {len(calls)} renders ({', '.join(c['name'] for c in calls)}) to {target}")
    return 0


def draw(argv) -> int:
    from cloudpbf import render
    parser = argparse.ArgumentParser(prog="render_elsewhere.py draw")
    parser.add_argument("pending", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    with gzip.open(args.pending, "rb") as fh:
        data = pickle.load(fh)
    folder = args.out / "data" / "renders"
    folder.mkdir(parents=True, exist_ok=True)
    for call in data["calls"]:
        fn = getattr(render, call["draw"])
        kwargs = dict(call["kwargs"])
        if "out_strip" in kwargs and kwargs["out_strip"] is not None:
            kwargs["out_strip"] = folder / Path(kwargs["out_strip"]).name
        made = render.render_or_note(fn, folder / call["name"], *call["args"], **kwargs)
        print(f"{call['name']}: {'written' if made else 'unavailable (note written)'}")
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("record", "draw"):
        print(__doc__)
        return 2
    return record(argv[1:]) if argv[0] == "record" else draw(argv[1:])


if __name__ == "__main__":
    raise SystemExit(main())
