"""The studies, each declared once, in its own file.

A study module ends with ``register(Study(...))``: its name (the demo's and the CLI's), its place in
the demo, how it runs there, the report sections it feeds, and its sizes at every scale (fields of
:class:`bench.studies.scales.Scale`).  The demo, the scale table, the CLI and the report find the
studies here: :func:`studies` imports every module of ``bench.studies`` once and returns what they
registered, in demo order.  Adding a study is adding its file.
"""
from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass, field
from typing import Any, Callable

__all__ = ["Study", "ReportSection", "register", "studies", "study", "demo_studies", "report_sections"]

SCALE_NAMES = ("smoke", "cpu", "gpu")


@dataclass(frozen=True)
class ReportSection:
    """A section of the HTML report that a study owns.

    id: the anchor in the page (other studies name it in their `sections` to feed it)
    title: its heading
    builder: "module:function" of builder(inputs, section, env), imported only when the report is built
      (so the CLI does not import matplotlib); the report's builders live in bench.report.build
    order: its place in the page (the report's own sections: environment 0, summary 5)
    """
    id: str
    title: str
    builder: str
    order: int

    def load(self) -> Callable:
        module, _, name = self.builder.partition(":")
        return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class Study:
    """One study.

    name: its name in `cloudpbf demo --only` (and its CLI command when it has one)
    order: its place in the demo (timing studies first: nothing else competes for the device)
    run: run(ctx, scene) for the demo (scene: the cloud scene of the demo); None: not in the demo
    sections: ids of the report sections its outputs feed (their builders are the report's)
    outputs: the files it writes under OUT/data
    scale: {field: {"smoke": v, "cpu": v, "gpu": v}}: its sizes, fields of every Scale
    command: a typer command function (the CLI registers it under `name`), or None
    report: the report sections this study owns (ReportSection: id, title, builder, order); the report
      shows them in order, whatever study feeds them
    """
    name: str
    order: int
    run: Callable[[Any, str], Any] | None = None
    sections: tuple = ()
    outputs: tuple = ()
    scale: dict = field(default_factory=dict)
    command: Callable | None = None
    report: tuple = ()

    def __post_init__(self):
        for name, values in self.scale.items():
            if set(values) != set(SCALE_NAMES):
                raise ValueError(f"study {self.name!r}: scale field {name!r} needs a value for each of "
                                 f"{', '.join(SCALE_NAMES)} (has {', '.join(values) or 'none'})")


_REGISTRY: dict[str, Study] = {}
_DISCOVERED = False


def register(study: Study) -> Study:
    """Add a study (its module calls this once, at import)."""
    other = _REGISTRY.get(study.name)
    if other is not None and other.run is not study.run:
        raise ValueError(f"two studies are named {study.name!r}")
    _REGISTRY[study.name] = study
    return study


def _discover() -> None:
    global _DISCOVERED
    if _DISCOVERED:
        return
    import bench.studies as package
    for info in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{package.__name__}.{info.name}")   # a module being imported is skipped
    _DISCOVERED = True


def studies() -> tuple[Study, ...]:
    """Every study of bench.studies, in demo order."""
    _discover()
    return tuple(sorted(_REGISTRY.values(), key=lambda s: (s.order, s.name)))


def demo_studies() -> tuple[Study, ...]:
    """The studies the demo runs, in order."""
    return tuple(s for s in studies() if s.run is not None)


def report_sections() -> tuple[ReportSection, ...]:
    """Every report section some study owns, in page order (ValueError when two own the same id)."""
    found: dict[str, ReportSection] = {}
    for s in studies():
        for section in s.report:
            if section.id in found:
                raise ValueError(f"report section {section.id!r} is owned by two studies")
            found[section.id] = section
    return tuple(sorted(found.values(), key=lambda r: (r.order, r.id)))


def study(name: str) -> Study:
    """The study named `name` (ValueError naming the allowed ones)."""
    found = {s.name: s for s in studies()}
    if name not in found:
        raise ValueError(f"unknown study {name!r}: allowed {', '.join(found)}")
    return found[name]
