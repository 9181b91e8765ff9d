"""The studies, each declared once, in its own file.

A study module (or the ``__init__.py`` of a study's folder) ends with ``register(Study(...))``: its name
(the demo's and the CLI's), its place in the demo, how it runs there, its command, its report sections and
verdict cards, the commands that produce its data, and its sizes at every scale (fields of
:class:`cloudpbf.studies.scales.Scale`).  The demo, the scale table, the CLI and the report find the studies
here: :func:`studies` imports every module of the packages in :data:`PACKAGES` once and returns what they
registered, in demo order.  Adding a study is adding its file; removing the file removes it everywhere.
"""
from __future__ import annotations

import importlib
import os
import pkgutil
from dataclasses import dataclass, field
from typing import Any, Callable

from cloudpbf.report.catalogue import GlanceCard, ReportSection

__all__ = ["Study", "ReportSection", "GlanceCard", "register", "studies", "study", "demo_studies",
           "report_sections", "PACKAGES"]

SCALE_NAMES = ("smoke", "cpu", "gpu")


@dataclass(frozen=True)
class Study:
    """One study.

    name: its name in `cloudpbf demo --only` (and its CLI command when it has one)
    order: its place in the demo (timing studies first: nothing else competes for the device)
    run: run(ctx, scene) for the demo (scene: the cloud scene of the demo); None: not in the demo
    sections: ids of the report sections its outputs feed (whatever study owns them)
    outputs: the files it writes under OUT/data
    scale: {field: {"smoke": v, "cpu": v, "gpu": v}}: its sizes, fields of every Scale
    command: a typer command function (the CLI registers it under `name`), or None
    report: the report sections this study owns (cloudpbf.report.catalogue.ReportSection: id, title, builder,
      order, short title); the report shows them in order, whatever study feeds them
    glance: its verdict cards on the report's first screen (cloudpbf.report.catalogue.GlanceCard)
    produces: input key -> the command that produces it (``{out}``: the output folder), shown in the report
      where that input is missing
    """
    name: str
    order: int
    run: Callable[[Any, str], Any] | None = None
    sections: tuple = ()
    outputs: tuple = ()
    scale: dict = field(default_factory=dict)
    command: Callable | None = None
    report: tuple = ()
    glance: tuple = ()
    produces: dict = field(default_factory=dict)

    def __post_init__(self):
        for name, values in self.scale.items():
            if set(values) != set(SCALE_NAMES):
                raise ValueError(f"study {self.name!r}: scale field {name!r} needs a value for each of "
                                 f"{', '.join(SCALE_NAMES)} (has {', '.join(values) or 'none'})")


_REGISTRY: dict[str, Study] = {}
_DISCOVERED: set[str] = set()


def register(study: Study) -> Study:
    """Add a study (its module calls this once, at import)."""
    other = _REGISTRY.get(study.name)
    if other is not None and other.run is not study.run:
        raise ValueError(f"two studies are named {study.name!r}")
    _REGISTRY[study.name] = study
    return study


PACKAGES = ["cloudpbf.studies", *(n.strip() for n in os.environ.get("CLOUDPBF_STUDIES", "").split(",") if n.strip())]
"""The packages whose modules are studies (each module or sub-package imported once, at discovery): cloudpbf.studies,
then those named, comma-separated, in $CLOUDPBF_STUDIES.  A study kept elsewhere (a plug-in, a test's toy study)
is found by naming its package there (for the CLI: ``CLOUDPBF_STUDIES=mystudies cloudpbf --help``) or by adding
it here (the next call of :func:`studies` imports it)."""


def _discover() -> None:
    for name in [n for n in PACKAGES if n not in _DISCOVERED]:
        package = importlib.import_module(name)
        for info in pkgutil.iter_modules(package.__path__):
            importlib.import_module(f"{package.__name__}.{info.name}")   # a module being imported is skipped
        _DISCOVERED.add(name)


def studies() -> tuple[Study, ...]:
    """Every study of cloudpbf.studies, in demo order."""
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
