"""Assemble the HTML report of an output directory from the sections the studies declare.

``build_report(OUT, catalogue)`` reads only ``OUT/data`` (layout below) and writes ``OUT/index.html``: figures
embedded at screen size (cloudpbf.report.images; a click opens the full-size file beside the page, under
``OUT/data/renders`` or ``OUT/figures``), styles inline, no external URL, so it opens offline.  The first
screen is the verdict cards (cloudpbf.report.glance); the header names every device, commit and scale the
sections' data come from; the environment comes last.  A missing input turns its section (or part of it)
into a visible "not run in this study" note with the command that produces it; nothing is ever filled in.

The sections, verdict cards and the commands that make each input come from the studies, in a
:class:`cloudpbf.report.catalogue.Catalogue` (cloudpbf.studies.page builds it from the study registry; ``cloudpbf report
--out OUT`` runs both); the page adds its own summary (the cards) and environment.

    OUT/data/environment.json        device, backend, commit, date, python, versions, scale
    OUT/data/table1.csv              example,figure,mode,max_particles,<phase>_ms...,total_ms,device,commit
    OUT/data/pbf_scaling.csv         particles,iterations,step_ms,neighbors_ms,solver_ms,device,commit
    OUT/data/adaptive_cost.csv       scene,spacing_m,mean_particles,max_particles,splitting_ms,merging_ms,...
    OUT/data/grid_scaling.csv        cells,step_ms,dtype,device,commit
    OUT/data/compare_timeseries.csv  solver,mode,seed,time_s, diagnostics (cloudpbf.statistics)
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

from .catalogue import Catalogue, ReportSection
from .common import Block, Inputs, Provenance, Section, _missing, _table, short_commit
from .glance import summary
from .images import place_images
from cloudpbf_io.files import atomic_write_text

__all__ = ["build_report", "report_sections"]

TEMPLATES = Path(__file__).resolve().parent / "templates"


def report_sections(catalogue: Catalogue) -> tuple[ReportSection, ...]:
    """Every section of the page, in order: the page's own (the summary of verdict cards, the environment) and
    those of the catalogue (the studies')."""
    def _summary(inp: Inputs, sec: Section, env: dict | None) -> None:
        summary(inp, sec, env, catalogue.cards, {r.id: r.title for r in sections})
    own = (ReportSection("summary", "At a glance", _summary, 5, "Verdicts"),
           ReportSection("environment", "Environment", _environment, 10_000))
    sections = tuple(sorted(own + tuple(catalogue.sections), key=lambda r: (r.order, r.id)))
    return sections


# ------------------------------------------------------------------------------------------
# sections
# ------------------------------------------------------------------------------------------
def _environment(inp: Inputs, sec: Section, env: dict | None) -> None:
    if env is None:
        _missing(sec, "environment.json", "environment", inp)
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
    return Provenance.of([str(env["device"])] if env.get("device") else [],
                         [short_commit(env["commit"])] if env.get("commit") else [],
                         [str(env["scale"])] if env.get("scale") else [])


def _lock_check(sec: Section, env: dict) -> None:
    """environment.json's ``lock`` (cloudpbf.environment.lock_check): installed versions against the lock file.
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


def _study_failure(status: dict, section_id: str, study_of_section) -> str:
    study = study_of_section.get(section_id)
    entry = status.get(study) if study else None
    if not isinstance(entry, dict) or entry.get("ok", True):
        return ""
    error = str(entry.get("error", "no error recorded")).strip()
    lines = error.splitlines()
    short = "\n".join(lines[:3]) + (f"\n... ({len(lines) - 3} more lines in data/demo_status.json)"
                                     if len(lines) > 3 else "")
    return f"The {study} study failed in this run: {short}"


def page_provenance(sections, short_titles: dict) -> dict:
    """The header's provenance: every device, commit and scale of the sections' data, each with the sections it
    comes from ({"devices": [(value, [titles])], "commits": ..., "scales": ...}); titles: the navigation's
    (`short_titles`: section id -> label)."""
    found = {"devices": {}, "commits": {}, "scales": {}}
    for sec in sections:
        if sec.id in ("summary", "environment"):
            continue
        title = short_titles.get(sec.id, sec.title)
        for key in found:
            for value in getattr(sec.provenance, key, ()):
                found[key].setdefault(value, []).append(title)
        if sec.provenance and not getattr(sec.provenance, "scales", ()):
            found["scales"].setdefault("not recorded", []).append(title)
    return {key: sorted(values.items(), key=lambda kv: -len(kv[1])) for key, values in found.items()}




# ------------------------------------------------------------------------------------------
# entry point
# ------------------------------------------------------------------------------------------
def build_report(out_dir, catalogue: Catalogue) -> Path:
    """Write OUT/index.html from OUT/data with the sections and cards of `catalogue`; return its path (atomic
    write)."""
    out = Path(out_dir).resolve()
    if not out.exists():
        raise FileNotFoundError(f"report directory {out} does not exist (run a study first, e.g. cloudpbf demo)")
    inp = Inputs(out, catalogue.commands)
    try:
        env = inp.environment()
        env_error = None
    except (json.JSONDecodeError, OSError) as exc:
        env, env_error = None, f"{type(exc).__name__}: {exc}"
    status = inp.study_status()
    sections = []
    declared = report_sections(catalogue)
    short_titles = {r.id: r.label for r in declared}
    for owned in declared:
        sid = owned.id
        sec = Section(sid, owned.title)
        failure = _study_failure(status, sid, catalogue.study_of_section)
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
        sections=sections, env=env or {}, provenance=page_provenance(sections, short_titles), short_titles=short_titles,
        generated=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        scale=(env or {}).get("scale", "unknown"),
        n_missing=sum(s.missing for s in sections),
        failed_studies=sorted(k for k, v in status.items() if isinstance(v, dict) and not v.get("ok", True)),
        Markup=jinja2.utils.markupsafe.Markup,
    )
    target = out / "index.html"
    atomic_write_text(target, page)
    return target
