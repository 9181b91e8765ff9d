"""The report of the registered studies: their sections, verdict cards and the commands that produce their
data, collected from the study registry and handed to the page assembly (cloudpbf.report.build).

    cloudpbf report --out OUT      # build OUT/index.html from OUT/data
"""
from __future__ import annotations

from pathlib import Path

from cloudpbf.report import build
from cloudpbf.report.catalogue import Catalogue, ReportSection
from cloudpbf.studies.registry import demo_studies, report_sections, studies

__all__ = ["catalogue", "sections", "build_report"]

ENVIRONMENT_COMMAND = "cloudpbf demo --out {out}"
"""What writes OUT/data/environment.json: every study does; the demo runs them all."""


def catalogue() -> Catalogue:
    """Every registered study's report sections, verdict cards and input commands, and which demo study feeds each
    section (ValueError where two studies declare the same section or input)."""
    commands = {"environment": ENVIRONMENT_COMMAND}
    for s in studies():
        for key, command in s.produces.items():
            if key in commands and commands[key] != command:
                raise ValueError(f"input {key!r} is produced by two commands: {commands[key]!r}, {command!r}")
            commands[key] = command
    return Catalogue(sections=report_sections(), cards=tuple(c for s in studies() for c in s.glance),
                     commands=commands,
                     study_of_section={section: s.name for s in demo_studies() for section in s.sections})


def sections() -> tuple[ReportSection, ...]:
    """Every section of the page, in page order (the page's own summary and environment included)."""
    return build.report_sections(catalogue())


def build_report(out) -> Path:
    """Write OUT/index.html from OUT/data with every registered study's sections; return its path."""
    return build.build_report(out, catalogue())
