"""Build the HTML report from a study's output directory.

``build_report(OUT)`` reads only ``OUT/data`` (layout below) and writes ``OUT/index.html``: figures
embedded at screen size (bench.report.images; a click opens the full-size file beside the page, under
``OUT/data/renders`` or ``OUT/figures``), styles inline, no external URL, so it opens offline.  The first
screen is the verdict cards (bench.report.glance); the header names every device, commit and scale the
sections' data come from; the environment comes last.  A missing input turns its section (or part of it)
into a visible "not run in this study" note with the command that produces it; nothing is ever filled in.

The section builders live in modules by subject (common, glance, timing, physics, tradeoffs, pictures);
this module imports them, so ``bench.report.build:<builder>`` names every one of them.

    OUT/data/environment.json        device, backend, commit, date, python, versions, scale
    OUT/data/table1.csv              example,figure,mode,max_particles,<phase>_ms...,total_ms,device,commit
    OUT/data/pbf_scaling.csv         particles,iterations,step_ms,neighbors_ms,solver_ms,device,commit
    OUT/data/adaptive_cost.csv       scene,spacing_m,mean_particles,max_particles,splitting_ms,merging_ms,...
    OUT/data/grid_scaling.csv        cells,step_ms,dtype,device,commit
    OUT/data/compare_timeseries.csv  solver,mode,seed,time_s, diagnostics (bench.statistics)
    OUT/data/compare_profiles.csv    solver,mode,seed,time_s,z,cloud_fraction,temperature,vapor,cloud
    OUT/data/sweep.csv               method,parameter,value,wall_s,error_self,error_other,...
    OUT/data/constant_gravity.csv    case,constant_gravity,cloud_gravity,particles,stable,...,final_cover
    OUT/data/stress.csv              parameter,value,stable,reason,step,particles,max_speed,density_error_mean
    OUT/data/renders/*.png           clouds_particles, clouds_volume, figure1_unsmoothed, figure1_smoothed,
                                     figure3_shape_energy (NAME.unavailable.txt: why a render is missing)
"""
from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import jinja2
import pandas as pd

from .common import (COMMANDS, PAPER_TABLE1, PHASES, Block, Inputs, Section, _missing, _table,  # noqa: F401
                     short_commit, step_time_ratios)
from .glance import _summary  # noqa: F401
from .images import place_images
from .physics import _adaptive, _compare, _compare_and_cycling, _shallow_cumulus, adaptive_tests  # noqa: F401
from .pictures import _figure1, _figure3, _render_blocks, _renders  # noqa: F401
from .timing import _benchmark_history, _peers, _phases, _scaling, _table1, paper_comparison  # noqa: F401
from .tradeoffs import _adaptive_pareto, _stress, _sweep, stress_frame, stress_limits  # noqa: F401

__all__ = ["build_report", "report_sections", "SECTIONS", "COMMANDS", "PAPER_TABLE1"]

TEMPLATES = Path(__file__).resolve().parent / "templates"
SHORT_TITLES = {"summary": "Verdicts", "table1": "Table 1", "phases": "Phases", "benchmark_history": "History",
                "peers": "SPlisHSPlasH", "adaptive": "Adaptive", "compare": "Particles vs grid",
                "shallow_cumulus": "Cumulus", "sweep": "Time vs error", "adaptive_pareto": "Adaptive front",
                "stress": "Stability", "renders": "Renders", "figure1": "Fig. 1", "figure3": "Fig. 3",
                "environment": "Environment", "scaling": "Scaling", "time_to_solution": "Time to solution"}
"""The navigation's label of each section (its title where not listed), short enough for one row at 1366 px."""


def report_sections():
    """Every section of the page, in order: the report's own (environment, the summary) and those the
    studies own (``ReportSection`` in each study's registration, bench.studies.registry)."""
    from bench.studies.registry import ReportSection, report_sections as owned
    own = (ReportSection("summary", "At a glance", f"{__name__}:_summary", 5),
           ReportSection("environment", "Environment", f"{__name__}:_environment", 10_000))
    return tuple(sorted(own + owned(), key=lambda r: (r.order, r.id)))


def __getattr__(name):
    if name == "SECTIONS":   # (id, title) of every section, in order; every id is always present in the page
        return tuple((r.id, r.title) for r in report_sections())
    raise AttributeError(name)


# ------------------------------------------------------------------------------------------
# sections
# ------------------------------------------------------------------------------------------
def _environment(inp: Inputs, sec: Section, env: dict | None) -> None:
    if env is None:
        _missing(sec, "environment.json", "environment", inp.out)
        return
    rows = [(k, v) for k, v in env.items() if k != "versions" and not isinstance(v, (dict, list))]
    sec.add("kv", rows)
    versions = env.get("versions") or {}
    if versions:
        sec.add("table", _table(pd.DataFrame({"package": list(versions), "version": [str(v) for v in versions.values()]})),
                caption="package versions")
    _lock_check(sec, env)
    sec.add("note", "environment.json describes the last study run into this folder"
                    + (f" (scale '{env['scale']}')" if env.get("scale") else "")
                    + "; each section's heading names the device, commit and scale of its own data.", level="info")
    sec.provenance = _provenance_of_environment(env)


