"""Shallow cumulus: the `shallow_cumulus` scene (growing under a capping inversion, docs/validation.md
"Shallow cumulus") over several noise seeds, its cloud statistics beside two published shallow-cumulus LES
cases, and renders of its clouds.

Every run is analysed by cloudpbf.statistics (particles deposited on the analysis grid, one cell per particle
spacing). Per seed, over the second half of the run (when the clouds have formed; `ANALYSIS_FROM` of the run
length): the mean and range of the cloud cover, the fraction of the snapshots with cover in the LES range
0.1-0.4, the time-mean cloud-fraction profile (its peak, the peak's height, cover / peak), the cloudy-period
means of cloud base, top and mean liquid water path, and the separate clouds at the end (3-D objects of
face-connected cloudy cells). Outputs in OUT/data:

* shallow_cumulus.csv: one row per seed and one `mean` row, the metrics above, device, commit
* shallow_cumulus_series.csv: seed, time_s, cloud_cover, cloud_base, cloud_top, lwp_mean, n_objects
* shallow_cumulus_profile.csv: seed, z, cloud_fraction (time mean over the analysis window)
* shallow_cumulus_les.csv: the LES cases' numbers (LES_CASES), each metric beside the scene's seed mean
* shallow_cumulus_state.npz: seed 0's last state, compact (cloudy particles, a tenth of the clear ones, the
  deposited cloud water), from which `--render-only` draws where the runs' machine cannot
* renders/shallow_cumulus_volume.png, renders/shallow_cumulus_particles.png: that state, volume rendered and
  as particles
"""
from __future__ import annotations

import math
import sys
from typing import Annotated, Optional

import numpy as np
import pandas as pd
import typer

from cloudpbf.report import plots
from cloudpbf.report.common import Inputs, Section, _missing, _provenance, _render_blocks, _table
from cloudpbf import render, runs, statistics
from cloudpbf.cli_common import (DEFAULT_OUT, Backend, BackendOpt, GpusOpt, OutOpt, QuietOpt, RunsRootOpt, ScaleOpt,
                              ScaleName, SchedulerOpt, WorkersOpt, run_command, study_context)
from cloudpbf.statistics import CLOUDY_COVER, cloudy_period_means
from cloudpbf.studies.context import StudyContext
from cloudpbf.studies.registry import ReportSection, Study, register
from cloudpbf.studies.scales import scale_scene
from pbf_cuda.scene import load_scene

SCENE = "shallow_cumulus"
ANALYSIS_FROM = 0.5          # the analysis window: the last half of the run
SHALLOW_COVER = (0.1, 0.4)   # cover of shallow-cumulus LES cases (below)
SERIES_COLUMNS = ("cloud_cover", "cloud_base", "cloud_top", "lwp_mean", "n_objects")
STATE_FILE = "shallow_cumulus_state.npz"   # seed 0's last state, compact (save_state), for the renders

# Published shallow-cumulus LES cases, numbers from the papers' text (docs/validation.md, "Shallow cumulus").
# lo/hi: the range the case gives; NaN where it gives none.
LES_CASES = (
    {"case": "BOMEX", "metric": "cover_mean", "lo": 0.08, "hi": 0.17,
     "note": "total cover over the models, last 3 h (ensemble mean 0.13)",
     "source": "Siebesma et al. 2003, J. Atmos. Sci. 60, 1201-1219"},
    {"case": "BOMEX", "metric": "cover_to_peak", "lo": 1.3, "hi": 3.7,
     "note": "total cover / maximum of the cloud-fraction profile (about 2.2): clouds of many tops share one base",
     "source": "Siebesma et al. 2003"},
    {"case": "BOMEX", "metric": "z_cf_peak_over_top", "lo": 0.0, "hi": 0.5,
     "note": "the cloud-fraction maximum sits near cloud base (about 500 m; tops up to the inversion at 1500 m)",
     "source": "Siebesma et al. 2003"},
    {"case": "BOMEX (one CM1 run)", "metric": "lwp_g_m2", "lo": 1.95, "hi": 14.16,
     "note": "domain-mean LWP of one CM1 r21.1 run of the case (6.4 km, 100 m grid): 6.35 g/m2 over the last 3 h, "
             "frame means 1.95-14.16; the intercomparison plots LWP (its Fig. 2b) but gives no number in its text",
     "source": "a public CM1 run report of the BOMEX case (Siebesma et al. 2003 set-up)"},
    {"case": "ARM", "metric": "cover_mean", "lo": 0.0, "hi": 0.4,
     "note": "cover peaking just under 0.3 (about 0.4 in a run with a less stable start)",
     "source": "Brown et al. 2002, Q. J. R. Meteorol. Soc. 128, 1075-1093"},
    {"case": "ARM", "metric": "cloud_base_m", "lo": 700.0, "hi": 1200.0,
     "note": "cloud base rising from about 700 m to 1200 m through the afternoon", "source": "Brown et al. 2002"},
    {"case": "ARM", "metric": "cloud_top_m", "lo": 0.0, "hi": 3000.0,
     "note": "tops of 2500-3000 m at most", "source": "Brown et al. 2002"},
)


