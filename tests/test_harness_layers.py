"""The layers of cloudpbf/ point down: every import of a harness module (function-local ones included) goes to a
module of the same layer or a lower one, and no two modules import each other, directly or through others.

    face            cloudpbf.cli, cloudpbf.cli_runs, cloudpbf.console
    studies         cloudpbf.studies.<study> (a module or a folder), cloudpbf.studies.page, cloudpbf.studies.demo,
                    cloudpbf.grid_scaling
    study floor     cloudpbf.studies.registry, context, scales, adaptive_variants, plans; cloudpbf.cli_common
    report          cloudpbf.report.* (primitives: never a study)
    execution       cloudpbf.execution, cloudpbf.runs, cloudpbf.export
    store           cloudpbf.store.*
    solvers         cloudpbf.solvers, cloudpbf.render
    analysis        cloudpbf.paper, cloudpbf.statistics, cloudpbf.deposition, cloudpbf.pareto, cloudpbf.roofline, cloudpbf.environment

(docs/architecture.md draws the same map.)

A function-local import defers an optional extra (cloudpbf.console.EXTRA_OF: its package, or a project module that
imports one at module level) and names that extra in a comment on its line or the line above; anything else is
imported at the top of its module.  Modules that are not optional extras' are found at their module level only.
"""
from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

import pytest

from cloudpbf.console import EXTRA_OF

BENCH = Path(__file__).resolve().parent.parent / "cloudpbf"

