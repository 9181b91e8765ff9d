"""The time-to-solution study's part of the report: its section "Time to solution at equal error" (the cheapest
settings for each error budget, the speed-up over today's defaults at their own error, and the front of error
against wall time per simulated second, one marker per setting) and its verdict card."""
from __future__ import annotations

import json
import math

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.ticker import FormatStrFormatter

from cloudpbf.report import glance_plots as gp
from cloudpbf.report import plots
from cloudpbf.report.common import Inputs, Section, _provenance, _shown_path, _table
from cloudpbf.report.glance import RESAMPLED, Card, data_link, ratio_words, resampled, section_link
from cloudpbf.studies.plans import scene_file_suffix

SCENES = ("growing", "cumulus", "cycling")
GROUP_STYLE = {  # group -> (marker, colour, label)
    "grid": ("o", "#1f77b4", "spacing x fixed dt"), "iterations": ("s", "#2ca02c", "PBF iterations"),
    "divergence": ("D", "#8c564b", "projection iterations"), "cfl": ("^", "#d62728", "CFL-controlled step"),
    "adaptive": ("*", "#ff7f0e", "adaptive twin")}
LABELS = {"setting": "setting", "wall_per_sim_s": "wall s per simulated s", "error": "error",
          "error_p05": "error 5%", "error_p95": "error 95%", "stable_seeds": "stable seeds",
          "speedup_vs_default": "speed-up vs defaults", "error_budget": "error budget"}


def _read(inp: Inputs, scene: str):
    suffix = scene_file_suffix(scene)
    frame, _ = inp.csv(f"time_to_solution{suffix}")
    path = inp.data / f"time_to_solution_verdict{suffix}.json"
    verdict = None
    if path.is_file():
        try:
            verdict = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            verdict = None
    return frame, verdict


def tts_plot(frame: pd.DataFrame, verdict: dict | None = None) -> str:
    """Error against wall time per simulated second: one marker per setting (5-95% error bars where the seeds
    were resampled), the front as a line, today's defaults and the reference's absence marked."""
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    df = frame[frame["group"] != "reference"].copy()
    for col in ("wall_per_sim_s", "error", "error_p05", "error_p95"):
        if col in df:
            df[col] = pd.to_numeric(df[col], errors="coerce")
    df = df[np.isfinite(df["wall_per_sim_s"]) & np.isfinite(df["error"])]
    qualified = df["qualified"].map(plots._truthy) if "qualified" in df else pd.Series(True, index=df.index)
    for group, (marker, colour, label) in GROUP_STYLE.items():
        g = df[df["group"] == group]
        if g.empty:
            continue
        x, y = 1e3 * g["wall_per_sim_s"].to_numpy(float), g["error"].to_numpy(float)
        if {"error_p05", "error_p95"} <= set(g.columns) and g["error_p05"].notna().any():
            lo, hi = g["error_p05"].to_numpy(float), g["error_p95"].to_numpy(float)
            ax.errorbar(x, y, yerr=[np.clip(y - lo, 0, None), np.clip(hi - y, 0, None)],
                        fmt="none", ecolor=colour, alpha=0.35, lw=1)
        ok = qualified.loc[g.index].to_numpy(bool)
        ax.scatter(x[ok], y[ok], marker=marker, color=colour, label=label, zorder=3)
        if (~ok).any():
            ax.scatter(x[~ok], y[~ok], marker=marker, facecolors="none", edgecolors=colour, zorder=3,
                       label=f"{label} (not stable in every seed)")
        for xi, yi, name in zip(x, y, g["setting"]):
            ax.annotate(str(name), (xi, yi), fontsize=6, alpha=0.7, xytext=(3, 2), textcoords="offset points")
    front = df[df["front"].map(plots._truthy)].sort_values("wall_per_sim_s") if "front" in df else df.iloc[:0]
    if len(front):
        ax.step(1e3 * front["wall_per_sim_s"].to_numpy(float), front["error"].to_numpy(float), where="post",
                color="k", lw=1, alpha=0.7, label="front")
    default = df[df["default"].map(plots._truthy)] if "default" in df else df.iloc[:0]
    if len(default):
        ax.scatter(1e3 * default["wall_per_sim_s"].to_numpy(float), default["error"].to_numpy(float), s=160,
                   facecolors="none", edgecolors="k", lw=1.5, zorder=4, label="today's defaults")
        ax.axhline(float(default["error"].iloc[0]), color="k", ls=":", lw=0.8)
    if verdict and verdict.get("noise_floor") is not None:
        ax.axhline(float(verdict["noise_floor"]), color="grey", ls="--", lw=0.8, label="seed-noise floor")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(FormatStrFormatter("%.3g"))
    ax.xaxis.set_minor_formatter(FormatStrFormatter("%.3g"))
    ax.set_xlabel("wall time per simulated second (ms)")
    ax.set_ylabel("error against the reference (relative L2)")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return plots.to_data_uri(fig)


