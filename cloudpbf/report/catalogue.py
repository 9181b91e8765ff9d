"""What the studies hand the page: their sections, their verdict cards and the commands that make their data.

The report never looks the studies up itself: cloudpbf.studies.page collects these declarations from the study
registry and passes them to :func:`cloudpbf.report.build.build_report` as a :class:`Catalogue`.  Nothing here
imports pandas, matplotlib or jinja2, so a study can declare its report cheaply.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable, Mapping


@dataclass(frozen=True)
class ReportSection:
    """A section of the HTML report.

    id: the anchor in the page (other studies name it in their `sections` to feed it)
    title: its heading
    build: build(inputs, section, env), or "module:function" of it (imported when the report is built)
    order: its place in the page (the page's own sections: summary 5, environment 10000)
    short: its label in the navigation bar (short enough for one row at 1366 px); "": the title
    """
    id: str
    title: str
    build: Callable | str
    order: int
    short: str = ""

    def load(self) -> Callable:
        if callable(self.build):
            return self.build
        module, _, name = self.build.partition(":")
        return getattr(importlib.import_module(module), name)

    @property
    def label(self) -> str:
        return self.short or self.title


@dataclass(frozen=True)
class GlanceCard:
    """A verdict card of the report's first screen.

    build: build(inputs, env, titles) -> cloudpbf.report.glance.Card, or None where the card has nothing to show
      (titles: section id -> title, for links)
    order: its place among the cards
    slot: cards of one slot stand in for each other: the first (by order) that shows data is drawn, else the
      first that says what is missing; "": a slot of its own
    """
    build: Callable
    order: int
    slot: str = ""


@dataclass(frozen=True)
class Catalogue:
    """Everything the studies contribute to the page.

    sections: the studies' report sections (the page adds its summary and environment)
    cards: the verdict cards
    commands: input key -> the command that produces it, with ``{out}`` for the output folder (shown where the
      input is missing)
    study_of_section: section id -> the demo study (a key of demo_status.json) whose outputs feed it
    """
    sections: tuple = ()
    cards: tuple = ()
    commands: Mapping[str, str] = field(default_factory=dict)
    study_of_section: Mapping[str, str] = field(default_factory=dict)
