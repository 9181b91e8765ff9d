"""The report's first screen: one card per verdict, each a small figure, a one-line answer and the error or
interval it holds with, and links to the section and the data files behind it.

Cards, in order: Table 1 against the paper, the adaptive front (adaptive-pareto, else the sweep), particles
against the grid, the stability map, and time to solution at equal error, shown only when the
time-to-solution study's verdicts exist (``time_to_solution_verdict[_scene].json``).  A card without data
says which command produces it.

Verdict rules: a speed-up against the paper only where the particle counts match (timing.paper_comparison);
every speed-up beside its interval, and "no difference measured" where the interval holds 1 (or 0 for a
difference); ms per step as a median with its spread where the data has the per-step times, else plainly as
the mean over the timed steps.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from . import glance_plots as gp
from . import plots
from .common import Inputs, Section, _command
from .inference import LEVEL, Interval, describes_no_difference, difference_ci, format_ci, mean_ci, median_spread


@dataclass
class Card:
    id: str
    title: str
    answer: str = ""
    detail: str = ""
    figure: str | None = None
    links: list = field(default_factory=list)      # (label, href): sections '#id', data files 'data/NAME'
    level: str = "ok"                              # ok, warn (no difference measured / caveat), missing
    command: str = ""


def _data_link(inp: Inputs, *names: str) -> list:
    return [(name, f"data/{name}") for name in names if (inp.data / name).is_file()]


def _section_link(target: str, titles: dict) -> list:
    return [(titles[target], f"#{target}")] if target in titles else []


def _missing(card: Card, inp: Inputs, what: str, key: str) -> Card:
    card.level, card.answer, card.command = "missing", f"not run in this study: {what}", _command(key, inp.out)
    return card


def _ratio_words(ci: Interval, what: str = "", interval: str = f"{100 * LEVEL:g}% interval") -> str:
    """'1.60x faster [1.30, 1.90]' or 'no difference measured (1.05x, 95% interval 0.8-1.3x)'; `interval` names
    the interval (a t-interval, or the 5-95% of resampled seeds)."""
    if describes_no_difference(ci):
        bounds = (f", {interval} {ci.lo:.2f}-{ci.hi:.2f}x" if np.isfinite(ci.lo) else ", no interval")
        return f"no difference measured ({ci.mean:.2f}x{bounds})"
    if ci.mean >= 1:
        return f"{ci.mean:.2f}x faster{what} [{ci.lo:.2f}, {ci.hi:.2f}]"
    return f"{1 / ci.mean:.2f}x slower{what} [{1 / ci.hi:.2f}, {1 / ci.lo:.2f}]"


RESAMPLED = "5-95% over resampled seeds"


def _resampled(value, interval, seeds) -> Interval:
    """A speed-up with its 5-95% interval over resampled seeds (NaN bounds where the study recorded none)."""
    lo, hi = (float(v) for v in interval) if interval else (math.nan, math.nan)
    return Interval(float(value), lo, hi, int(seeds or 0))


# ---- Table 1 ----------------------------------------------------------------------------------------------
def table1_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    from .timing import PAPER_NEEDS_GPU, paper_comparison, step_time_text
    card = Card("table1", "Table 1 against the paper")
    measured, _ = inp.csv("table1")
    if measured is None:
        return _missing(card, inp, "no table1.csv", "table1")
    rows = paper_comparison(measured, env)
    rows = rows[rows["variant"] == ""]
    card.links = _section_link("table1", titles) + _data_link(inp, "table1.csv")
    scale = rows["scale"].iloc[0]
    labels = [r.replace(" non-adaptive", "").replace(" adaptive", " adapt.") for r in rows["row"]]
    if scale != "gpu":
        rates = ", ".join(f"{r['row']} {r['particle_steps_per_s']:.3g}" for r in rows.to_dict("records"))
        counts = pd.to_numeric(rows["max_particles"], errors="coerce")
        card.answer = (f"Throughput at the {scale} scale ({counts.min():,.0f}-{counts.max():,.0f} particles): "
                       f"{rates} particle-steps per second.")
        card.detail = PAPER_NEEDS_GPU
        card.level = "warn"
        card.figure = gp.bars(labels, rows["particle_steps_per_s"], ylabel="particle-steps / s")
        return card
    matched = rows[rows["counts_match"]]
    other = rows[~rows["counts_match"]]
    parts = [f"{r['row']} {r['speedup_vs_paper']:.3g}x"
             + (f" [{r['speedup_lo']:.3g}, {r['speedup_hi']:.3g}]" if np.isfinite(r["speedup_lo"]) else "")
             for r in matched.to_dict("records")]
    card.answer = ("Per step faster than the paper at its particle counts: " + ", ".join(parts) + "."
                   if parts else "No row runs at the paper's particle counts: throughput only.")
    details = []
    if len(other):
        details.append("Other particle counts, so throughput (particle-steps/s) instead of a speed-up: " + ", ".join(
            f"{r['row']} {r['max_particles']:,.0f} against {r['paper_particles']:,.0f} particles, "
            f"{r['throughput_vs_paper']:.3g}x the paper's throughput" for r in other.to_dict("records")) + ".")
    first = rows.iloc[0].to_dict()
    details.append(f"{first['row']}: {step_time_text(first)}"
                   + (": no interval on the speed-ups." if not np.isfinite(first["speedup_lo"]) else
                      "; intervals: the paper's ms over our 95th and 5th percentile step."))
    card.detail = " ".join(details)
    card.figure = gp.bars(labels, rows["total_ms"], reference=rows["paper_ms"], ylabel="ms per step")
    return card


# ---- the adaptive front -----------------------------------------------------------------------------------
def _pareto_card(inp: Inputs, card: Card, titles: dict) -> Card | None:
    parts, details, figure = [], [], None
    for suffix in ("", "_cumulus"):
        path = inp.data / f"adaptive_verdict{suffix}.json"
        if not path.is_file():
            continue
        v = json.loads(path.read_text())
        scene = v.get("scene", suffix.strip("_") or "growing")
        best = v.get("best") or {}
        speed = best.get("speedup_at_equal_error")
        card.links += _data_link(inp, path.name, f"adaptive_pareto_configs{suffix}.csv")
        if speed is None or not np.isfinite(speed):
            parts.append(f"{scene}: {v.get('verdict', 'no verdict')}")
            continue
        interval = best.get("speedup_interval")
        ci = _resampled(speed, interval, best.get("seeds"))
        parts.append(f"{scene}: best variant {best.get('name', '?')} {_ratio_words(ci, interval=RESAMPLED)} "
                     f"at equal error "
                     f"{best.get('error', math.nan):.3g} (±{best.get('error_seed_spread', math.nan):.2g} over seeds)")
        details.append(f"{scene}: {_seed_ms(inp, suffix, best)} against "
                       f"{best.get('uniform_ms_at_equal_error', math.nan):.3g} ms per step of uniform particles at "
                       f"that error ({best.get('stable_seeds', '?')} of {best.get('seeds', '?')} seeds stable)")
        configs, _ = inp.csv(f"adaptive_pareto_configs{suffix}")
        if figure is None and configs is not None and {"kind", "ms_per_step", "error"} <= set(configs.columns):
            uni = configs[configs["kind"] == "uniform"]
            ada = configs[configs["kind"] == "adaptive"]
            star = configs[configs["config"] == best.get("name")] if "config" in configs.columns else ada.iloc[:0]
            figure = gp.front(uni["ms_per_step"], uni["error"], ada["ms_per_step"], ada["error"],
                              best=(float(star["ms_per_step"].iloc[0]), float(star["error"].iloc[0]))
                              if len(star) else None)
    if not parts:
        return None
    card.answer = "; ".join(parts) + "."
    card.detail = "; ".join(details) + ("." if details else "")
    card.figure = figure
    card.level = "warn" if "no difference measured" in card.answer else "ok"
    card.links = _section_link("adaptive_pareto", titles) + card.links
    return card


def _seed_ms(inp: Inputs, suffix: str, best: dict) -> str:
    """The best variant's ms per step as the median over its stable seeds with their 5-95% range
    (adaptive_pareto[_scene].csv), else the verdict's mean."""
    runs, _ = inp.csv(f"adaptive_pareto{suffix}")
    if runs is not None and {"config", "ms_per_step"} <= set(runs.columns):
        mine = runs[runs["config"] == best.get("name")]
        if "stable" in mine.columns:
            mine = mine[mine["stable"].map(plots._truthy)]
        med, lo, hi, n = median_spread(mine["ms_per_step"])
        if n >= 2:
            return f"{med:.3g} ms per step (median over {n} seeds, 5-95%: {lo:.3g}-{hi:.3g})"
    return f"{best.get('ms_per_step', math.nan):.3g} ms per step (mean over seeds)"


