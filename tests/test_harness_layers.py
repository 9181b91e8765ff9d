"""The layers of bench/ point down: every import of a bench module (function-local ones included) goes to a
module of the same layer or a lower one, and no two modules import each other, directly or through others.

    face            bench.cli, bench.cli_runs, bench.console
    studies         bench.studies.<study> (a module or a folder), bench.studies.page, bench.studies.demo,
                    bench.grid_scaling
    study floor     bench.studies.registry, context, scales, adaptive_variants; bench.cli_common
    report          bench.report.* (primitives: never a study)
    execution       bench.execution, bench.runs, bench.export
    store           bench.store.*
    solvers         bench.solvers, bench.render
    analysis        bench.paper, bench.statistics, bench.deposition, bench.pareto, bench.roofline, bench.environment

(docs/architecture.md draws the same map.)"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"

LAYERS = (   # lowest first; a module's layer: the one naming it, else the one whose "package.*" holds it
    ("analysis", ("bench", "bench.paper", "bench.statistics", "bench.deposition", "bench.pareto", "bench.roofline",
                  "bench.environment")),
    ("solvers", ("bench.solvers", "bench.render")),
    ("store", ("bench.store", "bench.store.*")),
    ("execution", ("bench.execution", "bench.runs", "bench.export")),
    ("report", ("bench.report", "bench.report.*")),
    ("study floor", ("bench.studies", "bench.studies.registry", "bench.studies.context", "bench.studies.scales",
                     "bench.studies.adaptive_variants", "bench.cli_common")),
    ("studies", ("bench.studies.*", "bench.grid_scaling")),
    ("face", ("bench.cli", "bench.cli_runs", "bench.console")),
)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(BENCH.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(BENCH.rglob("*.py"))}


def rank(module: str) -> int:
    for i, (_, names) in enumerate(LAYERS):
        if module in names:
            return i
    for i, (_, names) in enumerate(LAYERS):
        if any(n.endswith(".*") and module.startswith(n[:-1]) for n in names):
            return i
    raise AssertionError(f"{module}: in no layer of {__name__}.LAYERS (add it where it belongs)")


def imports(path: Path, known: dict, text: str | None = None) -> set[tuple[str, int]]:
    """(bench module imported, line) of every import in `path` (or in `text`, read as that module), at any depth
    (function-local ones too)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text() if text is None else text)):
        if isinstance(node, ast.Import):
            found |= {(a.name, node.lineno) for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
            for a in node.names:     # `from bench.report import plots`: the module bench.report.plots
                found.add((f"{base}.{a.name}" if f"{base}.{a.name}" in known else base, node.lineno))
    return {(m, line) for m, line in found if m == "bench" or m.startswith("bench.")}


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: {m for m, _ in imports(path, known) if m != name} for name, path in known.items()}


def test_every_module_has_a_layer():
    for name in modules():
        rank(name)


def test_imports_point_down():
    known = modules()
    wrong = []
    for name, path in known.items():
        for target, line in sorted(imports(path, known)):
            if target in known and rank(target) > rank(name):
                wrong.append(f"{path.relative_to(BENCH.parent)}:{line}: {name} ({LAYERS[rank(name)][0]}) imports "
                             f"{target} ({LAYERS[rank(target)][0]})")
    assert not wrong, "imports that point up:\n" + "\n".join(wrong)


def test_no_import_cycles():
    g = graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(g.get(node, ())):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt in g and nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(g):
        if node not in state:
            visit(node)


def test_the_report_never_imports_a_study():
    known = modules()
    for name, path in known.items():
        if name.startswith("bench.report"):
            assert not [m for m, _ in imports(path, known) if m.startswith("bench.studies")], name


def test_the_layer_check_sees_an_upward_import():
    """The check itself: a report module importing a study or the face is caught, function-local or not."""
    known = modules()
    text = "from bench.studies import table1\ndef f():\n    from ..cli import app\n"
    found = {m for m, _ in imports(BENCH / "report" / "common.py", known, text)}
    assert found == {"bench.studies.table1", "bench.cli"}
    assert all(rank(m) > rank("bench.report.common") for m in found)
