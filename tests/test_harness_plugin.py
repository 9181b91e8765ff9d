"""A study is one module (or one folder): adding it adds its command, its report section and its verdict card;
nothing outside it names its builders or its command, so removing it removes it everywhere."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cloudpbf.studies import page, registry

REPO = Path(__file__).resolve().parent.parent
STUDIES = REPO / "cloudpbf" / "studies"

TOY = '''
from pathlib import Path
from typing import Annotated

import typer

from cloudpbf.report.glance import Card
from cloudpbf.studies.registry import GlanceCard, ReportSection, Study, register


def toy_command(out: Annotated[Path, typer.Option("--out")] = Path("toy")) -> None:
    """A toy study."""
    typer.echo(f"toy into {out}")


def toy_section(inp, sec, env):
    toy, _ = inp.csv("toy")
    if toy is None:
        from cloudpbf.report.common import _missing
        _missing(sec, "toy.csv", "toy", inp)
        return
    sec.add("text", f"toy data: {int(toy['value'].sum())}")


def toy_card(inp, env, titles):
    return Card("toy", "The toy verdict", answer="toy answer 42")


register(Study("toy-study", order=999, command=toy_command,
               report=(ReportSection("toy", "A toy section", toy_section, 55, "Toy"),),
               glance=(GlanceCard(toy_card, 25),), produces={"toy": "cloudpbf toy-study --out {out}"}))
'''


@pytest.fixture
def toy_package(tmp_path, monkeypatch):
    """A package `toystudies` with one study module, found through registry.PACKAGES."""
    package = tmp_path / "toystudies"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "toy.py").write_text(TOY)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "PACKAGES", [*registry.PACKAGES, "toystudies"])
    yield tmp_path
    registry._REGISTRY.pop("toy-study", None)
    registry._DISCOVERED.discard("toystudies")
    for name in [m for m in sys.modules if m.startswith("toystudies")]:
        del sys.modules[name]


def _sections(page_html: str) -> dict:
    return {p.split('"', 1)[0]: p for p in page_html.split('<section id="')[1:]}


def test_a_toy_study_appears_in_the_report_with_its_section_card_and_command(toy_package, tmp_path):
    ids = [r.id for r in page.sections()]
    assert ids.index("toy") == ids.index("compare") + 1                 # order 55: after compare (50)
    out = tmp_path / "study"
    (out / "data").mkdir(parents=True)
    html = _sections(page.build_report(out).read_text())
    assert "toy.csv: not run in this study." in html["toy"] and "cloudpbf toy-study --out" in html["toy"]
    assert "toy answer 42" in html["summary"]
    (out / "data" / "toy.csv").write_text("value\n40\n2\n")
    text = page.build_report(out).read_text()
    assert "toy data: 42" in _sections(text)["toy"]
    assert '<a href="#toy" title="A toy section">Toy</a>' in text          # its short title in the navigation


def test_without_the_toy_package_the_study_is_nowhere(tmp_path):
    assert "toy-study" not in [s.name for s in registry.studies()]
    assert "toy" not in [r.id for r in page.sections()]


def test_the_cli_lists_a_study_of_a_package_named_in_cloudpbf_studies(tmp_path):
    package = tmp_path / "toystudies"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "toy.py").write_text(TOY)
    env = dict(os.environ, CLOUDPBF_STUDIES="toystudies",
               PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    code = "import sys; from cloudpbf.cli import main; sys.exit(main(['--help']))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "toy-study" in out.stdout
    code = "import sys; from cloudpbf.cli import main; sys.exit(main(['toy-study', '--out', 'x']))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0 and "toy into x" in out.stdout, out.stderr


# ---- nothing outside a study names its builders or its command --------------------------------------------
def _own_files(study) -> set[Path]:
    """The files of the study: its module, or every module of its folder."""
    module = sys.modules[study.command.__module__ if study.command else study.report[0].load().__module__]
    path = Path(module.__file__).resolve()
    folder = path.parent
    if folder != STUDIES:                                   # a study folder: cloudpbf/studies/<study>/
        while folder.parent != STUDIES:
            folder = folder.parent
        return set(folder.rglob("*.py"))
    return {path}


def _names_and_strings(path: Path) -> tuple[set[str], list[str]]:
    """Identifiers a module uses (names, attributes, imported names) and its string constants but docstrings."""
    tree = ast.parse(path.read_text())
    docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                  if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
                  and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    names, strings = set(), []
    for n in ast.walk(tree):
        if isinstance(n, ast.Name):
            names.add(n.id)
        elif isinstance(n, ast.Attribute):
            names.add(n.attr)
        elif isinstance(n, ast.alias):
            names.add((n.asname or n.name).rpartition(".")[2])
            names.add(n.name.rpartition(".")[2])
        elif isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docstrings:
            strings.append(n.value)
    return names, strings


def test_no_module_outside_a_study_names_its_builders_or_its_command():
    sources = sorted((REPO / "cloudpbf").rglob("*.py"))
    parsed = {p.resolve(): _names_and_strings(p) for p in sources}
    wrong = []
    for study in registry.studies():
        own = _own_files(study)
        builders = {f.__name__ for f in [study.command, *(r.build for r in study.report), *(c.build for c in study.glance)]
                    if callable(f)}
        command = f"cloudpbf {study.name}"
        for path, (names, strings) in parsed.items():
            if path in own:
                continue
            for name in sorted(builders & names):
                wrong.append(f"{path.relative_to(REPO)} names {study.name}'s {name}")
            for text in strings:
                if text == command or text.startswith(command + " "):
                    wrong.append(f"{path.relative_to(REPO)} names the command {text!r}")
    assert not wrong, "\n".join(wrong)


def test_the_report_package_names_no_study_section():
    """cloudpbf/report holds primitives: no section title or short title of a study is written there."""
    texts = "\n".join(p.read_text() for p in (REPO / "cloudpbf" / "report").rglob("*.py"))
    for section in registry.report_sections():
        assert f'"{section.title}"' not in texts, section.title
        assert not section.short or f'"{section.short}"' not in texts, section.short
