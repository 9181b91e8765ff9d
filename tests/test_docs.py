"""Documentation lives in the repository and is checked: a one-screen README whose links resolve, the design
document, no citation of a missing SPEC.md, the documentation site built with ``mkdocs build --strict`` (a
broken link or reference fails), its generated pages made from the current code and data, and an API
reference generated from the docstrings."""
from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def test_no_citation_of_a_missing_spec():
    out = subprocess.run(["git", "grep", "-n", "SPEC.md", "--", ":!tests/test_docs.py"], cwd=REPO,
                         capture_output=True, text=True)
    if out.returncode not in (0, 1):
        pytest.skip("not a git checkout")
    assert out.stdout == "", out.stdout
    design = (REPO / "docs" / "design.md").read_text()
    for section in ("## Architecture", "### One source, two backends", "## Physics, equation by equation",
                    "### Starting parameters", "## Checks", "## Benchmarks and studies"):
        assert section in design
    assert "docs/design.md" in (REPO / "README.md").read_text()


def test_readme_is_one_screen_with_working_links():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    for command in ("scripts/demo.sh", "scripts/test.sh"):
        assert command in text
    # no commit hashes: measured numbers are dated by version (CHANGELOG.md maps versions to commits)
    assert not re.findall(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b", text)
    # every relative link and image exists
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" in target:
            continue
        assert (REPO / target).exists(), f"README links to a missing file: {target}"


def test_code_points_to_docs_not_readme_sections():
    out = subprocess.run(["git", "grep", "-n", "-E", r"README[ ,:]+(\"|Physics|Speed|Adaptive|Shift|Budgets|Deviations)",
                          "--", "cloudpbf_io", "pbf_cuda", "cloudpbf", "grid_baseline", "benchmarks", "tests", "docs", "scripts",
                          ":!tests/test_docs.py"],
                         cwd=REPO, capture_output=True, text=True)
    if out.returncode not in (0, 1):
        pytest.skip("not a git checkout")
    assert out.stdout == "", out.stdout


def test_changelog_keeps_a_changelog():
    text = (REPO / "CHANGELOG.md").read_text()
    assert text.startswith("# Changelog")
    assert "## [Unreleased]" in text
    assert re.search(r"^## \[\d+\.\d+\.\d+\] - \d{4}-\d{2}-\d{2}$", text, re.M)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The documentation site, built once with warnings as errors (offline: no plugin fetches anything)."""
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONWARNINGS="ignore")
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(out)],
                         cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return out


def test_site_builds_strict_with_every_page(site):
    for page in ("index", "install", "tutorial", "report", "developer", "architecture", "design", "physics",
                 "performance", "results", "changelog", "reference/scenes", "reference/cli", "reference/studies",
                 "reference/api"):
        assert (site / f"{page}.html").is_file(), page
    api = (site / "reference" / "api.html").read_text()
    assert "to_pyvista" in api and "GridSimulation" in api


def test_generated_pages_are_made_from_the_current_code_and_data(site):
    """The generated pages are written at build time, so they follow the schema, the commands, the registry
    and the data they were built with: every field, command, study and result file appears."""
    from pbf_cuda import scene as schema
    scenes = (site / "reference" / "scenes.html").read_text()
    for section, cls in schema.SECTIONS.items():
        for f in dataclasses.fields(cls):
            assert f"<code>{f.name}</code>" in scenes, f"{section}.{f.name} missing from the scene reference"
    for name in schema.list_scenes():
        assert f"<code>{name}</code>" in scenes

    import typer
    from cloudpbf.cli import app
    cli = (site / "reference" / "cli.html").read_text()
    group = typer.main.get_command(app)
    for name in group.list_commands(None):
        assert f'id="{name}"' in cli, f"command {name} missing from the CLI reference"

    from cloudpbf.studies.registry import studies
    page = (site / "reference" / "studies.html").read_text()
    for s in studies():
        assert f'id="{s.name}"' in page, f"study {s.name} missing from the studies page"

    results = (site / "results.html").read_text()
    for csv in sorted((REPO / "reports" / "gpu" / "data").glob("*.csv")):
        assert f'id="{csv.stem}"' in results, f"{csv.name} missing from the results page"
    assert "## [Unreleased]" not in (site / "changelog.html").read_text()   # rendered, not raw


@pytest.mark.slow   # ~20 s; the site's mkdocstrings page checks the same docstrings in the quick tier
def test_api_reference_is_generated_from_docstrings(tmp_path):
    pytest.importorskip("pdoc")
    if shutil.which("bash") is None:
        pytest.skip("no bash")
    out = subprocess.run(["bash", str(REPO / "scripts" / "api_docs.sh"), str(tmp_path / "api")], cwd=REPO,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    page = (tmp_path / "api" / "pbf_cuda" / "simulation.html").read_text()
    assert "to_pyvista" in page and "progress" in page
    assert "fields_to_xarray" in (tmp_path / "api" / "cloudpbf_io" / "export.html").read_text()
    assert "read_bgeo" in (tmp_path / "api" / "cloudpbf_io" / "bgeo.html").read_text()
    assert (tmp_path / "api" / "grid_baseline" / "simulation.html").exists()
    assert (tmp_path / "api" / "index.html").exists()
