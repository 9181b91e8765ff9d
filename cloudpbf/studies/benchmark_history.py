"""The benchmark history: the solver's step time across commits, from the asv results kept in the repository.

``benchmarks/`` (docs/benchmarks.md) records ``SolverStep.time_step`` with asv, one JSON file per commit and
machine under ``benchmarks/results/<machine>/``.  This study reads those files as they are (asv's results
format: ``result_columns`` and, per benchmark, one column list over the product of its parameters), so the
report needs no asv, and lays each machine's commits out in commit order:

    cloudpbf benchmark-history --results benchmarks/results --out reports/gpu

writes OUT/data/benchmark_history.csv: machine, commit, date (the commit's, UTC), backend, scene, particles,
time_ms (asv's median) and its 99% interval (ci_low_ms, ci_high_ms), then, against the machine's previous
commit with the same benchmark, ratio (time / previous time) and change: ``slower`` / ``faster`` where the
ratio passes ``--factor`` and the two 99% intervals do not overlap (asv's own test in ``asv compare``),
else empty.
"""
from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Annotated

import pandas as pd
import typer

from cloudpbf.report import plots
from cloudpbf.report.common import Inputs, Section, _missing, _table
from cloudpbf import runs
from cloudpbf.cli_common import DEFAULT_OUT, OutOpt, click
from cloudpbf.studies.registry import ReportSection, Study, register

OUTPUT = "benchmark_history.csv"
BENCHMARK = "step.SolverStep.time_step"
COLUMNS = ("machine", "commit", "date", "backend", "scene", "particles", "time_ms", "ci_low_ms", "ci_high_ms",
           "ratio", "change")
DEFAULT_RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


class HistoryError(ValueError):
    """A results file that is not an asv results file of the step benchmark (names the file and why)."""


def _unquote(value: str):
    text = str(value).strip("'\"")
    try:
        return int(text)
    except ValueError:
        return text


def read_results_file(path: Path) -> pd.DataFrame:
    """The step benchmark's measured points of one asv results file (one row per measured parameter set)."""
    try:
        data = json.loads(Path(path).read_text())
        columns = data["result_columns"]
        entry = data["results"].get(BENCHMARK)
        commit, date = data["commit_hash"], data["date"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise HistoryError(f"{path}: not an asv results file ({type(exc).__name__}: {exc})") from None
    if entry is None:
        return pd.DataFrame(columns=COLUMNS[:9])
    field = dict(zip(columns, entry))
    params = field.get("params") or []
    if len(params) != 3:
        raise HistoryError(f"{path}: {BENCHMARK} has parameters {params}, expected (backend, scene, particles)")
    combos = list(itertools.product(*params))
    values = field.get("result") or []
    if len(values) != len(combos):
        raise HistoryError(f"{path}: {len(values)} results for {len(combos)} parameter sets")
    low = field.get("stats_ci_99_a") or [None] * len(combos)
    high = field.get("stats_ci_99_b") or [None] * len(combos)
    rows = []
    for (backend, scene, particles), value, lo, hi in zip(combos, values, low, high):
        if value is None or value != value:   # skipped (n/a) or failed
            continue
        rows.append({"machine": Path(path).parent.name, "commit": commit[:8],
                     "date": pd.Timestamp(date, unit="ms", tz="UTC"),
                     "backend": _unquote(backend), "scene": _unquote(scene), "particles": _unquote(particles),
                     "time_ms": 1e3 * value,
                     "ci_low_ms": 1e3 * lo if lo is not None and lo == lo else float("nan"),
                     "ci_high_ms": 1e3 * hi if hi is not None and hi == hi else float("nan")})
    return pd.DataFrame(rows, columns=COLUMNS[:9])


def benchmark_history(results: Path, factor: float = 1.05) -> pd.DataFrame:
    """Every machine's recorded commits in commit order, each benchmark against the previous commit."""
    results = Path(results)
    if not results.is_dir():
        raise HistoryError(f"{results}: no such folder (asv results: benchmarks/results)")
    frames = [read_results_file(p) for p in sorted(results.glob("*/*.json")) if p.name != "machine.json"]
    frames = [f for f in frames if len(f)]
    if not frames:
        return pd.DataFrame(columns=COLUMNS)
    df = pd.concat(frames, ignore_index=True).sort_values(["machine", "backend", "scene", "particles", "date"])
    key = ["machine", "backend", "scene", "particles"]
    prev = df.groupby(key)[["time_ms", "ci_low_ms", "ci_high_ms"]].shift(1)
    df["ratio"] = df["time_ms"] / prev["time_ms"]
    apart_up = df["ci_low_ms"] > prev["ci_high_ms"]
    apart_down = df["ci_high_ms"] < prev["ci_low_ms"]
    df["change"] = ""
    df.loc[(df["ratio"] > factor) & apart_up, "change"] = "slower"
    df.loc[(df["ratio"] < 1.0 / factor) & apart_down, "change"] = "faster"
    df["date"] = df["date"].dt.strftime("%Y-%m-%d %H:%M")
    return df[list(COLUMNS)].reset_index(drop=True)


def run_history(ctx, results: Path = DEFAULT_RESULTS, factor: float = 1.05) -> pd.DataFrame:
    """Write OUT/data/benchmark_history.csv from the kept asv results (nothing where the checkout has none,
    e.g. an installed wheel)."""
    if not Path(results).is_dir():
        return pd.DataFrame(columns=COLUMNS)
    frame = benchmark_history(results, factor)
    runs.write_csv(frame, ctx.data / OUTPUT)
    return frame


def benchmark_history_command(
    results: Annotated[Path, typer.Option(help="asv results folder (one sub-folder per machine)")] = DEFAULT_RESULTS,
    factor: Annotated[float, typer.Option(min=1.0, max=10.0, help="a change is flagged beyond this ratio (and "
                                                                   "when the 99% intervals do not overlap)")] = 1.05,
    out: OutOpt = DEFAULT_OUT,
) -> None:
    """The solver's step time across commits from the kept asv results (benchmark_history.csv)."""
    try:
        frame = benchmark_history(results, factor)
    except HistoryError as exc:
        raise click.BadParameter(str(exc), param_hint="'--results'") from None
    target = Path(out) / "data" / OUTPUT
    runs.write_csv(frame, target)
    changed = frame[frame["change"] != ""]
    typer.echo(f"{len(frame)} measurements of {frame['commit'].nunique()} commits on "
               f"{frame['machine'].nunique()} machines; {len(changed)} changes beyond {factor}x")
    if len(changed):
        typer.echo(changed[["machine", "commit", "backend", "scene", "particles", "time_ms", "ratio", "change"]]
                   .to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    typer.echo(f"wrote {target}")


# ---- report: the solver's step across commits ----------------------------------------------------
def _benchmark_history(inp: Inputs, sec: Section, env: dict | None) -> None:
    df, path = inp.csv("benchmark_history")
    if df is None:
        _missing(sec, "benchmark_history.csv (the solver's step across commits, from the asv results in "
                      "benchmarks/results)", "benchmark_history", inp)
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


register(Study("benchmark-history", order=95, run=lambda ctx, scene: run_history(ctx), outputs=(OUTPUT,),
               command=benchmark_history_command,
               report=(ReportSection("benchmark_history", "Benchmark history (asv)", _benchmark_history, 35,
                                     "History"),),
               produces={"benchmark_history": "cloudpbf benchmark-history --out {out}"}))