def shallow_specs(ctx: StudyContext, seeds: int) -> list[runs.RunSpec]:
    """One run of the scene per seed, at the context's particle count, every state of the last step kept."""
    scene = scale_scene(load_scene(SCENE), ctx.scale.particles, ctx.scale.step_fraction)
    every = max(1, scene.time.steps // 20)
    return [runs.RunSpec("particles", scene, backend=ctx.backend, seed=seed, keep_snapshots=1, snapshot_every=every)
            for seed in range(seeds)]


def analyse(result: runs.RunResult, scene) -> tuple[dict, pd.DataFrame, pd.DataFrame]:
    """(metrics, series, time-mean profile) of one run (see the module's docstring)."""
    row = {"stable": bool(result.stable), "step": int(result.step)}
    stats = result.stats().sort_values("step") if result.stable else pd.DataFrame()
    if not len(stats):
        return row, pd.DataFrame(), pd.DataFrame()
    t_end = float(stats["time_s"].max())
    late = stats[stats["time_s"] >= ANALYSIS_FROM * t_end]
    cover = late["cloud_cover"].to_numpy(float)
    onset = stats["time_s"][stats["cloud_cover"] > CLOUDY_COVER]
    means = cloudy_period_means(stats)
    row.update(cover_mean=float(cover.mean()), cover_min=float(cover.min()), cover_max=float(cover.max()),
               in_shallow_range=float(((cover >= SHALLOW_COVER[0]) & (cover <= SHALLOW_COVER[1])).mean()),
               onset_s=float(onset.iloc[0]) if len(onset) else math.nan,
               cloud_base_m=means["cloud_base_mean"], cloud_top_m=means["cloud_top_mean"],
               lwp_g_m2=1e3 * means["lwp_mean"], clouds_end=int(stats["n_objects"].iloc[-1]))
    prof = result.profiles()
    profile = pd.DataFrame()
    if len(prof):
        window = prof[prof["time_s"] >= ANALYSIS_FROM * t_end]
        profile = window.groupby("z", as_index=False)["cloud_fraction"].mean()
        i = int(np.argmax(profile["cloud_fraction"].to_numpy()))
        peak = float(profile["cloud_fraction"].iloc[i])
        row.update(cf_peak=peak, z_cf_peak_m=float(profile["z"].iloc[i]) if peak > 0 else math.nan,
                   cover_to_peak=row["cover_mean"] / peak if peak > 0 else math.nan)
        top = row["cloud_top_m"]
        row["z_cf_peak_over_top"] = row["z_cf_peak_m"] / top if top and math.isfinite(top) else math.nan
    series = stats[["time_s", *SERIES_COLUMNS]].copy()
    return row, series, profile


def with_seed_mean(per_seed: pd.DataFrame, keep=("stable",)) -> pd.DataFrame:
    """`per_seed` (one row per seed, `seed` a string) with a `seed = "mean"` row below: the mean of every
    numeric column; `keep` columns are all-true in the mean row (booleans), other text columns repeat the
    first row's (device, commit, solver)."""
    text = [c for c in per_seed.columns if c != "seed" and c not in keep and per_seed[c].dtype == object]
    numeric = per_seed.drop(columns=["seed", *keep, *text]).apply(pd.to_numeric, errors="coerce")
    mean = {"seed": "mean", **{c: bool(per_seed[c].all()) for c in keep if c in per_seed},
            **{c: per_seed[c].iloc[0] for c in text}, **numeric.mean().to_dict()}
    return pd.concat([per_seed, pd.DataFrame([mean])], ignore_index=True)


def les_table(summary: pd.DataFrame) -> pd.DataFrame:
    """LES_CASES with the scene's seed mean (and seed range) of each metric and whether it lies in the case's
    range."""
    mean = summary[summary["seed"] == "mean"].iloc[0] if len(summary) else None
    seeds = summary[summary["seed"] != "mean"]
    rows = []
    for case in LES_CASES:
        m = case["metric"]
        value = float(mean[m]) if mean is not None and m in mean and pd.notna(mean[m]) else math.nan
        lo_s = float(seeds[m].min()) if m in seeds and len(seeds) else math.nan
        hi_s = float(seeds[m].max()) if m in seeds and len(seeds) else math.nan
        rows.append({**case, "scene_mean": value, "scene_seed_min": lo_s, "scene_seed_max": hi_s,
                     "inside": bool(case["lo"] <= value <= case["hi"]) if math.isfinite(value) else False})
    return pd.DataFrame(rows)


def save_state(result: runs.RunResult, scene, path) -> bool:
    """The run's last state, compact, for renders wherever pyvista is (the GPU machine may have none): every
    cloudy particle and a tenth of the clear ones (position, cloud; cloudpbf.render.compact_particles) and the
    cloud water deposited on the analysis grid. False (and nothing written) where the run stored no state."""
    try:
        state = result.snapshot()
    except FileNotFoundError:
        return False
    grid = statistics.deposit_state(state, scene)
    compact = render.compact_particles(state)
    np.savez_compressed(path, **{f"particle_{k}": v for k, v in compact.items()}, grid_cloud=grid["cloud"],
                        grid_cell_size=np.asarray(grid["cell_size"]), grid_origin=np.asarray(grid["origin"]),
                        time_s=np.asarray(state["time_s"]), particles=np.asarray(len(state["cloud"])))
    return True


def draw(state_path, scene, out_dir) -> dict:
    """Volume and particle renders of a saved state (save_state); a NAME.unavailable.txt note where none can
    be drawn."""
    out_dir.mkdir(parents=True, exist_ok=True)
    volume, particles = out_dir / "shallow_cumulus_volume.png", out_dir / "shallow_cumulus_particles.png"
    if not state_path.is_file():
        for png in (volume, particles):
            runs.atomic_write_text(render.note_path(png), f"no stored state to draw ({state_path.name} is missing)\n")
        return {volume.name: None, particles.name: None}
    with np.load(state_path) as z:
        saved = {k: z[k] for k in z.files}
    state = {k[len("particle_"):]: v for k, v in saved.items() if k.startswith("particle_")}
    state["time_s"] = saved["time_s"]
    title = f"{SCENE}, {int(saved['particles']):,} particles, t = {float(saved['time_s']):.0f} s"
    return {volume.name: render.render_or_note(render.render_volume, volume, saved["grid_cloud"],
                                               tuple(saved["grid_cell_size"]), origin=tuple(saved["grid_origin"])),
            particles.name: render.render_or_note(render.render_particles, particles, state, scene,
                                                  color_by="cloud", title=title)}


def run_shallow_cumulus(ctx: StudyContext, seeds: int | None = None) -> dict[str, pd.DataFrame]:
    """Run the seeds (cached), analyse them, write the CSVs and renders; returns the frames by file stem."""
    seeds = seeds or ctx.scale.shallow_seeds
    specs = shallow_specs(ctx, seeds)
    results = ctx.run_parallel(specs, "shallow_cumulus")
    device, commit = results[0].info.get("device", ""), ctx.commit
    rows, series, profiles = [], [], []
    for spec, res in zip(specs, results):
        row, ser, prof = analyse(res, spec.scene)
        rows.append({"seed": str(spec.seed), "particles": spec.scene.estimated_particles(),
                     "spacing_m": spec.scene.particles.spacing, **row})
        if len(ser):
            series.append(ser.assign(seed=spec.seed))
        if len(prof):
            profiles.append(prof.assign(seed=spec.seed))
    summary = with_seed_mean(pd.DataFrame(rows)).assign(device=device, commit=commit)
    frames = {
        "shallow_cumulus": summary,
        "shallow_cumulus_series": (pd.concat(series, ignore_index=True) if series else pd.DataFrame())
        .assign(device=device, commit=commit),
        "shallow_cumulus_profile": (pd.concat(profiles, ignore_index=True) if profiles else pd.DataFrame())
        .assign(device=device, commit=commit),
        "shallow_cumulus_les": les_table(summary).assign(device=device, commit=commit),
    }
    for stem, frame in frames.items():
        runs.write_csv(frame, ctx.data / f"{stem}.csv")
    state_path = ctx.data / STATE_FILE
    if not save_state(results[0], specs[0].scene, state_path):
        state_path.unlink(missing_ok=True)
    render_state(ctx.data, specs[0].scene, ctx.say)
    return frames


def render_state(data_dir, scene, say=print) -> dict:
    """Draw OUT/data/renders/shallow_cumulus_*.png from OUT/data/shallow_cumulus_state.npz."""
    done = draw(data_dir / STATE_FILE, scene, data_dir / "renders")
    for name, path in done.items():
        say(f"shallow_cumulus: {name}: {'written' if path else 'unavailable (see the note beside it)'}")
    return done


def shallow_cumulus_command(
    seeds: Annotated[Optional[int], typer.Option(min=1, max=1000, help="noise seeds (default: the scale's)")] = None,
    render_only: Annotated[bool, typer.Option(
        "--render-only", help="run nothing: draw the renders from OUT/data/shallow_cumulus_state.npz")] = False,
    out: OutOpt = DEFAULT_OUT, runs_root: RunsRootOpt = None, scale: ScaleOpt = ScaleName.auto,
    backend: BackendOpt = Backend.auto, workers: WorkersOpt = None, scheduler: SchedulerOpt = None,
    quiet: QuietOpt = False, gpus: GpusOpt = None,
) -> None:
    """Shallow cumulus under a capping inversion: cover, cloud-fraction profile and LWP beside BOMEX and ARM."""
    if render_only:
        data = out / "data"
        if not (data / STATE_FILE).is_file():
            raise typer.BadParameter(f"'{data / STATE_FILE}': no saved state to draw (run the study first)",
                                     param_hint="'--out'")
        render_state(data, load_scene(SCENE), typer.echo)
        return
    with study_context(out, runs_root, scale, backend, workers, scheduler, quiet, gpus) as ctx:
        frames = run_shallow_cumulus(ctx, seeds)
    cols = ["seed", "particles", "cover_mean", "in_shallow_range", "cf_peak", "z_cf_peak_m", "cover_to_peak",
            "cloud_base_m", "cloud_top_m", "lwp_g_m2", "clouds_end"]
    summary = frames["shallow_cumulus"]
    typer.echo(summary[[c for c in cols if c in summary]].to_string(index=False))
    les = frames["shallow_cumulus_les"]
    typer.echo(les[["case", "metric", "lo", "hi", "scene_mean", "inside"]].to_string(index=False))
    typer.echo(f"wrote {ctx.data / 'shallow_cumulus.csv'}, shallow_cumulus_series.csv, shallow_cumulus_profile.csv, "
               "shallow_cumulus_les.csv, renders/shallow_cumulus_*.png")


# ---- report: the cumulus under its inversion -----------------------------------------------------
def _shallow_cumulus(inp: Inputs, sec: Section, env: dict | None) -> None:
    """The shallow_cumulus study (cloudpbf.studies.shallow_cumulus): statistics beside the LES cases, renders."""
    summary, path = inp.csv("shallow_cumulus")
    if summary is None:
        _missing(sec, "the shallow-cumulus study (shallow_cumulus.csv)", "shallow_cumulus", inp)
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
            f"The grid baseline on the same scene and seeds ({gpath.name}, cloudpbf run shallow_cumulus --solver grid, "
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


register(Study("shallow-cumulus", order=37, run=lambda ctx, scene: run_shallow_cumulus(ctx),
               sections=("shallow_cumulus",),
               report=(ReportSection("shallow_cumulus", "Shallow cumulus under an inversion", _shallow_cumulus, 57,
                                     "Cumulus"),),
               produces={"shallow_cumulus": "cloudpbf shallow-cumulus --out {out}"},
               outputs=("shallow_cumulus.csv", "shallow_cumulus_series.csv", "shallow_cumulus_profile.csv",
                        "shallow_cumulus_les.csv", STATE_FILE, "renders/shallow_cumulus_volume.png",
                        "renders/shallow_cumulus_particles.png"),
               scale={"shallow_seeds": {"smoke": 1, "cpu": 2, "gpu": 5}},
               command=shallow_cumulus_command))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.shallow_cumulus ARGS`` is ``cloudpbf shallow-cumulus ARGS``."""
    return run_command(shallow_cumulus_command, "shallow-cumulus", argv)


if __name__ == "__main__":
    sys.exit(main())