def sweep_verdict(v: dict) -> tuple[str, bool]:
    """(the sweep verdict's text, no difference measured) from sweep_verdict.json, its interval recomputed from the
    comparisons so that a verdict written before the interval existed is read by the same rule."""
    comps = v.get("comparisons") or []
    if not comps:
        return str(v.get("verdict", "no verdict")), True
    from bench.studies.sweep import speedup_summary
    summary = speedup_summary([c["speedup"] for c in comps])
    errs = [c["error"] for c in comps]
    return f"{summary['verdict']}; at errors {min(errs):.3g}-{max(errs):.3g}", summary["no_difference"]


def adaptive_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    card = Card("adaptive_front", "The adaptive front: speed-up at equal error")
    found = _pareto_card(inp, card, titles)
    if found is not None:
        return found
    path = inp.data / "sweep_verdict.json"
    if not path.is_file():
        return _missing(card, inp, "no adaptive_verdict.json or sweep_verdict.json", "adaptive_pareto")
    v = json.loads(path.read_text())
    text, none = sweep_verdict(v)
    card.answer = f"Sweep (one seed per run): {text}."
    card.detail = f"Error: {v.get('metric', 'against the finest run')}; wall time inside step()."
    card.level = "warn" if none else "ok"
    card.links = _section_link("sweep", titles) + _data_link(inp, "sweep_verdict.json", "sweep.csv")
    fixed, adapt = pd.DataFrame(v.get("non_adaptive") or []), pd.DataFrame(v.get("adaptive") or [])
    if len(fixed) and len(adapt):
        card.figure = gp.front(fixed["wall_s"], fixed["error_self"], adapt["wall_s"], adapt["error_self"],
                               xlabel="wall time in step() (s)", uniform_label="non-adaptive")
    return card


