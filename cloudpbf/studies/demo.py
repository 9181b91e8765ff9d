"""The main job: every study at a scale that fits the machine, then the HTML report.

The studies are those of cloudpbf.studies.registry, in their declared order: environment, the timing
studies in this process (Table 1, scaling), then compare, sweep and stress on the dask cluster, then
the renders, then the report.  A study that fails does not stop the
others: its error goes to OUT/data/demo_status.json and the report shows that section as not run.
Everything comes from the run cache, so a second demo only rebuilds the CSVs and the report.
"""
from __future__ import annotations

import time
import traceback
from pathlib import Path

from cloudpbf import runs
from cloudpbf import environment
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.page import build_report
from cloudpbf.studies.registry import demo_studies



def study_names() -> tuple[str, ...]:
    """The demo's studies, in order."""
    return tuple(s.name for s in demo_studies())


def run_demo(ctx: StudyContext, scene_name: str = "growing",
             only: tuple[str, ...] | None = None) -> tuple[Path | None, dict]:
    """Run the studies in `only` (all by default) and build the report.

    Returns (index.html or None when the report could not be built, {study: status})."""
    names = study_names()
    only = names if only is None else only
    unknown = [s for s in only if s not in names]
    if unknown:
        raise ValueError(f"unknown study {unknown[0]!r}: allowed {', '.join(names)}")
    environment.write_environment(ctx.out, ctx.scale.environment_label, ctx.particle_backend())  # also when called without the CLI
    status = {}
    for study in demo_studies():
        name = study.name
        if name not in only:
            continue
        ctx.say(f"== {name} ({ctx.scale.name} scale)")
        t0 = time.perf_counter()
        try:
            study.run(ctx, scene_name)
            status[name] = {"ok": True, "seconds": round(time.perf_counter() - t0, 1)}
        except Exception as exc:  # keep going: the report shows what is missing and why
            status[name] = {"ok": False, "seconds": round(time.perf_counter() - t0, 1),
                            "error": f"{type(exc).__name__}: {exc}"}
            ctx.say(f"{name} failed: {type(exc).__name__}: {exc}")
            if not ctx.quiet:
                traceback.print_exc()
        runs.atomic_write_json(ctx.data / "demo_status.json", {"scale": ctx.scale.name, "studies": status})
    ctx.close()
    ctx.say("== report")
    try:
        index = build_report(ctx.out)
    except Exception as exc:
        status["report"] = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        runs.atomic_write_json(ctx.data / "demo_status.json", {"scale": ctx.scale.name, "studies": status})
        ctx.say(f"report failed: {type(exc).__name__}: {exc}")
        return None, status
    return index, status
