"""What every section builder shares: the page model (Block, Section), the reader of OUT/data (Inputs, which
knows the command that makes each input), notes on missing inputs, render blocks, table formatting, provenance
and the paper's Table 1."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpbf.paper import PHASES, PAPER_TABLE1, paper_table as _paper_table  # noqa: F401
from . import plots
from .inference import format_ci




# ------------------------------------------------------------------------------------------
# page model
# ------------------------------------------------------------------------------------------
@dataclass
class Block:
    kind: str                  # "image", "table", "note", "text", "kv", "cards"
    content: object = None     # data URI, HTML string, text, [(key, value)] or [glance.Card]
    caption: str = ""
    level: str = "info"        # notes: "missing", "warn", "error", "info", "ok"
    command: str = ""          # notes about missing inputs: the command that makes them
    source: object = None      # images: the file under OUT the picture was read from (a render), if any
    full: str = ""             # images: the full-size file beside the page (relative href), when shrunk


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
    """Reads OUT/data: CSVs, environment.json and renders.  `commands`: input key -> the command that produces
    it, ``{out}`` standing for the output folder (cloudpbf.report.catalogue.Catalogue.commands)."""

    def __init__(self, out_dir: Path, commands: dict | None = None):
        self.out = Path(out_dir)
        self.commands = dict(commands or {})
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


def _command(key: str, inp: Inputs) -> str:
    """The command that produces input `key` in the report's folder ('' where no study declares one)."""
    template = inp.commands.get(key)
    return template.format(out=_shown_path(inp.out)) if template else ""


def _missing(section: Section, what: str, key: str, inp: Inputs) -> None:
    section.add("note", f"{what}: not run in this study.", level="missing", command=_command(key, inp))


def _render_blocks(inp: Inputs, sec: Section, names_captions, key: str = "renders") -> None:
    """One image per (render name, caption) of OUT/data/renders; a note where a render is unavailable (its
    reason) or missing (the command of input `key`)."""
    for name, caption in names_captions:
        png, reason = inp.render(name)
        if png is not None:
            sec.add("image", plots.png_file_uri(png), caption=caption, source=png)
        elif reason is not None:
            sec.add("note", f"{name}: render unavailable: {reason}", level="warn", command=_command(key, inp))
        else:
            _missing(sec, f"render {name}.png", key, inp)


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


class Provenance(str):
    """The text 'device: ...; commit: ...; scale: ...' of the data a section shows, with the values as sets
    (``devices``, ``commits``, ``scales``) for the page's header."""
    devices: tuple = ()
    commits: tuple = ()
    scales: tuple = ()

    @classmethod
    def of(cls, devices=(), commits=(), scales=()) -> "Provenance":
        devices, commits, scales = (tuple(dict.fromkeys(v)) for v in (devices, commits, scales))
        parts = [f"{key}: {', '.join(values)}" for key, values in
                 (("device", devices), ("commit", commits), ("scale", scales)) if values]
        out = cls("; ".join(parts))
        out.devices, out.commits, out.scales = devices, commits, scales
        return out


def short_commit(commit) -> str:
    """A commit as the page prints it: its first 7 hex digits (and '+dirty' where the data says so)."""
    text = str(commit)
    dirty = text.endswith("+dirty")
    text = text[:-len("+dirty")] if dirty else text
    return (text[:7] if all(c in "0123456789abcdef" for c in text.lower()) else text) + ("+dirty" if dirty else "")


def _provenance(*frames: pd.DataFrame | None, env: dict | None = None) -> Provenance:
    """Device, commit and scale of the data shown, from the CSVs' own columns. environment.json fills in
    only for data it describes: a frame without a commit column, or whose commit is environment.json's (a CSV
    of another commit does not inherit the environment's device or scale)."""
    frames = [df for df in frames if df is not None]
    if not frames:
        return Provenance("")
    env = env or {}
    env_commit = short_commit(env["commit"]) if env.get("commit") else None
    found = {"device": [], "commit": [], "scale": []}
    for df in frames:
        commits = ([short_commit(v) for v in df["commit"].dropna().unique()] if "commit" in df.columns else [])
        found["commit"] += commits
        described = not commits or (env_commit is not None and set(commits) == {env_commit})
        for key in ("device", "scale"):
            if key in df.columns and df[key].notna().any():
                found[key] += [str(v) for v in df[key].dropna().unique()]
            elif described and env.get(key):
                found[key].append(str(env[key]))
    if not found["commit"] and env_commit:
        found["commit"].append(env_commit)
    return Provenance.of(found["device"], found["commit"], found["scale"])


def _scale_of(env: dict | None, df: pd.DataFrame | None = None) -> str:
    if df is not None and "scale" in df.columns and df["scale"].notna().any():
        return str(df["scale"].dropna().iloc[0])
    return str((env or {}).get("scale", "unknown"))


def _mean_sd(values: pd.Series) -> str:
    """Mean over seeds with its 95% t-interval: 'mean [lo, hi]' (cloudpbf.report.inference)."""
    if values is None:
        return "–"
    return format_ci(values, digits=4)


def _numeric(df: pd.DataFrame, col: str) -> pd.Series:
    return pd.to_numeric(df[col], errors="coerce") if col in df.columns else pd.Series(np.nan, index=df.index)




def _variant(r) -> str:
    """A Table 1 row's variant name ('' on the paper's rows; older CSVs have no column)."""
    v = r.get("variant") if hasattr(r, "get") else getattr(r, "variant", "")
    return v if isinstance(v, str) else ""


def _non_adaptive_totals(df: pd.DataFrame) -> dict:
    """example -> total ms of its non-adaptive row."""
    rows = df[df["mode"] == "non-adaptive"]
    return dict(zip(rows["example"], pd.to_numeric(rows["total_ms"], errors="coerce")))


def step_time_ratios(df: pd.DataFrame) -> dict:
    """example -> non-adaptive total ms / adaptive total ms, over the paper's rows (no variant). The two runs hold
    different particle counts, so this is a ratio of step times, never a speed-up (the speed-up at equal error
    is the adaptive-pareto and sweep studies')."""
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