# ---- particles against the grid ---------------------------------------------------------------------------
def compare_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    card = Card("compare", "Particles against the grid")
    ts, _ = inp.csv("compare_timeseries")
    if ts is None or "solver" not in ts.columns or not {"particles", "grid"} <= set(ts["solver"]):
        return _missing(card, inp, "no compare_timeseries.csv with both solvers", "compare")
    last = ts.sort_values("time_s").groupby(["solver", "mode", "seed"]).tail(1)
    grid = last[last["solver"] == "grid"]["cloud_cover"]
    labels, cis, parts, none = [], [], [], []
    for mode in ("non-adaptive", "adaptive"):
        part = last[(last["solver"] == "particles") & (last["mode"] == mode)]["cloud_cover"]
        if not len(part):
            continue
        diff = difference_ci(part, grid)
        no = describes_no_difference(diff, 0.0)
        none.append(no)
        labels.append(f"particles {mode}")
        cis.append(mean_ci(part))
        bounds = (f"[{diff.lo:+.2g}, {diff.hi:+.2g}]" if np.isfinite(diff.lo) else "(no interval)")
        parts.append(f"{mode} {diff.mean:+.2g} {bounds}" + (": no difference measured" if no else ""))
    labels.append("grid")
    cis.append(mean_ci(grid))
    card.answer = "Final cloud cover, particles minus grid: " + "; ".join(parts) + "."
    card.detail = ("Seed means [95% t-interval]: " + ", ".join(f"{lab} {format_ci(ci)}" for lab, ci in zip(labels, cis))
                   + f"; difference: Welch {100 * LEVEL:g}% interval.")
    card.level = "warn" if any(none) else "ok"
    card.figure = gp.intervals(labels, [c.mean for c in cis], [c.lo for c in cis], [c.hi for c in cis],
                               "final cloud cover (fraction)")
    card.links = _section_link("compare", titles) + _data_link(inp, "compare_timeseries.csv", "compare_runs.csv")
    return card