def _provenance_of_environment(env: dict):
    from .common import Provenance
    return Provenance.of([str(env["device"])] if env.get("device") else [],
                         [short_commit(env["commit"])] if env.get("commit") else [],
                         [str(env["scale"])] if env.get("scale") else [])


def _lock_check(sec: Section, env: dict) -> None:
    """environment.json's ``lock`` (bench.environment.lock_check): installed versions against the lock file.
    Packages at another version are listed with both versions; locked packages not installed (extras the
    study did not need) are named on one line."""
    if "lock" not in env:
        return
    lock = env["lock"]
    if not isinstance(lock, dict):
        sec.add("note", "No lock file where this ran (an installed package, not a checkout): the versions above "
                        "were not checked against constraints.txt.", level="warn")
        return
    name = lock.get("file", "constraints.txt")
    differs = lock.get("differs") or {}
    other = {k: v for k, v in sorted(differs.items()) if v.get("installed")}
    absent = sorted(k for k, v in differs.items() if not v.get("installed"))
    if not other:
        sec.add("note", f"Every installed package is at the version of the lock file {name}.", level="ok")
    else:
        sec.add("table", _table(pd.DataFrame({"package": list(other),
                                              "locked": [str(v.get("locked")) for v in other.values()],
                                              "installed": [str(v.get("installed")) for v in other.values()]})),
                caption=f"packages at another version than the lock file {name}")
        sec.add("note", f"{len(other)} installed package(s) differ from the lock file {name}: these results were "
                        f"not produced with the locked versions (scripts/setup.sh installs them: "
                        f"pip install -c {name} -e \".[all]\").", level="warn")
    if absent:
        sec.add("text", f"Locked but not installed here: {', '.join(absent)}.")


def study_of_section() -> dict:
    """Which demo study (a key of demo_status.json) writes the inputs of each section (as each study
    declares in bench.studies.registry)."""
    from bench.studies.registry import demo_studies
    return {section: s.name for s in demo_studies() for section in s.sections}


def _study_failure(status: dict, section_id: str) -> str:
    study = study_of_section().get(section_id)
    entry = status.get(study) if study else None
    if not isinstance(entry, dict) or entry.get("ok", True):
        return ""
    error = str(entry.get("error", "no error recorded")).strip()
    lines = error.splitlines()
    short = "\n".join(lines[:3]) + (f"\n... ({len(lines) - 3} more lines in data/demo_status.json)"
                                     if len(lines) > 3 else "")
    return f"The {study} study failed in this run: {short}"


def page_provenance(sections) -> dict:
    """The header's provenance: every device, commit and scale of the sections' data, each with the sections it
    comes from ({"devices": [(value, [titles])], "commits": ..., "scales": ...})."""
    found = {"devices": {}, "commits": {}, "scales": {}}
    for sec in sections:
        if sec.id in ("summary", "environment"):
            continue
        title = SHORT_TITLES.get(sec.id, sec.title)
        for key in found:
            for value in getattr(sec.provenance, key, ()):
                found[key].setdefault(value, []).append(title)
        if sec.provenance and not getattr(sec.provenance, "scales", ()):
            found["scales"].setdefault("not recorded", []).append(title)
    return {key: sorted(values.items(), key=lambda kv: -len(kv[1])) for key, values in found.items()}




# ------------------------------------------------------------------------------------------
# entry point
# ------------------------------------------------------------------------------------------
def build_report(out_dir) -> Path:
    """Write OUT/index.html from OUT/data and return its path (atomic write)."""
    out = Path(out_dir).resolve()
    if not out.exists():
        raise FileNotFoundError(f"report directory {out} does not exist (run a study first, e.g. cloudpbf demo)")
    inp = Inputs(out)
    try:
        env = inp.environment()
        env_error = None
    except (json.JSONDecodeError, OSError) as exc:
        env, env_error = None, f"{type(exc).__name__}: {exc}"
    status = inp.study_status()
    sections = []
    for owned in report_sections():
        sid = owned.id
        sec = Section(sid, owned.title)
        failure = _study_failure(status, sid)
        if failure:
            sec.add("note", failure, level="error")
        try:
            if sid == "environment" and env_error:
                sec.add("note", f"could not read environment.json: {env_error}", level="error")
            else:
                owned.load()(inp, sec, env)
        except Exception as exc:  # a broken input must not hide the other sections
            sec.blocks.append(Block("note", f"could not build this section from data/: "
                                            f"{type(exc).__name__}: {exc}", level="error"))
        sections.append(sec)
    place_images(sections, out)
    template = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                                 undefined=jinja2.StrictUndefined).get_template("report.html.j2")
    page = template.render(
        sections=sections, env=env or {}, provenance=page_provenance(sections), short_titles=SHORT_TITLES,
        generated=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        scale=(env or {}).get("scale", "unknown"),
        n_missing=sum(s.missing for s in sections),
        failed_studies=sorted(k for k, v in status.items() if isinstance(v, dict) and not v.get("ok", True)),
        Markup=jinja2.utils.markupsafe.Markup,
    )
    target = out / "index.html"
    from cloudpbf_io.files import atomic_write_text
    atomic_write_text(target, page)
    return target


def main(argv=None) -> int:
    """``python -m bench.report.build OUT``: build OUT/index.html and print its path."""
    import argparse
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default="reports/latest", help="study output directory (holds data/)")
    args = parser.parse_args(argv)
    print(build_report(args.out))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