def _budget_table(verdict: dict) -> pd.DataFrame:
    rows = []
    for b in verdict.get("budgets", []):
        pick = b.get("cheapest") or {}
        rows.append({"budget": f"{b['factor']:g} x the defaults' error", "error_budget": b.get("error_budget"),
                     "setting": pick.get("setting", "none"), "error": pick.get("error"),
                     "wall_per_sim_s": pick.get("wall_per_sim_s"), "speedup_vs_default": b.get("speedup_vs_default")})
    return pd.DataFrame(rows)


def time_to_solution_section(inp: Inputs, sec: Section, env: dict | None) -> None:
    """One block per scene the study ran (growing first): the verdict, the budgets, the plot, the front."""
    frames = []
    for scene in SCENES:
        frame, verdict = _read(inp, scene)
        if frame is None:
            continue
        frames.append(frame)
        if verdict:
            sec.add("text", verdict.get("verdict", ""))
            sec.add("table", _table(_budget_table(verdict), labels=LABELS), caption=(
                f"{scene}: the cheapest setting (least wall time per simulated second) whose error is at most each "
                "budget, among the settings stable in every seed; speed-up = the defaults' wall time per simulated "
                "second over the setting's"))
        sec.add("image", tts_plot(frame, verdict), caption=(
            f"{scene}: error of each setting's seed-mean cover, cloudy volume and LWP series against the reference "
            "(finest spacing, smallest step, more iterations) against the solver's wall time per simulated second; "
            "bars: 5-95% over resampled seeds; line: the front (no setting both cheaper and more accurate)."))
        cols = [c for c in ("setting", "group", "stable_seeds", "wall_per_sim_s", "error", "error_p05", "error_p95",
                            "e_cover", "e_volume", "e_lwp", "front") if c in frame.columns]
        sec.add("table", _table(frame[cols], labels=LABELS), caption=f"{scene}: every setting")
    if not frames:
        sec.add("note", "time to solution at equal error: not run in this study.", level="missing",
                command=f"cloudpbf time-to-solution --out {_shown_path(inp.out)}")
        return
    sec.provenance = _provenance(*frames, env=env)


def time_to_solution_card(inp: Inputs, env: dict | None, titles: dict) -> Card | None:
    """The time-to-solution study's verdicts (time_to_solution_verdict[_scene].json, cloudpbf.studies.time_to_solution):
    the defaults' wall time per simulated second over the cheapest setting's at the defaults' own error, with its
    5-95% interval over resampled seeds; None where the study did not run."""
    card = Card("time_to_solution", "Time to solution at equal error")
    parts, figure = [], None
    for scene in SCENES:
        sfx = scene_file_suffix(scene)
        path = inp.data / f"time_to_solution_verdict{sfx}.json"
        if not path.is_file():
            continue
        v = json.loads(path.read_text())
        card.links += data_link(inp, path.name, f"time_to_solution{sfx}.csv")
        speed, budgets = v.get("speedup_at_default_error"), v.get("budgets") or []
        pick = (budgets[0].get("cheapest") or {}) if budgets else {}
        if speed is None or not np.isfinite(speed) or not pick:
            parts.append(str(v.get("verdict", f"{scene}: no verdict")))
            continue
        interval = v.get("speedup_interval")
        ci = resampled(speed, interval, v.get("seeds"))
        default = v.get("default") or {}
        parts.append(f"{scene}: {pick.get('setting', '?')} {ratio_words(ci, interval=RESAMPLED)} than the defaults "
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
    card.links = section_link("time_to_solution", titles) + card.links
    return card