# ---- the stability map ------------------------------------------------------------------------------------
def stability_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    from .tradeoffs import stress_frame, stress_limits
    card = Card("stress", "Stability map")
    df, _ = inp.csv("stress")
    if df is None:
        return _missing(card, inp, "no stress.csv", "stress")
    df = stress_frame(df)
    card.answer = stress_limits(df)
    if "reference_error" not in df.columns:
        card.level = "warn"
    dt = df[df["parameter"] == "dt"].sort_values("value")
    if len(dt):
        states = ["usable" if u else "stable" if s else "unstable" for u, s in zip(dt["usable"], dt["stable"])]
        card.figure = gp.strip(pd.to_numeric(dt["value"], errors="coerce"), states,
                               stable_label="stable, not usable" if "reference_error" in df.columns
                               else "stable (usable not checked)")
    card.links = _section_link("stress", titles) + _data_link(inp, "stress.csv", "stress_summary.json")
    return card


# ---- time to solution (shown when its data exists) ----------------------------------------------------------
TTS_SCENES = ("growing", "cumulus", "cycling")


def time_to_solution_card(inp: Inputs, env: dict | None, titles: dict) -> Card | None:
    """The time-to-solution study's verdicts (time_to_solution_verdict[_scene].json, bench.studies.time_to_solution):
    the defaults' wall time per simulated second over the cheapest setting's at the defaults' own error, with its
    5-95% interval over resampled seeds; None where the study did not run."""
    card = Card("time_to_solution", "Time to solution at equal error")
    parts, figure = [], None
    for scene in TTS_SCENES:
        sfx = "" if scene == "growing" else f"_{scene}"
        path = inp.data / f"time_to_solution_verdict{sfx}.json"
        if not path.is_file():
            continue
        v = json.loads(path.read_text())
        card.links += _data_link(inp, path.name, f"time_to_solution{sfx}.csv")
        speed, budgets = v.get("speedup_at_default_error"), v.get("budgets") or []
        pick = (budgets[0].get("cheapest") or {}) if budgets else {}
        if speed is None or not np.isfinite(speed) or not pick:
            parts.append(str(v.get("verdict", f"{scene}: no verdict")))
            continue
        interval = v.get("speedup_interval")
        ci = _resampled(speed, interval, v.get("seeds"))
        default = v.get("default") or {}
        parts.append(f"{scene}: {pick.get('setting', '?')} {_ratio_words(ci, interval=RESAMPLED)} than the defaults "
                     f"({default.get('setting', '?')}) at their error {default.get('error', math.nan):.3g}")
        frame, _ = inp.csv(f"time_to_solution{sfx}")
        if figure is None and frame is not None and {"wall_per_sim_s", "error"} <= set(frame.columns):
            front = frame[frame["front"].map(plots._truthy)] if "front" in frame.columns else frame.iloc[:0]
            others = frame.drop(front.index)
            figure = gp.front(1e3 * front["wall_per_sim_s"], front["error"], 1e3 * others["wall_per_sim_s"],
                              others["error"], best=(1e3 * float(pick["wall_per_sim_s"]), float(pick["error"]))
                              if pick.get("wall_per_sim_s") is not None and pick.get("error") is not None else None,
                              xlabel="ms per simulated second", uniform_label="front", others_label="settings")
    if not parts:
        return None
    card.answer = "; ".join(parts) + "."
    card.detail = ("Cost: the solver's wall time per simulated second; error against a converged reference; "
                   "interval: 5-95% over resampled seeds.")
    card.figure = figure
    card.level = "warn" if "no difference measured" in card.answer or "no verdict" in card.answer else "ok"
    card.links = _section_link("time_to_solution", titles) + card.links
    return card


CARDS = (table1_card, adaptive_card, compare_card, stability_card, time_to_solution_card)


def _summary(inp: Inputs, sec: Section, env: dict | None) -> None:
    """The verdict cards (the report's first screen)."""
    from .build import report_sections
    titles = {r.id: r.title for r in report_sections()}
    cards = []
    for make in CARDS:
        try:
            card = make(inp, env, titles)
        except Exception as exc:  # a broken input must not hide the other cards
            card = Card(make.__name__.replace("_card", ""), make.__name__.replace("_card", "").replace("_", " "),
                        answer=f"could not build this card from data/: {type(exc).__name__}: {exc}", level="missing")
        if card is not None:
            cards.append(card)
    sec.add("cards", cards)
