"""Matplotlib figures of the report, returned as ``data:image/png;base64`` URIs.

Each function takes the study's DataFrames (columns as in the data layout of
docs/harness.md, "Study outputs") and returns one embedded PNG.  Times are
ms per step (Table 1, scaling) or s (wall time, simulated time); heights are m.
"""
from __future__ import annotations

import base64
import io
import textwrap
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from cloudpbf.paper import PHASES  # noqa: E402
from cloudpbf.pareto import pareto_front  # noqa: E402

PHASE_COLORS = {"pbf": "#4c72b0", "smoothing": "#55a868", "cloud_dynamics": "#c44e52",
                "splitting": "#8172b2", "merging": "#ccb974"}
SERIES_STYLE = {  # (solver, mode) -> colour
    ("particles", "non-adaptive"): "#1f77b4",
    ("particles", "adaptive"): "#ff7f0e",
    ("grid", "grid"): "#2ca02c",
}
DPI = 110


def to_data_uri(fig) -> str:
    """Encode a figure as a PNG data URI and close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def save_png(fig, path, dpi: int = 110):
    """Write a figure to a PNG file (parent folders made), close it, return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def file_uri(path, mime: str) -> str:
    """Any image file (PNG, GIF) as a data URI of the given MIME type."""
    with open(path, "rb") as fh:
        return f"data:{mime};base64," + base64.b64encode(fh.read()).decode("ascii")


def png_file_uri(path) -> str:
    """A PNG file (e.g. a pyvista render) as a data URI."""
    with open(path, "rb") as fh:
        return "data:image/png;base64," + base64.b64encode(fh.read()).decode("ascii")


def image_grid(paths, row_labels: Sequence[str], col_labels: Sequence[str], width_in: float = 11.0) -> str:
    """Renders (PNG files) side by side: ``paths[r][c]`` in row r, column c (None leaves the cell empty),
    one figure with the row and column labels, so that e.g. a peak and the minimum after it of several
    solvers are read in one look."""
    rows, cols = len(paths), len(paths[0])
    first = next(p for row in paths for p in row if p is not None)
    h, w = plt.imread(first).shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(width_in, width_in * rows * h / (cols * w) + 0.4 * rows),
                             squeeze=False)
    for r, row in enumerate(paths):
        for c, path in enumerate(row):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if path is not None:
                ax.imshow(plt.imread(path))
            else:
                ax.text(0.5, 0.5, "not rendered", ha="center", va="center", transform=ax.transAxes)
            if r == 0:
                ax.set_title(col_labels[c], fontsize=10)
            if c == 0:
                ax.set_ylabel(row_labels[r], fontsize=10)
    fig.tight_layout()
    return to_data_uri(fig)


def _color(solver: str, mode: str, fallback_index: int = 0) -> str:
    return SERIES_STYLE.get((solver, mode), f"C{fallback_index % 10}")


# ------------------------------------------------------------------------------------------
# Table 1 phases
# ------------------------------------------------------------------------------------------
def phase_bars(measured: pd.DataFrame, paper: pd.DataFrame | None = None) -> str:
    """Stacked per-phase ms/step for each Table 1 row, measured (and the paper's) side by side."""
    has_paper = paper is not None and len(paper)
    fig, axes = plt.subplots(1, 2 if has_paper else 1, figsize=(11 if has_paper else 6.5, 4.2), squeeze=False)
    frames = [("measured", measured)] + ([("paper (GeForce GTX 780 Ti)", paper)] if has_paper else [])
    for ax, (title, df) in zip(axes[0], frames):
        labels = [f"{r.example}\n{r.mode}" for r in df.itertuples()]
        bottom = np.zeros(len(df))
        for phase in PHASES:
            col = f"{phase}_ms"
            if col not in df.columns:
                continue
            vals = pd.to_numeric(df[col], errors="coerce").fillna(0.0).to_numpy()
            if not vals.any():
                continue
            ax.bar(labels, vals, bottom=bottom, color=PHASE_COLORS[phase], label=phase)
            bottom += vals
        ax.set_ylabel("ms per step")
        ax.set_title(title)
        ax.tick_params(axis="x", labelsize=8)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return to_data_uri(fig)


