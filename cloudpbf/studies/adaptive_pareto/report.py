"""The adaptive-pareto study's part of the report: its section (per scene the Pareto plot, the configurations
and the verdict) and its verdict card (the best variant's speed-up at equal error, with its 5-95% interval over
resampled seeds; ms per step)."""
from __future__ import annotations

import json
import math

import numpy as np

from cloudpbf.report import glance_plots as gp
from cloudpbf.report import plots
from cloudpbf.report.common import Inputs, Section, _missing, _provenance, _table
from cloudpbf.report.glance import RESAMPLED, Card, data_link, missing_card, ratio_words, resampled, section_link
from cloudpbf.report.inference import median_spread
from cloudpbf.studies.adaptive_pareto.design import SCENES
from cloudpbf.studies.plans import scene_file_suffix


def _adaptive_pareto(inp: Inputs, sec: Section, env: dict | None) -> None:
    """Per scene (design.SCENES): the Pareto plot, the configurations and the study's verdict."""
    shown = False
    for scene, suffix in ((s, scene_file_suffix(s)) for s in SCENES):
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
            sec.add("image", plots.png_file_uri(png), source=png, caption=(
                f"{scene}, {name}, seed 0 at the end of the run: cloudy particles (w > 1e-5 kg/kg); the best "
                "adaptive variant is drawn beside the uniform runs at its level-0 and finest spacings."))
        runs_df, _ = inp.csv(f"adaptive_pareto{suffix}")
        sec.provenance = _provenance(runs_df, env=env)
    if not shown:
        _missing(sec, "adaptive_pareto_configs.csv (adaptive against uniform at equal error)", "adaptive_pareto", inp)


# ---- the verdict card -----------------------------------------------------------------------------
def _pareto_card(inp: Inputs, card: Card, titles: dict) -> Card | None:
    parts, details, figure = [], [], None
    for suffix in (scene_file_suffix(s) for s in SCENES):
        path = inp.data / f"adaptive_verdict{suffix}.json"
        if not path.is_file():
            continue
        v = json.loads(path.read_text())
        scene = v.get("scene", suffix.strip("_") or "growing")
        best = v.get("best") or {}
        speed = best.get("speedup_at_equal_error")
        card.links += data_link(inp, path.name, f"adaptive_pareto_configs{suffix}.csv")
        if speed is None or not np.isfinite(speed):
            parts.append(f"{scene}: {v.get('verdict', 'no verdict')}")
            continue
        interval = best.get("speedup_interval")
        ci = resampled(speed, interval, best.get("seeds"))
        parts.append(f"{scene}: best variant {best.get('name', '?')} {ratio_words(ci, interval=RESAMPLED)} "
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
    card.links = section_link("adaptive_pareto", titles) + card.links
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


def adaptive_front_card(inp: Inputs, env: dict | None, titles: dict) -> Card:
    """The adaptive front from the study's verdicts (adaptive_verdict[_<scene>].json); where there is none, a card
    saying so (the sweep's card stands in for it where the sweep ran, cloudpbf.studies.sweep)."""
    card = Card("adaptive_front", "The adaptive front: speed-up at equal error")
    found = _pareto_card(inp, card, titles)
    if found is not None:
        return found
    return missing_card(card, inp, "no adaptive_verdict.json or sweep_verdict.json", "adaptive_pareto")
