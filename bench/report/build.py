"""Build the self-contained HTML report from a study's output directory.

``build_report(OUT)`` reads only ``OUT/data`` (layout below) and writes
``OUT/index.html``: one file, figures and renders embedded as base64 PNG, styles
inline, no external URL, so it opens offline.  A missing input turns its section
(or part of it) into a visible "not run in this study" note with the command that
produces it; nothing is ever filled in.

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
import math
from dataclasses import dataclass, field
from pathlib import Path

import jinja2
import numpy as np
import pandas as pd

from bench.pareto import pareto_front

from . import plots
from .inference import LEVEL, format_ci, mean_ci, welch

__all__ = ["build_report", "report_sections", "SECTIONS", "COMMANDS", "PAPER_TABLE1"]

PAPER_TABLE1 = Path(__file__).resolve().parent.parent / "data" / "paper_table1.csv"
TEMPLATES = Path(__file__).resolve().parent / "templates"
PHASES = plots.PHASES


def report_sections():
    """Every section of the page, in order: the report's own (environment, the summary) and those the
    studies own (``ReportSection`` in each study's registration, bench.studies.registry)."""
    from bench.studies.registry import ReportSection, report_sections as owned
    own = (ReportSection("environment", "Environment", f"{__name__}:_environment", 0),
           ReportSection("summary", "At a glance", f"{__name__}:_summary", 5))
    return tuple(sorted(own + owned(), key=lambda r: (r.order, r.id)))


def __getattr__(name):
    if name == "SECTIONS":   # (id, title) of every section, in order; every id is always present in the page
        return tuple((r.id, r.title) for r in report_sections())
    raise AttributeError(name)


COMMANDS = {
    "environment": "cloudpbf demo --out {out}",
    "table1": "cloudpbf table1 --out {out}",
    "pbf_scaling": "cloudpbf scaling --out {out}",
    "grid_scaling": "cloudpbf grid-scaling --sizes 32,64,128 --out {out}/data/grid_scaling.csv",
    "adaptive_cost": "cloudpbf adaptive-cost --spacing 45 --out {out}/data/adaptive_cost.csv",
    "constant_gravity": "cloudpbf constant-gravity --out {out}/data/constant_gravity.csv",
    "compare": "cloudpbf compare growing --out {out}",
    "shallow_cumulus": "cloudpbf shallow-cumulus --out {out}",
    "sweep": "cloudpbf sweep --out {out}",
    "adaptive_pareto": "cloudpbf adaptive-pareto --scene growing --out {out}",
    "stress": "cloudpbf stress --out {out}",
    "renders": "cloudpbf demo --out {out}",
    "benchmark_history": "cloudpbf benchmark-history --out {out}",
    "peers": "cloudpbf peers --out {out}/data/cpu_peer.csv",
}
"""The command that produces each input (shown when it is missing)."""


# ------------------------------------------------------------------------------------------
# page model
# ------------------------------------------------------------------------------------------
@dataclass
class Block:
    kind: str                  # "image", "table", "note", "text", "kv"
    content: object = None     # data URI, HTML string, text, or [(key, value)]
    caption: str = ""
    level: str = "info"        # notes: "missing", "warn", "error", "info", "ok"
    command: str = ""          # notes about missing inputs: the command that makes them


@dataclass
class Section:
    id: str
    title: str
    blocks: list = field(default_factory=list)
    provenance: str = ""

    def add(self, kind, content=None, **kw):
        self.blocks.append(Block(kind, content, **kw))

    @property
    def missing(self) -> bool:
        """No data shown: only notes (missing inputs, failures)."""
        return bool(self.blocks) and all(b.kind == "note" and b.level in ("missing", "error") for b in self.blocks)


class Inputs:
    """Reads OUT/data: CSVs, environment.json and renders."""

    def __init__(self, out_dir: Path):
        self.out = Path(out_dir)
        self.data = self.out / "data"
        self.renders = self.data / "renders"
        self._cache: dict[str, tuple[pd.DataFrame | None, Path | None]] = {}

    def csv(self, name: str) -> tuple[pd.DataFrame | None, Path | None]:
        if name not in self._cache:
            found = self.data / f"{name}.csv"
            if not found.is_file():
                self._cache[name] = (None, None)
            else:
                df = pd.read_csv(found)
                self._cache[name] = (df if len(df) else None, found)
        return self._cache[name]

    def study_status(self) -> dict:
        """study name -> {"ok", "error", "seconds"} from OUT/data/demo_status.json (written by cloudpbf demo)."""
        path = self.data / "demo_status.json"
        if not path.is_file():
            return {}
        try:
            return dict(json.loads(path.read_text()).get("studies", {}))
        except (json.JSONDecodeError, OSError, AttributeError):
            return {}

    def environment(self) -> dict | None:
        path = self.data / "environment.json"
        if not path.is_file():
            return None
        return json.loads(path.read_text())

    def render(self, name: str, suffix: str = ".png") -> tuple[Path | None, str | None]:
        """(image path, None) if rendered, (None, reason) if a note says why not, else (None, None)."""
        png = self.renders / f"{name}{suffix}"
        if png.is_file() and png.stat().st_size > 0:
            return png, None
        note = self.renders / f"{name}.unavailable.txt"
        if note.is_file():
            return None, note.read_text().strip() or "no reason recorded"
        return None, None


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------
def _shown_path(path: Path) -> str:
    """A path as the report prints it: relative to the working directory when inside it, else its name
    (the report never shows a machine's absolute path)."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve())) or "."
    except ValueError:
        return path.name


def _command(key: str, out: Path) -> str:
    return COMMANDS[key].format(out=_shown_path(out))


def _missing(section: Section, what: str, key: str, out: Path) -> None:
    section.add("note", f"{what}: not run in this study.", level="missing", command=_command(key, out))


HIDDEN_COLUMNS = ("run_dir",)
"""Columns never shown in tables (machine-local paths)."""

MAX_CELL = 48
"""Longest text shown in a table cell; longer cells (lists of particle ids, error messages) are cut."""


def shorten(text: str, limit: int = MAX_CELL) -> str:
    """A cell's text cut to `limit` characters; a list of ids keeps its first few and says how many."""
    text = " ".join(str(text).split())
    if len(text) <= limit:
        return text
    words = text.split(" ")
    if len(words) > 3 and all(w.lstrip("-").isdigit() for w in words):
        return f"{len(words)} ids: {' '.join(words[:3])} …"
    return text[:limit - 1].rstrip() + "…"


def _table(df: pd.DataFrame, float_format: str = "{:.4g}", index: bool = False,
           labels: dict[str, str] | None = None) -> str:
    """HTML of `df` (HIDDEN_COLUMNS dropped, floats in `float_format`, long text cut); `labels` maps a CSV
    column name to its header (readable, with units); other columns keep their names."""
    df = df.drop(columns=[c for c in HIDDEN_COLUMNS if c in df.columns])

    def fmt(v):
        if isinstance(v, (float, np.floating)):
            if math.isnan(v):
                return "–"
            return float_format.format(v)
        if isinstance(v, str):
            return shorten(v)
        return v
    shown = df.copy()
    for col in shown.columns:
        shown[col] = shown[col].map(fmt)
    if labels:
        shown = shown.rename(columns=labels)
    return shown.to_html(index=index, escape=True, border=0, classes="data", na_rep="–")


def _provenance(*frames: pd.DataFrame | None, env: dict | None = None) -> str:
    """'device: ...; commit: ...' of the data shown (environment.json's when the CSVs lack them)."""
    if all(df is None for df in frames):
        return ""
    parts = []
    for key in ("device", "commit"):
        values = []
        for df in frames:
            if df is not None and key in df.columns:
                values += [str(v) for v in df[key].dropna().unique()]
        if not values and env and env.get(key):
            values = [str(env[key])]
        if values:
            parts.append(f"{key}: {', '.join(dict.fromkeys(values))}")
    return "; ".join(parts)


def _scale_of(env: dict | None, df: pd.DataFrame | None = None) -> str:
    if df is not None and "scale" in df.columns and df["scale"].notna().any():
        return str(df["scale"].dropna().iloc[0])
    return str((env or {}).get("scale", "unknown"))


def _mean_sd(values: pd.Series) -> str:
    """Mean over seeds with its 95% t-interval: 'mean [lo, hi]' (bench.report.inference)."""
    if values is None:
        return "–"
    return format_ci(values, digits=4)


def _numeric(df: pd.DataFrame, col: str) -> pd.Series:
    return pd.to_numeric(df[col], errors="coerce") if col in df.columns else pd.Series(np.nan, index=df.index)


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
    scale = env.get("scale")
    if scale and scale != "gpu":
        sec.add("note", f"Scale '{scale}': a CPU run at scaled-down particle counts and step counts. Timings "
                        "show the harness works and how costs divide; they are not comparable with the paper's GPU "
                        "numbers (see reports/gpu for the GPU reference results).", level="warn")


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


def _summary_row(rows: list, question: str, answer: str, section: str, missing_key: str | None = None,
                 out: Path | None = None) -> None:
    rows.append((question, answer, section, _command(missing_key, out) if missing_key and out else ""))


def _summary_table1(inp: Inputs, env: dict | None) -> str | None:
    measured, _ = inp.csv("table1")
    if measured is None:
        return None
    measured = measured.copy()
    measured["total_ms"] = _measured_total(measured)
    paper = _paper_table().set_index(["example", "mode"])["total_ms"]
    parts = []
    for r in measured.itertuples():
        p = paper.get((r.example, r.mode), math.nan)
        ratio = (p / r.total_ms) if r.total_ms and np.isfinite(p) else math.nan
        variant = _variant(r._asdict())
        parts.append(f"{r.example} {r.mode}{f' ({variant})' if variant else ''}: {r.total_ms:.3g} ms (paper {p:.3g} ms"
                     + (f", {ratio:.3g}x faster" if ratio >= 1 else f", {1 / ratio:.3g}x slower" if ratio > 0 else "")
                     + ")")
    scale = _scale_of(env, measured)
    note = "" if scale == "gpu" else f" [scale '{scale}': scaled-down CPU runs, not comparable with the paper]"
    return "; ".join(parts) + note


def _summary_adaptive(inp: Inputs) -> str | None:
    """The adaptive speed-up at equal error, always beside the error it holds at."""
    parts = []
    for suffix in ("", "_cumulus"):
        path = inp.data / f"adaptive_verdict{suffix}.json"
        if not path.is_file():
            continue
        v = json.loads(path.read_text())
        best = v.get("best") or {}
        speed = best.get("speedup_at_equal_error")
        if speed is None or not np.isfinite(speed):
            scene, text = v.get("scene", suffix.strip("_") or "growing"), str(v.get("verdict", "no verdict"))
            parts.append(text if text.startswith(scene) else f"{scene}: {text}")
            continue
        word = f"{speed:.2f}x faster" if speed >= 1 else f"{1 / speed:.2f}x slower"
        parts.append(f"{v.get('scene', 'growing')}: best adaptive variant ({best.get('name', '?')}) {word} than "
                     f"uniform particles at equal error {best.get('error', math.nan):.3g} "
                     f"(seed spread {best.get('error_seed_spread', math.nan):.2g}, seed-noise floor "
                     f"{v.get('noise_floor') or math.nan:.2g}): {best.get('ms_per_step', math.nan):.3g} against "
                     f"{best.get('uniform_ms_at_equal_error', math.nan):.3g} ms per step"
                     + (f" (stable in {best['stable_seeds']} of {best['seeds']} seeds)"
                        if best.get("stable_seeds") is not None and best.get("seeds") else "")
                     + (", 5-95% over resampled seeds {:.2f}-{:.2f}x".format(*best["speedup_interval"])
                        if best.get("speedup_interval") else ""))
    if parts:
        return "; ".join(parts)
    path = inp.data / "sweep_verdict.json"
    if path.is_file():
        v = json.loads(path.read_text())
        comps = v.get("comparisons") or []
        if comps:
            errs = [c["error"] for c in comps]
            return (f"{v.get('verdict', '')} at errors {min(errs):.3g}..{max(errs):.3g} "
                    f"({v.get('metric', 'error against the finest run')})")
        return f"sweep: {v.get('verdict', 'no verdict')}"
    return None


def _summary_agreement(inp: Inputs) -> str | None:
    ts, _ = inp.csv("compare_timeseries")
    if ts is None or "solver" not in ts.columns or not {"particles", "grid"} <= set(ts["solver"]):
        return None
    parts = []
    last = ts.sort_values("time_s").groupby(["solver", "mode", "seed"]).tail(1)
    grid = last[last["solver"] == "grid"]["cloud_cover"]
    for mode in ("non-adaptive", "adaptive"):
        part = last[(last["solver"] == "particles") & (last["mode"] == mode)]["cloud_cover"]
        if not len(part):
            continue
        _, p = welch(part, grid)
        parts.append(f"final cloud cover, particles {mode} {format_ci(part)} against grid {format_ci(grid)}"
                     + ("" if math.isnan(p) else f" (Welch p = {p:.2g})"))
    return "; ".join(parts) + f" (mean [{100 * LEVEL:g}% CI] over seeds)" if parts else None


def _summary_stability(inp: Inputs) -> str | None:
    df, _ = inp.csv("stress")
    if df is None:
        return None
    return stress_limits(df) or None


def _summary(inp: Inputs, sec: Section, env: dict | None) -> None:
    """The answers a reader comes for, one line each, with the section that holds the evidence."""
    rows = [("Step time against the paper's Table 1 (total ms per step)", _summary_table1(inp, env), "table1",
             "table1"),
            ("Adaptive speed-up at equal error (with that error)", _summary_adaptive(inp), "adaptive_pareto",
             "adaptive_pareto"),
            ("Particles against the grid baseline", _summary_agreement(inp), "compare", "compare"),
            ("Stability limit", _summary_stability(inp), "stress", "stress")]
    import html
    titles = dict((r.id, r.title) for r in report_sections())
    body = []
    for question, answer, target, key in rows:
        if answer is None:
            answer_html = (f'<span class="na">not run in this study</span> (<code>'
                           f"{html.escape(_command(key, inp.out))}</code>)")
        else:
            answer_html = html.escape(answer)
        body.append(f"<tr><th>{html.escape(question)}</th><td>{answer_html}</td>"
                    f'<td><a href="#{target}">{html.escape(titles.get(target, target))}</a></td></tr>')
    sec.add("table", '<table class="summary"><tr><th>question</th><th>answer (measured)</th><th>details</th></tr>'
            + "".join(body) + "</table>", caption=(
                "At a glance; the wide tables and figures follow in the sections named on the right."))
    sec.provenance = _provenance(inp.csv("table1")[0], inp.csv("compare_timeseries")[0], inp.csv("stress")[0],
                                 env=env)


def _paper_table() -> pd.DataFrame:
    paper = pd.read_csv(PAPER_TABLE1)
    phase_cols = [f"{p}_ms" for p in PHASES if f"{p}_ms" in paper.columns]
    paper["total_ms"] = paper[phase_cols].sum(axis=1, min_count=1)
    return paper


def _variant(r) -> str:
    """A Table 1 row's variant name ('' on the paper's rows; older CSVs have no column)."""
    v = r.get("variant") if hasattr(r, "get") else getattr(r, "variant", "")
    return v if isinstance(v, str) else ""


def _non_adaptive_totals(df: pd.DataFrame) -> dict:
    """example -> total ms of its non-adaptive row."""
    rows = df[df["mode"] == "non-adaptive"]
    return dict(zip(rows["example"], pd.to_numeric(rows["total_ms"], errors="coerce")))


def _adaptive_speedups(df: pd.DataFrame) -> dict:
    """example -> non-adaptive total / adaptive total, over the paper's rows (no variant)."""
    if "variant" in df.columns:
        df = df[df["variant"].fillna("").astype(str) == ""]
    non_adaptive = _non_adaptive_totals(df)
    out = {}
    for r in df[df["mode"] == "adaptive"].itertuples():
        total = pd.to_numeric(r.total_ms, errors="coerce")
        if r.example in non_adaptive and total > 0:
            out[r.example] = non_adaptive[r.example] / total
    return dict(sorted(out.items()))


def _measured_total(df: pd.DataFrame) -> pd.Series:
    if "total_ms" in df.columns and df["total_ms"].notna().all():
        return pd.to_numeric(df["total_ms"], errors="coerce")
    cols = [f"{p}_ms" for p in PHASES if f"{p}_ms" in df.columns]
    return df[cols].apply(pd.to_numeric, errors="coerce").sum(axis=1, min_count=1)


def _table1(inp: Inputs, sec: Section, env: dict | None) -> None:
    measured, _ = inp.csv("table1")
    if measured is None:
        _missing(sec, "table1.csv", "table1", inp.out)
        return
    measured = measured.copy()
    measured["total_ms"] = _measured_total(measured)
    paper = _paper_table()
    scale = _scale_of(env, measured)
    merged = measured.merge(paper, on=["example", "mode"], how="left", suffixes=("", "_paper"))
    non_adaptive = _non_adaptive_totals(measured)
    speed_p = _adaptive_speedups(paper)
    rows = []
    for r in merged.itertuples(index=False):
        r = r._asdict()
        variant = _variant(r)
        row = {"example": r["example"], "figure": r.get("figure") if isinstance(r.get("figure"), str)
               else r.get("figure_paper"), "mode": f"{r['mode']} ({variant})" if variant else r["mode"],
               "particles": r.get("max_particles"), "particles (paper)": r.get("max_particles_paper")}
        for p in PHASES:
            m, pp = r.get(f"{p}_ms"), r.get(f"{p}_ms_paper")
            row[f"{p} ms"] = m
            row[f"{p} ms (paper)"] = pp
        row["total ms"] = r["total_ms"]
        row["total ms (paper)"] = r.get("total_ms_paper")
        total_p = r.get("total_ms_paper")
        row["paper / measured"] = (total_p / r["total_ms"]) if total_p and r["total_ms"] else math.nan
        if r["mode"] == "adaptive":   # a paper row or the best variant's: against the example's non-adaptive row
            row["adaptive speedup"] = (non_adaptive.get(r["example"], math.nan) / r["total_ms"]
                                       if r["total_ms"] and r["total_ms"] > 0 else math.nan)
            row["adaptive speedup (paper)"] = speed_p.get(r["example"], math.nan)
        else:
            row["adaptive speedup"] = math.nan
            row["adaptive speedup (paper)"] = math.nan
        rows.append(row)
    table = pd.DataFrame(rows)
    table = table.loc[:, [c for c in table.columns if not table[c].isna().all() or "paper" in c or c == "total ms"]]
    first = ["example", "mode", "total ms", "total ms (paper)", "paper / measured", "adaptive speedup",
             "adaptive speedup (paper)"]
    table = table[[c for c in first if c in table.columns] + [c for c in table.columns if c not in first]]
    sec.add("table", _table(table), caption=(
        "Milliseconds per step per phase, measured beside the paper's Table 1 (GeForce GTX 780 Ti). "
        "'adaptive speedup' = non-adaptive total / adaptive total of the same example; "
        "'paper / measured' = the paper's total / ours (> 1: faster than the paper). A row 'adaptive (name)' is "
        "the adaptive study's best variant (cloudpbf adaptive-pareto), timed beside the paper's rows."))
    if scale != "gpu":
        sec.add("note", f"Scale '{scale}': CPU run, scaled down (particle counts in the 'particles' column, not the "
                        "paper's). Compare the adaptive speedup, not absolute milliseconds.", level="warn")
    missing_rows = set(paper["example"] + "/" + paper["mode"]) - set(measured["example"] + "/" + measured["mode"])
    if missing_rows:
        sec.add("note", "rows not measured in this study: " + ", ".join(sorted(missing_rows)), level="missing",
                command=_command("table1", inp.out))
    sec.provenance = _provenance(measured, env=env)


def _phases(inp: Inputs, sec: Section, env: dict | None) -> None:
    measured, _ = inp.csv("table1")
    if measured is None:
        _missing(sec, "table1.csv (per-phase timings)", "table1", inp.out)
        return
    paper = _paper_table()
    sec.add("image", plots.phase_bars(measured, paper), caption=(
        "Stacked ms per step of the Table 1 phases (pbf includes neighbour search and constraint iterations). "
        "Phases a run does not have (splitting and merging without adaptivity) are absent, not zero."))
    shares = measured[["example", "mode"]].copy()
    total = _measured_total(measured)
    for p in PHASES:
        if f"{p}_ms" in measured.columns and measured[f"{p}_ms"].notna().any():
            shares[f"{p} %"] = 100.0 * pd.to_numeric(measured[f"{p}_ms"], errors="coerce") / total
    sec.add("table", _table(shares, "{:.1f}"), caption="share of each phase in the measured step time (%)")
    cost, cost_path = inp.csv("adaptive_cost")
    if cost is None:
        _missing(sec, "adaptive_cost.csv (splitting and merging at ~500k adaptive particles, GPU)", "adaptive_cost",
                 inp.out)
    else:
        cols = [c for c in ("scene", "spacing_m", "mean_particles", "max_particles", "splitting_ms", "merging_ms",
                            "merge_passes_ms", "compaction_ms", "pbf_ms", "split_target_ms", "merge_target_ms",
                            "meets_targets", "device", "commit") if c in cost.columns]
        sec.add("table", _table(cost[cols]), caption=(
            f"Splitting and merging at the size of the targets, from {cost_path.name}: ms per step over the whole "
            "run (merge_passes and compaction are parts of merging; pbf is the same run's constraint solve). "
            "meets_targets is left empty off the GPU or below 400k particles."))
    sec.provenance = _provenance(measured, env=env)


def _scaling(inp: Inputs, sec: Section, env: dict | None) -> None:
    pbf, pbf_path = inp.csv("pbf_scaling")
    grid, grid_path = inp.csv("grid_scaling")
    if pbf is None:
        _missing(sec, "pbf_scaling.csv (particle solver step time against particle count)", "pbf_scaling", inp.out)
    else:
        sec.add("image", plots.pbf_scaling_plot(pbf), caption=f"PBF step (log-log) from {pbf_path.name}")
        extra = pbf.copy()
        if "step_ms" in extra and "particles" in extra:
            extra["ns per particle"] = 1e6 * extra["step_ms"] / extra["particles"]
        sec.add("table", _table(extra))
    if grid is None:
        _missing(sec, "grid_scaling.csv (grid baseline step time against cell count)", "grid_scaling", inp.out)
    else:
        sec.add("image", plots.grid_scaling_plot(grid), caption=f"grid baseline step (log-log) from {grid_path.name}")
        extra = grid.copy()
        if "step_ms" in extra and "cells" in extra:
            extra["ns per cell"] = 1e6 * extra["step_ms"] / extra["cells"]
        sec.add("table", _table(extra))
    sec.provenance = _provenance(pbf, grid, env=env)


def _benchmark_history(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, path = inp.csv("benchmark_history")
    if df is None:
        _missing(sec, "benchmark_history.csv (the solver's step across commits, from the asv results in "
                      "benchmarks/results)", "benchmark_history", inp.out)
        return
    sec.add("text", "Each point is one commit's median of asv samples (docs/benchmarks.md), error bars its 99% "
                    "interval. A change is flagged when the ratio to the machine's previous recorded commit passes "
                    "the history's factor and the two intervals do not overlap.")
    for machine in sorted(df["machine"].unique()):
        sec.add("image", plots.benchmark_history_plot(df, machine), caption=f"{machine}, from {path.name}")
    changed = df[df["change"].fillna("") != ""]
    if len(changed):
        shown = changed[["machine", "commit", "backend", "scene", "particles", "time_ms", "ratio", "change"]].rename(
            columns={"time_ms": "ms per step", "ratio": "ratio to the previous commit"})
        sec.add("table", _table(shown, float_format="{:.3g}"), caption="changes between consecutive recorded commits")
    else:
        sec.add("note", "no change beyond the factor between consecutive recorded commits", level="ok")


def _peers(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, path = inp.csv("cpu_peer")
    if df is None:
        _missing(sec, "cpu_peer.csv (SPlisHSPlasH's PBF dam break against cloudpbf's: cloudpbf peers)", "peers", inp.out)
        return
    sec.add("text", "SPlisHSPlasH's DamBreakModel with PBF (4 iterations, dt 0.002 s) and cloudpbf's dam break on the "
                    "same box, water cube and spacing, timed alternately in one run; per run the faster repeat of each "
                    "and cloudpbf's ratio to SPlisHSPlasH of the faster repeats and of the means. A shared host's "
                    "speed drifts between runs: compare within a row. Fluid particle-steps per second: more is "
                    "faster.")
    from bench.studies.peers import best_rates
    wide = best_rates(df)
    wide["threads"] = wide["threads"].map(lambda t: "GPU" if int(t) == 0 else str(int(t)))
    commits = ", ".join(sorted(df["commit"].astype(str).unique()))
    sec.add("table", _table(wide, float_format="{:.3g}"), caption=f"from {path.name}, commit {commits}")


PARTICLE_COUNT_COLUMNS = ("n_particles", "particles", "max_particles")


def _adaptive(inp: Inputs, sec: Section, env: dict | None) -> None:
    ts, _ = inp.csv("compare_timeseries")
    table1, _ = inp.csv("table1")
    particles = None
    if ts is not None and "solver" in ts.columns:
        particles = ts[ts["solver"] == "particles"]
        if particles.empty or particles["mode"].nunique() < 2:
            particles = None
    if particles is None and table1 is None:
        _missing(sec, "adaptive and non-adaptive particle runs (compare_timeseries.csv, table1.csv)", "compare",
                 inp.out)
        return
    if table1 is not None:
        measured = table1.copy()
        measured["total_ms"] = _measured_total(measured)
        speed = _adaptive_speedups(measured)
        paper = _adaptive_speedups(_paper_table())
        counts = measured.pivot_table(index="example", columns="mode", values="max_particles", aggfunc="max")
        rows = []
        for example in sorted(set(speed) | set(counts.index)):
            rows.append({"example": example,
                         "particles non-adaptive": counts.get("non-adaptive", pd.Series()).get(example, math.nan),
                         "particles adaptive": counts.get("adaptive", pd.Series()).get(example, math.nan),
                         "speedup (measured)": speed.get(example, math.nan),
                         "speedup (paper)": paper.get(example, math.nan)})
        sec.add("table", _table(pd.DataFrame(rows)), caption=(
            "Step time: non-adaptive total / adaptive total (Table 1 rows); the paper reports "
            + ", ".join(f"{k} {v:.2f}x" for k, v in paper.items()) + "."))
    else:
        _missing(sec, "table1.csv (adaptive speedup)", "table1", inp.out)
    if particles is not None:
        count_col = next((c for c in PARTICLE_COUNT_COLUMNS if c in particles.columns), None)
        panels = ([(count_col, "particles (count)")] if count_col else []) + [
            ("cloud_cover", "cloud cover (fraction of columns)"), ("lwp_mean", "mean liquid water path (kg/m$^2$)")]
        shown = particles
        if "total_water" in particles.columns:
            shown = particles.assign(total_water_change=plots.relative_change(particles, "total_water"))
            panels.append(("total_water_change", "total water (vapor + cloud), relative change since t = 0"))
        sec.add("image", plots.timeseries_plot(shown, panels), caption=(
            "Particle runs, non-adaptive and adaptive: mean over seeds, band = min..max over seeds. Total water "
            "is shown as its relative change from each run's start (conserved without sources: it stays near 0)."))
        rows = []
        for mode, g in particles.groupby("mode", sort=True):
            last = g.sort_values("time_s").groupby("seed").tail(1)
            onset = [_onset(gs) for _, gs in g.groupby("seed")]
            row = {"mode": mode, "seeds": g["seed"].nunique(), "onset s": _mean_sd(pd.Series(onset)),
                   "final cover": _mean_sd(last["cloud_cover"]), "final LWP kg/m2": _mean_sd(last.get("lwp_mean"))}
            if count_col:
                row["final particles"] = _mean_sd(last[count_col])
                row["max particles"] = f"{pd.to_numeric(g[count_col]).max():.0f}"
            rows.append(row)
        sec.add("table", _table(pd.DataFrame(rows)), caption="mean [95% confidence interval, t over seeds]")
        tests = adaptive_tests(particles, inp.csv("compare_runs")[0])
        if tests is not None:
            sec.add("table", _table(tests), caption=(
                "Adaptive against non-adaptive, seed by seed: Welch's t-test (unequal variances, scipy.stats."
                "ttest_ind) of each quantity; p < 0.05: the difference is larger than the seed spread explains. "
                "Wall time is the time inside step() of each run (compare_runs.csv)."))
    else:
        _missing(sec, "compare_timeseries.csv with both particle modes (cloud statistics over time)", "compare",
                 inp.out)
    sec.provenance = _provenance(table1, ts, env=env)


def _per_seed(particles: pd.DataFrame, runs_df: pd.DataFrame | None, mode: str) -> dict:
    """quantity label -> per-seed values of one particle mode (the last time of each seed's series)."""
    g = particles[particles["mode"] == mode]
    last = g.sort_values("time_s").groupby("seed").tail(1)
    out = {"onset time (s)": [_onset(gs) for _, gs in g.groupby("seed")],
           "final cloud cover (fraction)": last["cloud_cover"]}
    if "lwp_mean" in last.columns:
        out["final mean LWP (kg/m2)"] = last["lwp_mean"]
    if runs_df is not None and {"solver", "mode", "step_wall_s"} <= set(runs_df.columns):
        r = runs_df[(runs_df["solver"] == "particles") & (runs_df["mode"] == mode)]
        out["wall time in step() (s)"] = r["step_wall_s"]
    return out


def adaptive_tests(particles: pd.DataFrame, runs_df: pd.DataFrame | None = None) -> pd.DataFrame | None:
    """One row per quantity: both modes' mean [95% CI] over seeds, the difference and Welch's p-value;
    None without both modes."""
    if particles is None or not {"non-adaptive", "adaptive"} <= set(particles["mode"]):
        return None
    fixed, adapt = _per_seed(particles, runs_df, "non-adaptive"), _per_seed(particles, runs_df, "adaptive")
    rows = []
    for name in fixed:
        if name not in adapt:
            continue
        a, b = mean_ci(fixed[name]), mean_ci(adapt[name])
        t, p = welch(adapt[name], fixed[name])    # t > 0: adaptive larger
        rows.append({"quantity": name, "non-adaptive": format_ci(a), "adaptive": format_ci(b),
                     "seeds": f"{a.n} / {b.n}", "adaptive - non-adaptive": b.mean - a.mean, "Welch t": t,
                     "p": p, "significant (5%)": "–" if math.isnan(p) else ("yes" if p < 0.05 else "no")})
    return pd.DataFrame(rows) if rows else None


def _onset(g: pd.DataFrame) -> float:
    from bench.statistics import onset_time
    return onset_time(g)


SUMMARY_COLUMNS = (("cloud_cover", "cover"), ("lwp_mean", "LWP kg/m2"), ("cloud_base", "base m"),
                   ("cloud_top", "top m"), ("base_p10", "base p10 m"), ("top_p90", "top p90 m"),
                   ("n_objects", "objects"))


def _compare(inp: Inputs, sec: Section, env: dict | None) -> None:
    ts, _ = inp.csv("compare_timeseries")
    prof, _ = inp.csv("compare_profiles")
    if ts is None and prof is None:
        _missing(sec, "compare_timeseries.csv and compare_profiles.csv", "compare", inp.out)
        return
    if prof is not None:
        sec.add("image", plots.profiles_plot(prof), caption=(
            "Horizontal-mean vertical profiles at the last common time, particles deposited on a grid with the SPH "
            "kernel, the grid baseline on its own grid; both through the same statistics code."))
    else:
        _missing(sec, "compare_profiles.csv", "compare", inp.out)
    if ts is not None:
        panels = list(plots.TIMESERIES_PANELS)
        if "base_p10" in ts.columns and "top_p90" in ts.columns:
            panels += [("base_p10", "cloud base, 10th percentile of columns (m)"),
                       ("top_p90", "cloud top, 90th percentile of columns (m)")]
        sec.add("image", plots.timeseries_plot(ts, panels), caption=(
            "Cloud statistics against time: line = mean over seeds, band = min..max over seeds."))
        budget = [c for c in ("heat_source_total", "heat_latent_total", "heat_adiabatic_total",
                              "heat_smoothing_total", "heat_numerical_total", "mass_centre_height",
                              "kinetic_energy") if c in ts.columns]
        if budget:
            labels = {"heat_source_total": "warming from the ground heating, eq. 5 (K)",
                      "heat_latent_total": "warming from latent heat, eq. 11 (K)",
                      "heat_adiabatic_total": "warming from the adiabatic term, eq. 7 (K)",
                      "heat_smoothing_total": "warming from smoothing, eq. 12-17 (K)",
                      "heat_numerical_total": "warming from the grid's advection scheme (K)",
                      "mass_centre_height": "mass-centre height (m)", "kinetic_energy": "kinetic energy (J)"}
            sec.add("image", plots.timeseries_plot(ts, [(c, labels[c]) for c in budget]), caption=(
                "Heat budget of every run, particles and grid alike (mass-weighted mean warming from each "
                "process, summed from t = 0; they add up to the change of the mean temperature; "
                "docs/validation.md), mass-centre height and kinetic energy: line = mean over seeds, band = "
                "min..max. In a closed, incompressible atmosphere the adiabatic term and the mass centre stay "
                "near zero and smoothing adds no heat; the grid has no smoothing and reports what its "
                "advection creates instead."))
        rows = []
        keys = [k for k in ("solver", "mode") if k in ts.columns]
        for key, g in ts.groupby(keys, sort=True):
            key = key if isinstance(key, tuple) else (key,)
            last = g.sort_values("time_s").groupby("seed").tail(1) if "seed" in g else g.tail(1)
            onset = [_onset(gs) for _, gs in g.groupby("seed")] if "seed" in g else [_onset(g)]
            row = dict(zip(keys, key))
            row["seeds"] = g["seed"].nunique() if "seed" in g else 1
            row["onset s"] = _mean_sd(pd.Series(onset))
            for col, label in SUMMARY_COLUMNS:
                if col in last.columns:
                    row[f"final {label}"] = _mean_sd(last[col])
            rows.append(row)
        sec.add("table", _table(pd.DataFrame(rows)), caption=(
            "At each run's last time; mean [95% confidence interval, t over seeds] (onset: first time with cover > 0; "
            "'–' where no cloud formed)."))
        agreement, _ = inp.csv("particles_vs_grid")
        if agreement is not None and len(agreement):
            sec.add("table", _table(agreement[["metric", "particles", "grid", "rel_diff", "cloudy_from_s",
                                               "cloudy_to_s"]]), caption=(
                "Particles (non-adaptive) against the grid: time means over the cloudy period (both seed-mean covers "
                "above 1%) of the seed-mean cloud base and top (m), cover and mean LWP (kg/m2), and each solver's "
                "mixed-layer LCL (m: the lifting condensation level of the mean air below half its cloud base); "
                "rel_diff = (particles - grid) / grid."))
        if "seed" in ts.columns and ts.groupby(keys)["seed"].nunique().min() < 5:
            sec.add("note", "fewer than 5 seeds in at least one group: the spread is not well sampled.", level="warn")
    else:
        _missing(sec, "compare_timeseries.csv", "compare", inp.out)
    sec.provenance = _provenance(ts, prof, env=env)


CYCLING_PANELS = (("cloud_cover", "cloud cover (fraction of columns)"), ("lwp_mean", "mean liquid water path (kg/m2)"),
                  ("cloud_top", "cloud top (m)"), ("rain_total", "rain removed since t = 0 (kg, eq. C3)"),
                  ("water_relaxation_total", "vapor added by the relaxation since t = 0 (kg, eq. C2)"))


def _cycling(inp: Inputs, sec: Section) -> None:
    """Paper example 2 (docs/cycling.md), shown in the compare section when `cloudpbf cycling` ran."""
    ts, _ = inp.csv("cycling_timeseries")
    cycles, path = inp.csv("cycling_cycles")
    if ts is None and cycles is None:
        return
    sec.add("text", "Example 2: clouds that disappear and reappear (cloudpbf cycling, docs/cycling.md): "
                    "time-of-day ground heating, relaxation toward the initial profiles and rain.")
    if ts is not None:
        sec.add("image", plots.timeseries_plot(ts, CYCLING_PANELS), caption=(
            "The cycling scene: cover, liquid water path, cloud top and the water budget's sinks and sources "
            "(docs/cycling.md C4: total water = initial + relaxation - rain) against time for the three solvers; "
            "line = mean over seeds, band = min..max over seeds."))
    if cycles is not None:
        rows = []
        for (solver, mode), g in cycles.groupby(["solver", "mode"], sort=True):
            rows.append({"solver": solver, "mode": mode, "seeds": g["seed"].nunique(),
                         "full cycles": _mean_sd(g["cycles"]), "fewest cycles": int(g["cycles"].min()),
                         "peak cover": _mean_sd(g["peak_cover"]), "min cover": _mean_sd(g["min_cover"])})
        sec.add("table", _table(pd.DataFrame(rows)), caption=(
            f"Full cycles per run from {path.name}: after the cover first reaches half its peak, a fall below "
            "20% of the peak followed by a climb back above 50%; mean [95% confidence interval, t over seeds]."))
    budgets, bpath = inp.csv("cycling_budgets")
    if budgets is not None and len(budgets):
        shown = budgets.copy()
        shown["closure"] = shown["closure"].map(lambda x: f"{x:.1e}")
        keep = ["mode", "seed", "cycle", "start_s", "peak_s", "min_s", "end_s", "peak_cover", "rain", "relaxation",
                "d_total_water", "closure", "latent_heat"]
        sec.add("table", _table(shown[[c for c in keep if c in shown.columns]].round(3)), caption=(
            f"The water budget over each full cycle ({bpath.name}, docs/cycling.md C4), kg: rain removed, "
            "vapor added by the relaxation (negative: removed), the change of the solver's own total water, and "
            "closure = (change - (relaxation - rain)) / mean total water; latent heat released, K (eq. 11)."))
    modes, tags = ("non-adaptive", "adaptive", "grid"), ("peak", "min")
    grid = [[inp.render(f"cycling_{mode}_{tag}")[0] for tag in tags] for mode in modes]
    shown = [(mode, row) for mode, row in zip(modes, grid) if any(p is not None for p in row)]
    if shown:
        sec.add("image", plots.image_grid([row for _, row in shown], [mode for mode, _ in shown],
                                          ["first cover peak", "clearest moment after that peak"]), caption=(
            "Example 2 in the style of the paper's Fig. 5c/d: each solver's seed-0 run at its first cover "
            "peak (left) and at the clearest moment that follows (right), side by side "
            "(bench.studies.cycling.cycle_states; the times are those of the water-budget table). Particles "
            "with w > 1e-5 kg/kg are drawn, the grid's cloud water as a volume."))


def _convergence(inp: Inputs, sec: Section) -> None:
    """Both solvers against resolution in the scene's own domain (scripts/probe_convergence.py --out
    convergence.csv; docs/validation.md, "Convergence of both solvers with resolution")."""
    conv, path = inp.csv("convergence")
    if conv is None:
        return
    figure = plots.convergence_plot(conv)
    if figure is None:
        return
    sec.add("image", figure, caption=(
        f"Convergence in the full domain ({path.name}, {_provenance(conv)}): each solver's cloud statistics "
        "(time means over the cloudy period, seed 0) against its resolution, particle spacing or grid cell size "
        "(finer to the right); where the lines approach each other, the solvers converge toward one answer."))


def _compare_and_cycling(inp: Inputs, sec: Section, env: dict | None) -> None:
    _compare(inp, sec, env)
    _convergence(inp, sec)
    _cycling(inp, sec)


def _shallow_cumulus(inp: Inputs, sec: Section, env: dict | None) -> None:
    """The shallow_cumulus study (bench.studies.shallow_cumulus): statistics beside the LES cases, renders."""
    summary, path = inp.csv("shallow_cumulus")
    if summary is None:
        _missing(sec, "the shallow-cumulus study (shallow_cumulus.csv)", "shallow_cumulus", inp.out)
        return
    sec.add("text", "growing under a capping inversion (scene shallow_cumulus, docs/validation.md "
                    "\"Shallow cumulus\"): per seed, statistics over the last half of the run. "
            + _provenance(summary, env=env))
    cols = {"seed": "seed", "particles": "particles", "cover_mean": "cover (mean)", "cover_max": "cover (max)",
            "in_shallow_range": "snapshots in 0.1-0.4", "cf_peak": "cloud-fraction peak",
            "z_cf_peak_m": "peak height (m)", "cover_to_peak": "cover / peak", "cloud_base_m": "base (m)",
            "cloud_top_m": "top (m)", "lwp_g_m2": "LWP (g/m²)", "clouds_end": "clouds at the end"}
    shown = summary[[c for c in cols if c in summary.columns]].rename(columns=cols)
    sec.add("table", _table(shown), caption=f"{path.name}: one row per seed and their mean.")
    les, lpath = inp.csv("shallow_cumulus_les")
    if les is not None:
        keep = ["case", "metric", "lo", "hi", "scene_mean", "scene_seed_min", "scene_seed_max", "inside", "note",
                "source"]
        sec.add("table", _table(les[[c for c in keep if c in les.columns]]), caption=(
            f"{lpath.name}: the published cases' numbers (from the papers' text) beside the scene's seed mean "
            "and seed range; inside: the mean lies in the case's range."))
    grid, gpath = inp.csv("shallow_cumulus_grid")
    if grid is not None:
        seeds = [str(x) for x in grid["seed"] if str(x) != "mean"]
        particles = summary[summary["seed"].astype(str).isin(seeds)]
        keep = [c for c in cols if c not in ("seed", "particles") and c in grid.columns and c in particles.columns]
        rows = [{"solver": f"particles (seeds {', '.join(seeds)})", **particles[keep].mean(numeric_only=True)},
                {"solver": f"grid, {int(grid['cells'].iloc[0])}³ cells (seeds {', '.join(seeds)})",
                 **grid[grid["seed"].astype(str) != "mean"][keep].mean(numeric_only=True)}]
        sec.add("table", _table(pd.DataFrame(rows).rename(columns=cols)), caption=(
            f"The grid baseline on the same scene and seeds ({gpath.name}, scripts/probe_shallow_grid.py, "
            f"{_provenance(grid)}), analysed as the particle runs are: seed means."))
    series, _ = inp.csv("shallow_cumulus_series")
    profile, _ = inp.csv("shallow_cumulus_profile")
    if series is not None and profile is not None:
        covers = les[les["metric"] == "cover_mean"] if les is not None else pd.DataFrame()
        bands = [(str(r.case), float(r.lo), float(r.hi)) for r in covers.itertuples()]
        sec.add("image", plots.shallow_cumulus_plot(series, profile, bands),
                caption="Cover against time (shaded: the LES cases' cover ranges) and the time-mean cloud-fraction "
                        "profile.")
    _render_blocks(inp, sec, [
        ("shallow_cumulus_volume", "seed 0 at the end: the cloud water deposited on the analysis grid, volume "
                                   "rendered"),
        ("shallow_cumulus_particles", "the same state as particles with w > 1e-5 kg/kg, opacity rising with w"),
    ])


SWEEP_HIDDEN = ("device", "commit", "run_dir")
SWEEP_LABELS = {   # sweep.csv column -> table header (bench.studies.sweep writes the columns)
    "value": "value (spacings in m)", "wall_s": "wall time (s)",
    "error_self": "error vs own finest run", "error_other": "error vs other method's finest run",
    "error_cover_self": "cover error vs own finest", "error_profile_self": "profile error vs own finest",
    "error_cover_other": "cover error vs other's finest", "error_profile_other": "profile error vs other's finest",
    "particles": "particles (max)", "initial_particles": "particles (initial)", "cells": "grid cells",
    "spacing_m": "spacing (m)", "iterations": "PBF iterations", "resolution_m": "resolution (m)",
    "cloud_base_mean": "cloud base (m)", "cloud_top_mean": "cloud top (m)", "cover_mean": "cloud cover (fraction)",
    "lwp_mean": "LWP (kg/m²)", "split_threshold": "split threshold α", "reference": "reference run",
    "pareto": "on Pareto front"}
"""Errors are relative L2 differences of the cover series and the cloud-fraction profile (dimensionless);
cover, LWP, base and top are time means over the run's cloudy snapshots (cover > 1%)."""


def _sweep(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, _ = inp.csv("sweep")
    if df is None:
        _missing(sec, "sweep.csv (run time against error)", "sweep", inp.out)
        return
    df = df.copy()
    reference = (df["reference"].map(plots._truthy) if "reference" in df.columns
                 else pd.to_numeric(df["error_self"], errors="coerce") <= 0)
    sec.add("image", plots.pareto_plot(df, reference=reference), caption=(
        "Each point one run; error = difference of the cloud statistics from the finest run of the same method "
        "(left) and of the other method (right); lines: Pareto fronts per method and mode (no run on a front is "
        "beaten in both wall time and error by another of its group)."))
    keys = [k for k in ("method", "mode") if k in df.columns]
    measured = df[~reference & df["error_self"].notna() & df["wall_s"].notna()]
    fronts = [pareto_front(g, "wall_s", "error_self") for _, g in measured.groupby(keys, sort=True)]
    cols = [c for c in ("method", "mode", "parameter", "value", "particles", "cells", "wall_s", "error_self",
                        "error_other") if c in df.columns]
    if fronts:
        sec.add("table", _table(pd.concat(fronts)[cols], labels=SWEEP_LABELS), caption=(
            "runs on the Pareto front of each method / mode (wall time against the error vs the own finest run; "
            "the reference runs excluded)"))
    verdict = _study_verdict(inp) or _verdict(measured)
    if verdict:
        sec.add("text", verdict)
    convergence = plots.convergence_plot(df)
    if convergence is not None:
        sec.add("image", convergence, caption=(
            "Convergence: each solver's cloud statistics (time means over the run's cloudy period, cover > 1%) "
            "against its resolution, particle spacing or grid cell size (finer to the right); where the two "
            "lines approach each other as they refine, the solvers converge toward one answer."))
    if "stable" in df.columns:
        unstable = df[~df["stable"].map(plots._truthy)]
        if len(unstable):
            sec.add("note", f"{len(unstable)} sweep run(s) went unstable and have no wall time or error: "
                    + "; ".join(f"{r.method} {r.parameter} = {r.value}: {getattr(r, 'reason', '')}"
                                for r in unstable.itertuples()), level="warn")
    sec.add("table", _table(df.drop(columns=[c for c in SWEEP_HIDDEN if c in df.columns]), labels=SWEEP_LABELS),
            caption="all runs (errors: relative L2 of the cover series and the cloud-fraction profile; cloud cover, "
                    "LWP, base and top: time means over the run's cloudy snapshots)")
    sec.provenance = _provenance(df, env=env)


def _adaptive_pareto(inp: Inputs, sec: Section, env: dict | None) -> None:
    """Per scene (growing, cumulus): the Pareto plot, the configurations and the study's verdict."""
    shown = False
    for scene, suffix in (("growing", ""), ("cumulus", "_cumulus")):
        configs, _ = inp.csv(f"adaptive_pareto_configs{suffix}")
        verdict_path = inp.data / f"adaptive_verdict{suffix}.json"
        if configs is None or not verdict_path.is_file():
            continue
        shown = True
        verdict = json.loads(verdict_path.read_text())
        sec.add("text", f"{verdict.get('verdict', '')} PBF cost per adaptive particle against a uniform particle at "
                        f"equal count: {verdict.get('cost_ratio_per_particle') or float('nan'):.2f}x.")
        excluded = [e["name"] for e in verdict.get("excluded") or []]
        sec.add("image", plots.adaptive_pareto_plot(configs, verdict.get("noise_floor"), excluded), caption=(
            f"{scene}: ms per step against the error of each configuration's seed mean (cover, cloudy volume and "
            "LWP time series against the mean of the finer reference's seeds); bars: seed spread of the error; "
            "grey band: a single reference seed's error (differences below it cannot be told apart)"
            + ("; open markers: left out of the verdict (unstable in some seeds)." if excluded else ".")))
        cols = [c for c in ("config", "stable_seeds", "seeds", "particles", "ms_per_step", "pbf_ms_per_particle",
                            "error", "error_seed_spread",
                            "e_cover", "e_volume", "e_lwp", "e_base", "e_top", "e_profile", "speedup_at_equal_error",
                            "speedup_p05", "speedup_p95")
                if c in configs.columns]
        rule = verdict.get("min_stable_seeds")
        resampling = verdict.get("resampling") or {}
        sec.add("table", _table(configs[cols]), caption=f"{scene}: one row per configuration (means over its stable "
                "seeds)" + (f"; the verdict and the uniform front use only configurations stable in at least {rule} "
                            "seeds" if rule else "")
                + (f"; speedup_p05 and speedup_p95: the 5th and 95th percentiles of the speed-up over "
                   f"{resampling['replicates']} resamples of the seeds" if resampling else ""))
        for png in sorted(inp.renders.glob(f"pareto_{scene}_*.png")):
            name = png.stem[len(f"pareto_{scene}_"):]
            sec.add("image", plots.png_file_uri(png), caption=(
                f"{scene}, {name}, seed 0 at the end of the run: cloudy particles (w > 1e-5 kg/kg); the best "
                "adaptive variant is drawn beside the uniform runs at its level-0 and finest spacings."))
        runs_df, _ = inp.csv(f"adaptive_pareto{suffix}")
        sec.provenance = _provenance(runs_df, env=env)
    if not shown:
        _missing(sec, "adaptive_pareto_configs.csv (adaptive against uniform at equal error)", "adaptive_pareto",
                 inp.out)


def _study_verdict(inp: Inputs) -> str:
    """The sweep study's own verdict (OUT/data/sweep_verdict.json), if it wrote one."""
    path = inp.data / "sweep_verdict.json"
    if not path.is_file():
        return ""
    data = json.loads(path.read_text())
    text = str(data.get("verdict", ""))
    if text and data.get("metric"):
        text += f" (metric: {data['metric']})"
    return text


def _verdict(df: pd.DataFrame) -> str:
    """Adaptive against non-adaptive at equal error, from the Pareto fronts of each mode."""
    if "mode" not in df.columns:
        return ""
    fronts = {}
    for mode in ("non-adaptive", "adaptive"):
        g = df[(df["mode"] == mode) & (df["method"] == "particles")]
        if len(g.dropna(subset=["wall_s", "error_self"])):
            fronts[mode] = pareto_front(g, "wall_s", "error_self")
    if len(fronts) < 2:
        return ""
    level = max(f["error_self"].min() for f in fronts.values())  # an error both modes reach
    cost = {m: float(f[f["error_self"] <= level]["wall_s"].min()) for m, f in fronts.items()}
    faster = min(cost, key=cost.get)
    slower = max(cost, key=cost.get)
    ratio = cost[slower] / cost[faster] if cost[faster] > 0 else math.inf
    return (f"At equal error (error_self <= {level:.3g}, the smallest error both particle modes reach), "
            f"{faster} needs {cost[faster]:.3g} s and {slower} {cost[slower]:.3g} s: {faster} is "
            f"{ratio:.2f}x faster.")


STRESS_LABELS = {   # stress.csv column -> table header (bench.studies.stress writes the columns)
    "value": "value (dt in s, heating in K/s)", "step": "last step", "particles": "unstable particle ids",
    "max_speed": "max speed (m/s)", "density_error_mean": "density error, last step",
    "density_error_max": "density error, worst step", "energy_jump": "kinetic energy jump (x per step)",
    "dt": "dt (s)", "iterations": "PBF iterations", "heating_rate": "heating S_e (K/s)",
    "phase_rate": "phase rate α (1/s)", "alpha_dt": "α dt", "n_particles": "particles (max)",
    "last_good_step": "last good step"}
"""Density errors are the per-step mean of |rho/rho0 - 1| (a fraction, eq. 1)."""
GRAVITY_LABELS = {   # constant_gravity.csv column -> table header
    "constant_gravity": "g_c (m/s²)", "cloud_gravity": "cloud gravity (m/s²)", "first_cloud_s": "first cloud (s)",
    "max_cover": "max cloud cover (fraction)", "final_cover": "final cloud cover (fraction)",
    "vanished_and_returned": "vanished and returned", "density_error_mean": "density error, last step",
    "max_speed": "max speed (m/s)"}


def _stress(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, _ = inp.csv("stress")
    if df is None:
        _missing(sec, "stress.csv (stability sweep)", "stress", inp.out)
        return
    df = df.copy()
    df["stable"] = df["stable"].map(plots._truthy)
    from bench.studies.stress import DENSITY_ERROR_LIMIT, ENERGY_JUMP_LIMIT, usable_mask
    df["usable"] = df["usable"].map(plots._truthy) if "usable" in df.columns else usable_mask(df)
    energy = ENERGY_JUMP_LIMIT if "energy_jump" in df.columns else None
    if df["parameter"].astype(str).str.startswith("dt x ").any():
        sec.add("image", plots.stability_map_2d(df, DENSITY_ERROR_LIMIT, energy), caption=(
            "Two-parameter maps: every cell one run of the stress scene. Colour: the largest per-step mean density "
            "error (eq. 1); black line: the usable region's boundary (an accuracy bound, not only blow-up)."))
    else:
        sec.add("note", "no 2-D map in this stress.csv (made by an older version of the stress study); "
                        "rerun it for the dt x iterations and dt x heating-rate maps.", level="missing",
                command=_command("stress", inp.out))
    sec.add("image", plots.stability_map(df), caption=(
        f"One parameter at a time. Green: usable (stable and density error <= {100 * DENSITY_ERROR_LIMIT:g}%); "
        "orange: ran to the end but not usable; red: stopped as unstable (reason shown)."))
    limit = stress_limits(df)
    if limit:
        sec.add("text", limit)
    bad = df[~df["stable"]]
    numeric = [c for c in ("max_speed", "density_error_mean") if c in df.columns]
    finite = df[df["stable"]][numeric].apply(pd.to_numeric, errors="coerce")
    if numeric and not np.isfinite(finite.to_numpy(dtype=float)).all():
        sec.add("note", "a run marked stable has non-finite statistics: check stress.csv", level="error")
    sec.add("text", f"{len(df)} runs, {int(df['stable'].sum())} stable, {len(bad)} unstable.")
    sec.add("table", _table(df.drop(columns=[c for c in ("device", "commit") if c in df.columns]),
                            labels=STRESS_LABELS),
            caption="all cases (an unstable run is stopped at the step the check caught it; its NaN never "
                    "enters the statistics; density error: the mean of |rho/rho0 - 1| over the particles)")
    gravity, gravity_path = inp.csv("constant_gravity")
    if gravity is None:
        _missing(sec, "constant_gravity.csv (paper example 2: a constant gravity on the whole domain)",
                 "constant_gravity", inp.out)
    else:
        cols = [c for c in ("case", "constant_gravity", "cloud_gravity", "particles", "stable", "reason",
                            "first_cloud_s", "max_cover", "final_cover", "vanished_and_returned",
                            "density_error_mean", "max_speed") if c in gravity.columns]
        sec.add("table", _table(gravity[cols], labels=GRAVITY_LABELS), caption=(
            f"A constant gravity g_c (m/s^2) added to every particle of the growing scene, beside the shipped "
            f"cycling scene, from {gravity_path.name}: cloud cover (fraction of columns) and the last step's "
            "density error and largest speed (m/s)."))
    sec.provenance = _provenance(df, env=env)


def stress_limits(df: pd.DataFrame) -> str:
    """'Largest usable dt (density error <= X%): ... s; largest stable dt: ... s.' from the 1-D dt cases."""
    from bench.studies.stress import DENSITY_ERROR_LIMIT, largest_stable_dt, usable_mask
    dt = df[df["parameter"] == "dt"].copy()
    if not len(dt):
        return ""
    dt["value"] = pd.to_numeric(dt["value"], errors="coerce")
    dt["stable"] = dt["stable"].map(plots._truthy)
    dt["usable"] = dt["usable"].map(plots._truthy) if "usable" in dt.columns else usable_mask(dt)
    found = largest_stable_dt(dt)
    usable, stable = found["largest_usable_dt"], found["largest_stable_dt"]
    text = (f"Largest usable dt (density error <= {100 * DENSITY_ERROR_LIMIT:g}%): "
            + (f"{usable:g} s" if usable is not None else "none of the tried dt") + "; ")
    text += (f"largest stable dt (no blow-up, accuracy aside): {stable:g} s" if stable is not None
             else "no tried dt was stable")
    if found["smallest_unstable_dt"] is not None:
        text += f"; smallest unstable dt: {found['smallest_unstable_dt']:g} s"
    return text + "."


def _render_blocks(inp: Inputs, sec: Section, names_captions) -> None:
    for name, caption in names_captions:
        png, reason = inp.render(name)
        if png is not None:
            sec.add("image", plots.png_file_uri(png), caption=caption)
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
        sec.add("image", plots.file_uri(gif, "image/gif"), caption=(
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
    template = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                                 undefined=jinja2.StrictUndefined).get_template("report.html.j2")
    page = template.render(
        sections=sections, env=env or {},
        generated=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        scale=(env or {}).get("scale", "unknown"),
        n_missing=sum(s.missing for s in sections),
        failed_studies=sorted(k for k, v in status.items() if isinstance(v, dict) and not v.get("ok", True)),
        Markup=jinja2.utils.markupsafe.Markup,
    )
    target = out / "index.html"
    from pbf_cuda.files import atomic_write_text
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
