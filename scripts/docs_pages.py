"""The documentation site's generated pages, made from the code and the data at build time.

MkDocs runs this file as a hook (mkdocs.yml, ``hooks:``): every build writes these pages from what the
repository holds at that moment, so they cannot go stale:

* ``reference/scenes.md``: every scene field from the schema (pbf_cuda/scene.py): unit, range, default, meaning;
  and the shipped scenes with their particle counts and descriptions
* ``reference/cli.md``: every ``cloudpbf`` command with its arguments and options (the typer/click command tree)
* ``reference/studies.md``: every study of the registry (cloudpbf/studies/registry.py): what it runs (its module's
  docstring), what it writes, its report sections, its sizes per scale and what its verdict means
* ``results.md``: a table per CSV of the committed results (reports/gpu/data), with its devices and commits
* ``changelog.md``: CHANGELOG.md of the repository root

``python scripts/docs_pages.py OUTDIR`` writes the same pages into OUTDIR (to read them without a build).
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# The committed result folders the results page is made from (reports/latest is a local, ignored output).
RESULT_DIRS = ("reports/gpu",)

# What each study's verdict or main number means. A study registered without an entry here fails the docs
# build (mkdocs build --strict), so a new study comes with its explanation.
VERDICTS = {
    "table1": "Per-phase milliseconds per step of the paper's four examples (plus the growing study's best adaptive "
              "variant), beside the paper's GTX 780 Ti numbers: the speed-up column is paper time / measured time. "
              "Only GPU-scale rows are comparable with the paper; smaller scales time scaled-down scenes.",
    "scaling": "Milliseconds per step against particle count (and grid cells): how the step grows with size. "
               "Linear growth means the neighbour search and solve stay O(N).",
    "convergence": "Both solvers at several resolutions and seeds: each statistic's order of convergence p of "
                   "S_inf + C h^p with a 90% interval (bootstrap over seeds), or the reason none is determined "
                   "(a flat or non-monotone series, too few resolutions). An order with a narrow interval says the "
                   "statistic converges at that rate; S_inf is the extrapolated value the two solvers should share.",
    "compare": "Particles (non-adaptive, adaptive) against the grid baseline over noise seeds: cloud base, top, "
               "cover and liquid water path with 95% confidence intervals and Welch tests. Agreement within the "
               "intervals means both solvers produce the same clouds; a significant difference names the metric.",
    "cycling": "Counts the full disappear/reappear cycles of the cloud cover in each solver and seed; the verdict "
               "holds when every run shows the expected cycles and the water budget closes over each one.",
    "shallow-cumulus": "Cloud cover, base, top and water path of the capped scene beside the BOMEX and ARM LES "
                       "ranges: inside the ranges means a realistic shallow-cumulus regime.",
    "sweep": "Run time against error for particles and the grid (a Pareto front); the verdict is the speed ratio "
             "of adaptive to uniform particles at equal error in the same box, with the error it was taken at.",
    "adaptive-pareto": "Adaptive against uniform particles at equal error over many seeds: the speed-up of the best "
                       "adaptive variant at the uniform runs' error, with a bootstrap interval over seeds. Above 1 "
                       "adaptivity pays; below 1 a uniform run of the same error is faster.",
    "stress": "The stability map: for dt, iterations, heating rate and alpha*dt, the largest value that stays stable "
              "(no NaN, no runaway speed or density error) and within the accuracy bound.",
    "renders": "No verdict: the report's pictures (clouds, Figure 1, Figure 3, the animation).",
    "adaptive-cost": "Split and merge milliseconds per step at a given adaptive particle count, against the targets "
                     "(splitting <= 0.3 ms, merging <= 1 ms at about 500k particles on a GPU).",
    "pbf-scaling": "Milliseconds per step at large particle counts beside the roofline (the least time the step's "
                   "memory traffic allows): the closer, the better the step uses the GPU.",
    "constant-gravity": "Whether a constant gravity on every particle (the paper's example 2 read literally) makes "
                        "clouds vanish and return: stable or not, density error, largest speed, cloud cover.",
    "multigpu-sweep": "Wall time of the sweep on 1, 2, ... GPUs: the speed-up over one GPU (ideal: the GPU count).",
    "budgets": "Heat and water budgets of both solvers for one scene: each process's warming and the total water; "
               "a closed budget means the terms add up to the change of the mean temperature and water.",
    "cbl": "Mixed-layer depth of the dry convective boundary layer in both solvers against encroachment theory "
           "(h^2 = 2 H t / gamma): within 10% passes.",
    "benchmark-history": "The solver's step time across commits (asv results): each commit against the previous one "
                         "on the same machine, slowdowns flagged.",
    "time-to-solution": "The cheapest settings of the particle solver (spacing, time step or CFL control, iterations, "
                         "adaptivity) that meet an error budget against a fine reference: for the defaults' own error, "
                         "half and twice it, the cheapest stable setting, and the speed-up over the defaults at no "
                         "larger error, with 5-95% intervals over resampled seeds. Above 1 the defaults can be made "
                         "cheaper at the same accuracy.",
    "peers": "cloudpbf's PBF dam break against SPlisHSPlasH's on the same geometry and thread count: the time ratio "
             "(above 1: cloudpbf is faster).",
}


# ---- helpers ----------------------------------------------------------------------------------------
def _cell(value) -> str:
    """A table cell: pipes escaped, newlines folded, numbers to 4 significant digits."""
    if value is None:
        return ""
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        if value.is_integer() and abs(value) < 1e12:
            return str(int(value))
        if 1e4 <= abs(value) < 1e12:
            text = f"{value:.0f}"
        elif value != 0 and (abs(value) >= 1e12 or abs(value) < 1e-3):
            text = f"{value:.3e}"
        else:
            text = f"{value:.4g}"
    else:
        text = str(value)
    return text.replace("|", "\\|").replace("\n", " ").strip()


def _table(header: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in rows]
    return "\n".join(out)


def _docstring_markdown(text: str) -> str:
    """A module docstring as Markdown: reST ``code`` is Markdown code already; indented blocks stay code."""
    return inspect.cleandoc(text or "").replace(":func:", "").replace(":class:", "").replace(":data:", "")


# ---- the scene reference ----------------------------------------------------------------------------
def scene_reference() -> str:
    from pbf_cuda import scene as schema
    lines = ["# Scene reference", "",
             "Generated from the scene schema (`pbf_cuda/scene.py`) at every build of this site. A scene file is "
             "TOML; it names only what differs from the defaults, and `extends = \"growing\"` inherits another "
             "scene. Units are SI (m, s, K, kg, kg/kg); `y` is up. A value outside its range fails with the file, "
             "the field, the value and the range. The sections `atmosphere` and `wave` are optional: present in a "
             "file, they switch cloud physics or the initial wave on.", ""]
    lines += ["## Shipped scenes", "", "`cloudpbf scenes` lists them; `load_scene(\"name\")` loads one.", ""]
    rows = []
    for name in schema.list_scenes():
        scene = schema.load_scene(name)
        kind = "cloud" if scene.thermodynamics else "fluid"
        if scene.adaptive.enabled:
            kind += ", adaptive"
        rows.append([f"`{name}`", f"{scene.estimated_particles():,}", scene.time.steps, f"{scene.time.dt:g}", kind,
                     " ".join(scene.description.split())])
    lines += [_table(["scene", "particles", "steps", "dt (s)", "kind", "description"], rows), ""]
    for section, cls in schema.SECTIONS.items():
        optional = " (optional section)" if section in schema.OPTIONAL_SECTIONS else ""
        lines += [f"## `[{section}]`{optional}", ""]
        if cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "("):
            lines += [" ".join(cls.__doc__.split()), ""]
        rows = []
        for f in dataclasses.fields(cls):
            meta = f.metadata
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            if meta.get("choices"):
                allowed = " / ".join(f"`{c}`" for c in meta["choices"])
            elif meta.get("lo") is not None or meta.get("hi") is not None:
                allowed = f"[{_cell(meta.get('lo'))}, {_cell(meta.get('hi'))}]"
            elif isinstance(default, bool):
                allowed = "true / false"
            else:
                allowed = ""
            if meta.get("length"):
                allowed = f"{meta['length']} values, each {allowed}" if allowed else f"{meta['length']} values"
            shown = "(see meaning)" if default is None else f"`{default!r}`".replace("'", '"')
            if isinstance(default, bool):
                shown = f"`{str(default).lower()}`"
            rows.append([f"`{f.name}`", meta.get("unit", ""), allowed, shown, " ".join(str(meta.get("doc", "")).split())])
        lines += [_table(["field", "unit", "allowed", "default", "meaning"], rows), ""]
    return "\n".join(lines)


# ---- the CLI reference ------------------------------------------------------------------------------
def cli_reference() -> str:
    import click
    import typer
    from cloudpbf.cli import app
    group = typer.main.get_command(app)
    ctx = click.Context(group, info_name="cloudpbf")
    lines = ["# Command line reference", "",
             "Generated from the `cloudpbf` command tree at every build of this site; `cloudpbf COMMAND --help` "
             "prints the same. Lists are comma-separated (`--sizes 250000,1000000`); a bad argument exits with "
             "code 2 and one line naming it.", "",
             "```text", "cloudpbf --version     print the installed version (needs no extra)", "```", ""]
    names = sorted(group.list_commands(ctx))
    lines += ["| command | what it does |", "|---|---|"]
    for name in names:
        cmd = group.get_command(ctx, name)
        lines.append(f"| [`{name}`](#{name}) | {_cell(cmd.get_short_help_str(limit=150))} |")
    lines.append("")
    for name in names:
        cmd = group.get_command(ctx, name)
        sub = click.Context(cmd, info_name=name, parent=ctx)
        usage = " ".join(cmd.collect_usage_pieces(sub))
        lines += [f"## {name}", "", "```text", f"cloudpbf {name} {usage}".rstrip(), "```", ""]
        if cmd.help:
            lines += [inspect.cleandoc(cmd.help).replace("\b\n", ""), ""]
        rows = []
        for param in cmd.params:
            if param.name == "help":
                continue
            if isinstance(param, click.Argument):
                names_ = f"`{param.human_readable_name}`"
            else:
                names_ = ", ".join(f"`{o}`" for o in param.opts + param.secondary_opts)
            type_ = param.type
            if isinstance(type_, click.Choice):
                kind = " / ".join(str(c) for c in type_.choices)
            else:
                kind = getattr(type_, "name", str(type_)).lower()
                if isinstance(param, click.Option) and param.is_flag:
                    kind = "flag"
            default = param.default
            if callable(default) or default is None or (isinstance(param, click.Option) and param.is_flag
                                                        and default is False):
                default = ""
            elif hasattr(default, "value"):
                default = default.value
            help_ = getattr(param, "help", "") or ""
            if param.required:
                help_ = ("(required) " + help_).strip()
            rows.append([names_, kind, f"`{default}`" if default != "" else "", help_])
        if rows:
            lines += [_table(["argument / option", "type", "default", "meaning"], rows), ""]
    return "\n".join(lines)


# ---- the studies ------------------------------------------------------------------------------------
def studies_reference() -> tuple[str, list[str]]:
    """The page, and the names of the studies that have no VERDICTS entry."""
    from cloudpbf.studies.registry import studies
    found = studies()
    missing = [s.name for s in found if s.name not in VERDICTS]
    lines = ["# Studies", "",
             "Generated from the study registry (`cloudpbf/studies/registry.py`) at every build of this site. "
             "`cloudpbf demo` runs the studies marked *demo* in this order at a scale that fits the machine "
             "(`smoke` without a GPU, `gpu` with one); the others run as their own commands. Each writes CSVs "
             "into `OUT/data` (default `reports/latest/data`), which the report reads. Sizes per scale are in "
             "the table under each study.", ""]
    rows = [[f"[`{s.name}`](#{s.name})", "demo" if s.run is not None else "", f"`cloudpbf {s.name}`" if s.command else "",
             ", ".join(f"`{o}`" for o in s.outputs)] for s in found]
    lines += [_table(["study", "in the demo", "command", "writes"], rows), ""]
    for s in found:
        module = importlib.import_module(getattr(s.run or s.command, "__module__", "") or "cloudpbf.studies")
        doc = _docstring_markdown(module.__doc__ or "")
        title, _, body = doc.partition("\n")
        lines += [f"## {s.name}", "", f"**{title.strip()}**", ""]
        lines += [f"**What its verdict means.** {VERDICTS.get(s.name, '(not documented)')}", ""]
        facts = []
        if s.run is not None:
            facts.append(f"runs in `cloudpbf demo` (place {s.order})")
        if s.command is not None:
            facts.append(f"command `cloudpbf {s.name}` ([options](cli.md#{s.name}))")
        if s.outputs:
            facts.append("writes " + ", ".join(f"`{o}`" for o in s.outputs))
        if s.sections or s.report:
            titles = [r.title for r in s.report] or list(s.sections)
            facts.append("report sections: " + ", ".join(titles))
        if facts:
            lines += ["- " + f for f in facts] + [""]
        if s.scale:
            scale_rows = [[f"`{k}`", *(_cell(v[n]) for n in ("smoke", "cpu", "gpu"))] for k, v in sorted(s.scale.items())]
            lines += [_table(["size", "smoke", "cpu", "gpu"], scale_rows), ""]
        if body.strip():
            lines += ["??? note \"What it runs (from its module)\"", ""]
            lines += ["    " + line if line.strip() else "" for line in body.strip("\n").split("\n")] + [""]
    return "\n".join(lines), missing


# ---- the results ------------------------------------------------------------------------------------
MAX_ROWS = 40
MAX_COLUMNS = 10


def results_page() -> str:
    import pandas as pd
    lines = ["# Results", "",
             "Generated from the committed result files (" + ", ".join(f"`{d}/data`" for d in RESULT_DIRS) +
             ") at every build of this site: every number below is read from a CSV, with the device and the "
             "commit that produced it. The HTML report (`reports/gpu/index.html`) draws the same data; "
             "[how to read it](report.md). Tables longer than "
             f"{MAX_ROWS} rows show their first rows; wider ones their first {MAX_COLUMNS} columns.", ""]
    for folder in RESULT_DIRS:
        data = ROOT / folder / "data"
        if not data.is_dir():
            lines += [f"`{folder}/data` is not in this checkout.", ""]
            continue
        files = sorted(data.glob("*.csv"))
        lines += [f"## `{folder}`", "", _table(["file", "rows", "devices", "commits"],
                                               [[f"[`{f.name}`](#{f.stem})", *_provenance(pd.read_csv(f), len_only=True)]
                                                for f in files]), ""]
        for f in files:
            frame = pd.read_csv(f)
            rows, devices, commits = _provenance(frame)
            lines += [f"### {f.stem}", "", f"`{folder}/data/{f.name}`: {rows} rows. Devices: {devices or 'not recorded'}. "
                      f"Commits: {commits or 'not recorded'}.", ""]
            keep = [c for c in frame.columns if c not in ("device", "commit")][:MAX_COLUMNS]
            keep += [c for c in ("device", "commit") if c in frame.columns]
            more = len(frame.columns) - len(keep)
            shown = frame[keep].head(MAX_ROWS)
            lines += [_table([f"`{c}`" for c in keep], shown.astype(object).where(shown.notna(), None).values.tolist()), ""]
            if more > 0 or len(frame) > MAX_ROWS:
                extra = []
                if len(frame) > MAX_ROWS:
                    extra.append(f"{len(frame) - MAX_ROWS} more rows")
                if more > 0:
                    extra.append(f"{more} more columns: " + ", ".join(f"`{c}`" for c in frame.columns if c not in keep))
                lines += ["In the CSV: " + "; ".join(extra) + ".", ""]
    return "\n".join(lines)


def _provenance(frame, len_only: bool = False):
    def values(column):
        if column not in frame.columns:
            return ""
        found = [str(v) for v in frame[column].dropna().unique()]
        if column == "commit":
            found = [v[:12] for v in found]
        found = sorted(set(found))
        if len(found) > 4:
            return ", ".join(found[:4]) + f" and {len(found) - 4} more"
        return ", ".join(found)
    return len(frame), values("device"), values("commit")


# ---- the changelog ----------------------------------------------------------------------------------
def changelog_page() -> str:
    return (ROOT / "CHANGELOG.md").read_text()


def pages() -> dict[str, str]:
    """Every generated page: site path -> Markdown."""
    studies_md, missing = studies_reference()
    if missing:
        raise RuntimeError(f"studies without an entry in VERDICTS (scripts/docs_pages.py): {', '.join(missing)}")
    return {
        "reference/scenes.md": scene_reference(),
        "reference/cli.md": cli_reference(),
        "reference/studies.md": studies_md,
        "results.md": results_page(),
        "changelog.md": changelog_page(),
    }


# Figures of the committed results the pages show, copied into the site under figures/.
FIGURES = ("reports/gpu/cbl_profiles.png", "reports/gpu/budgets.png",
           "reports/gpu/data/renders/shallow_cumulus_particles.png", "reports/gpu/data/renders/clouds_volume.png")


# ---- the MkDocs hook --------------------------------------------------------------------------------
def on_files(files, config):
    from mkdocs.structure.files import File
    for figure in FIGURES:
        source = ROOT / figure
        if source.is_file():
            files.append(File.generated(config, f"figures/{source.name}", abs_src_path=str(source)))
    for path, text in pages().items():
        existing = files.get_file_from_path(path)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, path, content=text))
    return files


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python scripts/docs_pages.py OUTDIR")
    out = Path(sys.argv[1])
    for path, text in pages().items():
        target = out / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
        print(target)