LAYERS = (   # lowest first; a module's layer: the one naming it, else the one whose "package.*" holds it
    ("analysis", ("cloudpbf", "cloudpbf.paper", "cloudpbf.statistics", "cloudpbf.deposition", "cloudpbf.pareto", "cloudpbf.roofline",
                  "cloudpbf.environment")),
    ("solvers", ("cloudpbf.solvers", "cloudpbf.render")),
    ("store", ("cloudpbf.store", "cloudpbf.store.*")),
    ("execution", ("cloudpbf.execution", "cloudpbf.runs", "cloudpbf.export")),
    ("report", ("cloudpbf.report", "cloudpbf.report.*")),
    ("study floor", ("cloudpbf.studies", "cloudpbf.studies.registry", "cloudpbf.studies.context", "cloudpbf.studies.scales",
                     "cloudpbf.studies.adaptive_variants", "cloudpbf.studies.plans", "cloudpbf.cli_common")),
    ("studies", ("cloudpbf.studies.*", "cloudpbf.grid_scaling")),
    ("face", ("cloudpbf.cli", "cloudpbf.cli_runs", "cloudpbf.console")),
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
    """(harness module imported, line) of every import in `path` (or in `text`, read as that module), at any depth
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
            for a in node.names:     # `from cloudpbf.report import plots`: the module cloudpbf.report.plots
                found.add((f"{base}.{a.name}" if f"{base}.{a.name}" in known else base, node.lineno))
    return {(m, line) for m, line in found if m == "cloudpbf" or m.startswith("cloudpbf.")}


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
        if name.startswith("cloudpbf.report"):
            assert not [m for m, _ in imports(path, known) if m.startswith("cloudpbf.studies")], name


NOT_STUDIES = ("cloudpbf.studies.page", "cloudpbf.studies.demo")   # the report page and the demo: every study's


def study_of(module: str) -> str | None:
    """The study `module` belongs to (cloudpbf.studies.<study>, a module or a folder), None outside the studies."""
    if module in NOT_STUDIES or not module.startswith("cloudpbf.studies.") or LAYERS[rank(module)][0] != "studies":
        return None
    return ".".join(module.split(".")[:3])


def studies_importing_studies(known: dict, texts: dict | None = None) -> list[str]:
    """Imports of a study from another (`texts`: module -> source read in its place; then only those modules)."""
    wrong = []
    for name, path in known.items():
        if texts is not None and name not in texts:
            continue
        own = study_of(name)
        for target, line in sorted(imports(path, known, (texts or {}).get(name))):
            other = study_of(target) if target in known else None
            if own and other and other != own:
                wrong.append(f"{path.relative_to(BENCH.parent)}:{line}: the study {own} imports the study {other}")
    return wrong


def test_a_study_names_no_other_study():
    """Removing one study's file breaks no other: what two studies share lives below them (cloudpbf.studies.plans)."""
    wrong = studies_importing_studies(modules())
    assert not wrong, "studies that import another study (move what they share below the studies):\n" + \
        "\n".join(wrong)


def test_the_study_check_sees_a_study_importing_another():
    known = modules()
    texts = {"cloudpbf.studies.multigpu": "def f():\n    from cloudpbf.studies.sweep import sweep_plan\n",
             "cloudpbf.studies.cycling": "from cloudpbf.studies import compare\n"}
    wrong = studies_importing_studies(known, texts)
    assert len(wrong) == 2 and "the study cloudpbf.studies.multigpu imports the study cloudpbf.studies.sweep" in wrong[1]
    assert study_of("cloudpbf.studies.time_to_solution.report") == "cloudpbf.studies.time_to_solution"
    assert study_of("cloudpbf.studies.plans") is None and study_of("cloudpbf.studies.page") is None

def test_the_layer_check_sees_an_upward_import():
    """The check itself: a report module importing a study or the face is caught, function-local or not."""
    known = modules()
    text = "from cloudpbf.studies import table1\ndef f():\n    from ..cli import app\n"
    found = {m for m, _ in imports(BENCH / "report" / "common.py", known, text)}
    assert found == {"cloudpbf.studies.table1", "cloudpbf.cli"}
    assert all(rank(m) > rank("cloudpbf.report.common") for m in found)


# ---- function-local imports: optional extras only, each named ---------------------------------------------
PROJECT = ("cloudpbf", "pbf_cuda", "grid_baseline", "cloudpbf_io")   # this repository's packages


def _source(module: str) -> Path | None:
    path = BENCH.parent.joinpath(*module.split("."))
    return path / "__init__.py" if (path / "__init__.py").exists() else path.with_suffix(".py") \
        if path.with_suffix(".py").exists() else None


def _targets(node, path: Path) -> list[str]:
    """The modules an import statement loads (relative imports resolved; `from m import name`: m.name if a
    module, else m)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        name = module_name(path)
        parts = (name if path.name == "__init__.py" else name.rpartition(".")[0]).split(".")
        base = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
    return [f"{base}.{a.name}" if _source(f"{base}.{a.name}") else base for a in node.names]


def _module_level(tree: ast.Module) -> list:
    """The import statements that run when the module is imported (not in functions or `if TYPE_CHECKING`)."""
    found, todo = [], list(tree.body)
    while todo:
        st = todo.pop()
        if isinstance(st, (ast.Import, ast.ImportFrom)):
            found.append(st)
        elif isinstance(st, ast.If) and "TYPE_CHECKING" in ast.unparse(st.test):
            todo += st.orelse
        elif not isinstance(st, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for child in ast.iter_child_nodes(st):
                if isinstance(child, ast.stmt):
                    todo.append(child)
                elif isinstance(child, (ast.ExceptHandler, ast.match_case)):
                    todo += child.body
    return found


@lru_cache(maxsize=None)
def _imported_at_module_level(name: str) -> tuple[str, ...]:
    path = _source(name)
    if path is None:
        return ()
    return tuple(t for node in _module_level(ast.parse(path.read_text())) for t in _targets(node, path))


def extras_of(module: str) -> set[str]:
    """The optional extras importing `module` loads: its own, or those its project modules (and their packages)
    import at module level, at any depth."""
    found, seen, todo = set(), set(), [module]
    while todo:
        name = todo.pop()
        root = name.split(".")[0]
        if root in EXTRA_OF:
            found.add(EXTRA_OF[root])
        elif root in PROJECT and name not in seen:
            seen.add(name)
            parts = name.split(".")
            todo += [".".join(parts[:i]) for i in range(1, len(parts))]           # its packages run first
            todo += _imported_at_module_level(name)
    return found


def local_import_problems(path: Path, text: str | None = None) -> list[str]:
    """Function-local imports of `path` (or of `text`, read as that file) that defer no optional extra or do not
    name it.  An import in the `except ImportError` of a `try` that imports an extra is that extra's fallback."""
    text = path.read_text() if text is None else text
    lines, tree, wrong = text.splitlines(), ast.parse(text), []
    for function in [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]:
        fallback = {}
        for node in ast.walk(function):
            if isinstance(node, ast.Try):
                tried = set().union(*[extras_of(t) for n in node.body if isinstance(n, (ast.Import, ast.ImportFrom))
                                      for t in _targets(n, path)])
                for handler in node.handlers:
                    for n in ast.walk(handler):
                        fallback[id(n)] = tried
        for node in ast.walk(function):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or not node.col_offset:
                continue
            extras = set().union(*[extras_of(t) for t in _targets(node, path)]) or fallback.get(id(node), set())
            where = f"{path.relative_to(BENCH.parent)}:{node.lineno}: {lines[node.lineno - 1].strip()}"
            comment = " ".join(lines[max(0, node.lineno - 2):node.lineno])
            if not extras:
                wrong.append(f"{where}  (no optional extra: import it at the top of the module)")
            elif not any(f"{extra} extra" in comment for extra in extras):
                wrong.append(f"{where}  (name its extra in a comment: {' or '.join(sorted(extras))} extra)")
    return wrong


def test_function_local_imports_defer_a_named_optional_extra():
    wrong = [w for path in modules().values() for w in local_import_problems(path)]
    assert not wrong, "function-local imports that are not an optional extra's:\n" + "\n".join(wrong)


def test_the_local_import_check_sees_a_bad_one():
    """The check itself: a local import of a project module without extras, or an extra's without its name."""
    path = BENCH / "solvers.py"
    assert extras_of("grid_baseline") == {"grid"} and extras_of("cloudpbf.statistics") == {"harness"}
    assert not local_import_problems(path, "def f():\n    # grid extra (jax)\n    from grid_baseline import x\n")
    assert not local_import_problems(path, "def f():\n    try:\n        import filelock  # harness extra\n"
                                           "    except ImportError:\n        import fcntl  # harness extra\n")
    for bad in ("def f():\n    from pbf_cuda.scene import load_scene  # grid extra\n",
                "def f():\n    import json\n",
                "def f():\n    import jax\n",
                "def f():\n    from cloudpbf import statistics  # grid extra\n"):
        assert len(local_import_problems(path, bad)) == 1, bad