# ------------------------------------------------------------------------------------------
# scaling
# ------------------------------------------------------------------------------------------
def _loglog_guides(ax, x, y):
    """Dotted lines of slope 1 (linear cost) through the first point."""
    if len(x) and np.all(np.asarray(x) > 0) and np.all(np.asarray(y) > 0):
        xs = np.array([min(x), max(x)], dtype=float)
        ax.plot(xs, y[0] * xs / x[0], ":", color="grey", lw=1, label="linear scaling")


def pbf_scaling_plot(df: pd.DataFrame) -> str:
    """ms per PBF step against particle count (log-log), per device and iteration count."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for i, ((device, iters), g) in enumerate(df.groupby(["device", "iterations"], sort=True)):
        g = g.sort_values("particles")
        x = g["particles"].to_numpy(dtype=float)
        ax.plot(x, g["step_ms"], "o-", color=f"C{i}", label=f"step, {device}, {iters} it.")
        for col, style in (("neighbors_ms", "--"), ("solver_ms", "-.")):
            if col in g and g[col].notna().any():
                ax.plot(x, g[col], style, color=f"C{i}", alpha=0.7, label=f"{col[:-3]}")
        if i == 0:
            _loglog_guides(ax, x, g["step_ms"].to_numpy(dtype=float))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("particles")
    ax.set_ylabel("ms per step")
    ax.set_title("PBF step time")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return to_data_uri(fig)


def benchmark_history_plot(df: pd.DataFrame, machine: str) -> str:
    """ms per step of each recorded commit (commit order) on one machine, one line per backend, scene and
    size, with asv's 99% interval as error bars; slowdowns flagged by the history are ringed."""
    g = df[df["machine"] == machine]
    commits = list(dict.fromkeys(g.sort_values("date")["commit"]))
    where = {c: i for i, c in enumerate(commits)}
    fig, ax = plt.subplots(figsize=(8.0, 5.6))
    for i, ((backend, scene, particles), h) in enumerate(g.groupby(["backend", "scene", "particles"], sort=True)):
        h = h.sort_values("date")
        x = h["commit"].map(where).to_numpy(dtype=float)
        y = h["time_ms"].to_numpy(dtype=float)
        err = np.vstack([y - h["ci_low_ms"].to_numpy(dtype=float), h["ci_high_ms"].to_numpy(dtype=float) - y])
        style = "o-" if scene == "growing" else "s--"
        ax.errorbar(x, y, yerr=np.nan_to_num(np.abs(err)), fmt=style, color=f"C{i % 10}", ms=4, capsize=2,
                    label=f"{backend}, {scene}, {particles:,} particles")
        slow = h["change"] == "slower"
        ax.plot(x[slow.to_numpy()], y[slow.to_numpy()], "o", ms=11, mfc="none", mec="red")
    ax.set_xticks(range(len(commits)), commits, rotation=30, fontsize=8)
    ax.set_yscale("log")
    ax.set_xlabel("commit (oldest left)")
    ax.set_ylabel("ms per step")
    ax.set_title(f"Solver step across commits, {machine}\n(red ring: slower than the commit before)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)
    fig.tight_layout()
    return to_data_uri(fig)


def grid_scaling_plot(df: pd.DataFrame) -> str:
    """ms per grid step against cell count (log-log), per device and dtype."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for i, ((device, dtype), g) in enumerate(df.groupby(["device", "dtype"], sort=True)):
        g = g.sort_values("cells")
        x = g["cells"].to_numpy(dtype=float)
        ax.plot(x, g["step_ms"], "s-", color=f"C{i}", label=f"{device}, {dtype}")
        if i == 0:
            _loglog_guides(ax, x, g["step_ms"].to_numpy(dtype=float))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("grid cells")
    ax.set_ylabel("ms per step")
    ax.set_title("grid baseline step time")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return to_data_uri(fig)


# ------------------------------------------------------------------------------------------
# time series and profiles with seed spread
# ------------------------------------------------------------------------------------------
def seed_spread(df: pd.DataFrame, x: str, y: str, by: Sequence[str] = ("solver", "mode")) -> pd.DataFrame:
    """Mean, min and max of `y` over seeds at each `x`, per group: columns *by, x, mean, lo, hi, n."""
    by = [b for b in by if b in df.columns]
    agg = (df.dropna(subset=[y]).groupby([*by, x], sort=True)[y]
           .agg(mean="mean", lo="min", hi="max", n="count").reset_index())
    return agg


def _band(ax, stats: pd.DataFrame, x: str, label: str, color: str, horizontal: bool = False):
    if horizontal:  # profiles: value on x, height on y
        ax.plot(stats["mean"], stats[x], color=color, label=label)
        ax.fill_betweenx(stats[x], stats["lo"], stats["hi"], color=color, alpha=0.25, lw=0)
    else:
        ax.plot(stats[x], stats["mean"], color=color, label=label)
        ax.fill_between(stats[x], stats["lo"], stats["hi"], color=color, alpha=0.25, lw=0)


def series_name(solver: str, mode: str) -> str:
    """Legend text of a solver/mode group: 'grid' (not 'grid grid'), 'particles adaptive'."""
    solver, mode = str(solver).strip(), str(mode).strip()
    return solver if mode in ("", solver, "all") else f"{solver} {mode}"


def relative_change(df: pd.DataFrame, col: str, by=("solver", "mode", "seed")) -> pd.Series:
    """(x(t) - x(0)) / x(0) of each run (group `by`), x(0) its first time's value: a conserved total's drift
    without the large offset of its absolute value."""
    by = [b for b in by if b in df.columns]
    values = pd.to_numeric(df[col], errors="coerce")
    order = df.sort_values("time_s").index
    first = values.loc[order].groupby([df.loc[order, b] for b in by]).transform("first") if by else \
        pd.Series(values.loc[order].iloc[0], index=order)
    first = first.reindex(df.index)
    return (values - first) / first.where(first != 0)


def _groups(df: pd.DataFrame):
    keys = [k for k in ("solver", "mode") if k in df.columns]
    if not keys:
        yield ("all", "all"), df
        return
    for key, g in df.groupby(keys, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        yield (key + ("",))[:2], g


TIMESERIES_PANELS = (
    ("cloud_cover", "cloud cover (fraction of columns)"),
    ("lwp_mean", "mean liquid water path (kg/m$^2$)"),
    ("cloud_base", "cloud base (m)"),
    ("cloud_top", "cloud top (m)"),
)


def timeseries_plot(df: pd.DataFrame, panels=TIMESERIES_PANELS, title: str | None = None) -> str:
    """Diagnostics against time per solver/mode: mean over seeds, band = min..max over seeds."""
    panels = [(c, l) for c, l in panels if c in df.columns]
    ncol = 2
    nrow = max(1, int(np.ceil(len(panels) / ncol)))
    fig, axes = plt.subplots(nrow, ncol, figsize=(11, 3.4 * nrow), squeeze=False)
    for ax, (col, label) in zip(axes.ravel(), panels):
        for i, ((solver, mode), g) in enumerate(_groups(df)):
            stats = seed_spread(g, "time_s", col, by=())
            n_seeds = g["seed"].nunique() if "seed" in g else 1
            _band(ax, stats, "time_s", f"{series_name(solver, mode)} ({n_seeds} seeds)", _color(solver, mode, i))
        ax.set_xlabel("time (s)")
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return to_data_uri(fig)


def common_last_time(df: pd.DataFrame) -> float:
    """The latest time (s) that every solver/mode group reached."""
    return float(min(g["time_s"].max() for _, g in _groups(df)))


PROFILE_PANELS = (
    ("cloud_fraction", "cloud fraction a$_c$"),
    ("temperature", "temperature T (K)"),
    ("vapor", "vapor v (kg/kg)"),
    ("cloud", "cloud w (kg/kg)"),
)


def profiles_plot(df: pd.DataFrame, time_s: float | None = None) -> str:
    """Vertical profiles at one time (default: the last time every group reached)."""
    if time_s is None:
        time_s = common_last_time(df)
    at = df[np.isclose(df["time_s"], time_s)]
    panels = [(c, l) for c, l in PROFILE_PANELS if c in at.columns]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels) + 1, 4.2), squeeze=False, sharey=True)
    for ax, (col, label) in zip(axes[0], panels):
        for i, ((solver, mode), g) in enumerate(_groups(at)):
            stats = seed_spread(g, "z", col, by=())
            _band(ax, stats, "z", series_name(solver, mode), _color(solver, mode, i), horizontal=True)
        ax.set_xlabel(label)
        ax.grid(True, alpha=0.3)
    axes[0][0].set_ylabel("height z (m)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"horizontal-mean profiles at t = {time_s:g} s (band: min..max over seeds)")
    fig.tight_layout()
    return to_data_uri(fig)


# ------------------------------------------------------------------------------------------
# sweep: run time against error
# ------------------------------------------------------------------------------------------
ERROR_LABELS = {"error_self": "error against the method's finest run\n(relative L2 of cover and profile)",
                "error_other": "error against the other method's finest run\n(relative L2 of cover and profile)"}


def pareto_plot(df: pd.DataFrame, errors: Sequence[str] = ("error_self", "error_other"),
                reference: pd.Series | None = None) -> str:
    """Wall time against error per method (and mode), with the Pareto front of each as a line.

    ``reference`` marks the runs the errors are measured against (default: error_self
    == 0): drawn as dotted vertical lines at their wall time, left out of the fronts.
    """
    if reference is None:
        reference = pd.to_numeric(df["error_self"], errors="coerce") <= 0
    df = df.assign(_reference=np.asarray(reference, dtype=bool))
    errors = [e for e in errors if e in df.columns and df[e].notna().any()]
    fig, axes = plt.subplots(1, len(errors), figsize=(5.8 * len(errors), 4.4), squeeze=False)
    titles = {"error_self": "error against the method's own finest run",
              "error_other": "error against the other method's finest run"}
    markers = "osD^v<>ph"
    keys = [k for k in ("method", "mode") if k in df.columns]
    for ax, err in zip(axes[0], errors):
        for i, (key, g) in enumerate(df.groupby(keys, sort=True)):
            key = key if isinstance(key, tuple) else (key,)
            method, mode = (key + ("",))[:2]
            name = series_name(method, mode)
            color = _color(method, mode, i)
            ref = g["_reference"]
            for j, (param, gp) in enumerate(g[~ref].groupby("parameter", sort=True)):
                ax.scatter(gp["wall_s"], gp[err], color=color, marker=markers[j % len(markers)], alpha=0.75,
                           label=f"{name}: {param}")
            if ref.any():
                for x in g[ref]["wall_s"]:
                    ax.axvline(x, color=color, ls=":", lw=1)
                shown = g[ref & (g[err] > 0)]
                if len(shown):  # a reference has an error against the other method's reference
                    ax.scatter(shown["wall_s"], shown[err], color=color, marker="*", s=140, label=f"{name} reference")
            front = pareto_front(g[~ref & (g[err] > 0)], "wall_s", err)
            if len(front):
                ax.step(front["wall_s"], front[err], where="post", color=color, lw=2, alpha=0.9,
                        label=f"{name} Pareto front")
        values = df[err].dropna()
        if len(values[values > 0]) and (values[values > 0].max() / values[values > 0].min() > 20):
            ax.set_yscale("log")
        walls = df["wall_s"].dropna()
        if len(walls) and (walls > 0).all():
            ax.set_xscale("log")
            ax.set_xlim(walls.min() / 1.3, walls.max() * 1.3)   # reference runs (vertical lines) included
        ax.set_xlabel("wall time (s); dotted: reference runs (zero error)")
        ax.set_ylabel(ERROR_LABELS.get(err, err))
        ax.set_title(titles.get(err, err), fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return to_data_uri(fig)


# ------------------------------------------------------------------------------------------
# stress: stability map
# ------------------------------------------------------------------------------------------
STRIP_LABELS = {"dt": "time step dt (s)", "iterations": "PBF iterations", "heating_rate": "heating S$_e$ (K/s)",
                "alpha_dt": "alpha dt (eq. 9)"}


def stability_map(df: pd.DataFrame, stable_label: str = "stable, not usable") -> str:
    """One row per swept parameter: values on a log axis; green usable, orange stable but not usable
    (the `usable` column, when present; `stable_label` names them), red unstable. Only the kinds present are
    in the legend."""
    params = [p for p in dict.fromkeys(df["parameter"]) if not str(p).startswith("dt x ")]
    fig, axes = plt.subplots(len(params), 1, figsize=(8, 1.3 * len(params) + 0.8), squeeze=False)
    for ax, param in zip(axes[:, 0], params):
        g = df[df["parameter"] == param].sort_values("value")
        values = pd.to_numeric(g["value"], errors="coerce")
        stable = g["stable"].map(_truthy)
        usable = g["usable"].map(_truthy) if "usable" in g.columns else stable
        reason = g["reference_reason"] if "reference_reason" in g.columns else pd.Series("", index=g.index)
        unchecked = reason.fillna("").astype(str).str.startswith("not run: no reference")
        for mask, colour, marker, label in ((stable & usable, "#2ca02c", "o", "usable"),
                                            (stable & ~usable & ~unchecked, "#ff9f1c", "s", stable_label),
                                            (stable & ~usable & unchecked, "#9aa7b4", "s", "stable, usable not checked"),
                                            (~stable, "#d62728", "X", "unstable")):
            if mask.any():
                ax.scatter(values[mask], np.zeros(mask.sum()), s=90, color=colour, marker=marker, label=label)
        for v, ok, reason in zip(values, stable, g.get("reason", pd.Series([""] * len(g)))):
            if not ok and isinstance(reason, str) and reason:
                ax.annotate(reason[:28], (v, 0), xytext=(0, 9), textcoords="offset points", fontsize=6,
                            ha="center", rotation=20, color="#d62728")
        if (values > 0).all() and values.max() / values.min() > 20:
            ax.set_xscale("log")
        ax.set_yticks([])
        ax.set_ylabel(STRIP_LABELS.get(param, param), rotation=0, ha="right", va="center")
        ax.set_ylim(-1, 1.6)
        ax.grid(True, axis="x", which="both", alpha=0.3)
    handles = {}
    for ax in axes[:, 0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    axes[0, 0].legend(handles.values(), handles.keys(), fontsize=7, loc="upper left", ncol=3)
    axes[-1, 0].set_xlabel("parameter value (units in the row label)")
    fig.tight_layout()
    return to_data_uri(fig)


MAP_AXES = {"iterations": "PBF solver iterations", "heating_rate": "ground heating rate S$_e$ (K/s, eq. 5)"}


def stability_map_2d(df: pd.DataFrame, bound: str, energy_limit: float | None = None) -> str:
    """One panel per 2-D map (parameter "dt x <other>"): cells on the (dt, other) grid coloured by the
    largest per-step mean density error (log), red X where the run blew up, and a thick black line
    around the usable cells (the boolean ``usable`` column, never set on an unstable run); `bound` says what
    usable means (cloudpbf.studies.stress.usable_bound_text)."""
    maps = [p for p in dict.fromkeys(df["parameter"]) if isinstance(p, str) and p.startswith("dt x ")]
    fig, axes = plt.subplots(1, len(maps), figsize=(5.8 * len(maps) + 1.2, 4.6), squeeze=False,
                             layout="constrained")
    err_col = "density_error_max" if "density_error_max" in df.columns else "density_error_mean"
    norm = matplotlib.colors.LogNorm(vmin=1e-5, vmax=1.0)
    image = None
    for ax, name in zip(axes[0], maps):
        other = name[len("dt x "):]
        g = df[df["parameter"] == name]
        xs = sorted(pd.to_numeric(g["dt"], errors="coerce").dropna().unique())
        ys = sorted(pd.to_numeric(g[other], errors="coerce").dropna().unique())
        err = np.full((len(ys), len(xs)), np.nan)
        usable = np.zeros((len(ys), len(xs)), dtype=bool)
        for r in g.itertuples():
            i, j = ys.index(float(getattr(r, other))), xs.index(float(r.dt))
            e = pd.to_numeric(getattr(r, err_col), errors="coerce")
            stable = _truthy(r.stable)
            err[i, j] = max(float(e), 1e-5) if stable and np.isfinite(e) else np.nan
            usable[i, j] = stable and _truthy(getattr(r, "usable", False))
            if not stable:
                ax.plot(j, i, "X", color="#d62728", ms=14)
            elif np.isfinite(e):
                ax.text(j, i, f"{100 * float(e):.3g}%", ha="center", va="center", fontsize=8,
                        color="white" if float(e) < 0.03 else "black")
        image = ax.imshow(np.ma.masked_invalid(err), origin="lower", cmap="viridis", norm=norm, aspect="auto")
        for i in range(len(ys)):          # the usable region's boundary: edges between usable and not
            for j in range(len(xs)):
                if not usable[i, j]:
                    continue
                for di, dj, seg in ((0, 1, ([j + .5, j + .5], [i - .5, i + .5])),
                                    (0, -1, ([j - .5, j - .5], [i - .5, i + .5])),
                                    (1, 0, ([j - .5, j + .5], [i + .5, i + .5])),
                                    (-1, 0, ([j - .5, j + .5], [i - .5, i - .5]))):
                    ni, nj = i + di, j + dj
                    if not (0 <= ni < len(ys) and 0 <= nj < len(xs)) or not usable[ni, nj]:
                        ax.plot(*seg, color="black", lw=2.5)
        ax.set_xticks(range(len(xs)), [f"{v:g}" for v in xs])
        ax.set_yticks(range(len(ys)), [f"{v:.3g}" for v in ys])
        ax.set_xlabel("time step dt (s)")
        ax.set_ylabel(MAP_AXES.get(other, other))
        ax.set_title(f"dt against {MAP_AXES.get(other, other).split(' (')[0]}", fontsize=10)
    if image is not None:
        bar = fig.colorbar(image, ax=axes[0].tolist(), shrink=0.9)
        bar.set_label("largest mean density error |rho/rho0 - 1| over the steps")
    fig.suptitle(textwrap.fill(f"inside the black line: usable ({bound}); red X: blew up", 110), fontsize=9)
    return to_data_uri(fig)


def _truthy(value) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes", "stable")
    return bool(value) and not (isinstance(value, float) and np.isnan(value))


# ------------------------------------------------------------------------------------------
# adaptive-pareto: adaptive variants against the uniform front
# ------------------------------------------------------------------------------------------
def adaptive_pareto_plot(configs: pd.DataFrame, noise_floor: float | None = None, excluded=()) -> str:
    """ms/step against the seed-mean error per configuration: uniform runs joined as their Pareto front,
    adaptive variants as points with the seed spread of their error as horizontal bars, and the
    reference seeds' own spread (the noise floor) as a shaded band.  Configurations named in `excluded`
    (left out of the verdict: unstable in some seeds) are drawn with open markers and stay off the front."""
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    d = configs[configs["kind"] != "reference"].dropna(subset=["error", "ms_per_step"])
    uniform = d[d["kind"] == "uniform"]
    front = pareto_front(uniform[~uniform["config"].isin(list(excluded))], "ms_per_step", "error").sort_values("error")
    ax.errorbar(uniform["error"], uniform["ms_per_step"], xerr=uniform["error_seed_spread"], fmt="o",
                color="#444444", capsize=3, label="uniform")
    ax.plot(front["error"], front["ms_per_step"], "-", color="#444444", lw=1, label="uniform front")
    for row in uniform.itertuples():
        ax.annotate(f"{row.spacing_m:g} m", (row.error, row.ms_per_step), textcoords="offset points", xytext=(4, 4),
                    fontsize=8)
    markers = {"paper": "s", "lookahead": "D", "thermal": "^", "heated": "v"}
    for i, (crit, g) in enumerate(d[d["kind"] == "adaptive"].groupby("criterion")):
        out = g["config"].isin(list(excluded))
        for part, face, label in ((g[~out], None, f"adaptive, {crit}"),
                                  (g[out], "none", f"adaptive, {crit}, left out")):
            if len(part):
                ax.errorbar(part["error"], part["ms_per_step"], xerr=part["error_seed_spread"],
                            fmt=markers.get(crit, "^"), color=f"C{i + 1}", mfc=face, capsize=3, label=label)
        for row in g.itertuples():
            ax.annotate(f"{row.spacing_m:g} m", (row.error, row.ms_per_step), textcoords="offset points",
                        xytext=(4, -10), fontsize=8, color=f"C{i + 1}")
    if noise_floor and np.isfinite(noise_floor):
        ax.axvspan(0, noise_floor, color="#dddddd", alpha=0.6, label="seed-noise floor")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("error of the seed mean against the reference (cover, volume, LWP)")
    ax.set_ylabel("ms per step")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return to_data_uri(fig)


# ------------------------------------------------------------------------------------------
# sweep: convergence of both solvers with resolution
# ------------------------------------------------------------------------------------------
CONVERGENCE_PANELS = (("cover_mean", "cloud cover (fraction of columns)"), ("lwp_mean", "mean LWP (kg/m2)"),
                      ("cloud_base_mean", "cloud base (m)"), ("cloud_top_mean", "cloud top (m)"))


def convergence_plot(sweep: pd.DataFrame) -> str | None:
    """Time means over the cloudy period of each resolution run of the sweep (particles: spacing; grid: cell
    size along the longest axis) against that resolution, one panel per statistic, one line per solver;
    None when the sweep has no such columns."""
    runs_ = sweep[sweep["parameter"].isin(["spacing", "cells"])] if "parameter" in sweep else sweep.iloc[:0]
    panels = [(c, label) for c, label in CONVERGENCE_PANELS if c in runs_.columns and runs_[c].notna().any()]
    if "resolution_m" not in runs_.columns or not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4), squeeze=False)
    for ax, (column, label) in zip(axes[0], panels):
        for i, (method, g) in enumerate(runs_.groupby("method", sort=True)):
            g = g.sort_values("resolution_m")
            ax.plot(g["resolution_m"], g[column], "o-", color=f"C{i}", label=method)
        ax.set_xscale("log")
        ax.invert_xaxis()                       # finer to the right
        ax.set_xlabel("particle spacing / grid cell (m)")
        ax.set_ylabel(label)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    return to_data_uri(fig)


# ------------------------------------------------------------------------------------------
# shallow cumulus (cloudpbf.studies.shallow_cumulus)
# ------------------------------------------------------------------------------------------
def shallow_cumulus_plot(series: pd.DataFrame, profile: pd.DataFrame, bands: Sequence[tuple] = ()) -> str:
    """Cover against time per seed with the LES cases' cover ranges shaded (bands: (case, lo, hi)), and the
    time-mean cloud-fraction profile per seed (heights in m)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.0))
    for (case, lo, hi), shade in zip(sorted(bands, key=lambda b: b[1] - b[2]), ("0.85", "#c6dbef", "#d9f0d3")):
        left.axhspan(lo, hi, color=shade, label=f"{case} {lo:g}-{hi:g}")
    for i, (seed, g) in enumerate(series.groupby("seed")):
        left.plot(g["time_s"], g["cloud_cover"], color=f"C{i}", label=f"seed {seed}")
    left.set_xlabel("time (s)")
    left.set_ylabel("cloud cover")
    left.set_ylim(0, 1)
    left.legend(fontsize=7)
    left.grid(True, alpha=0.3)
    for i, (seed, g) in enumerate(profile.groupby("seed")):
        right.plot(g["cloud_fraction"], g["z"], color=f"C{i}", label=f"seed {seed}")
    right.set_xlabel("cloud fraction (time mean, last half)")
    right.set_ylabel("height z (m)")
    right.grid(True, alpha=0.3)
    right.legend(fontsize=7)
    fig.tight_layout()
    return to_data_uri(fig)
