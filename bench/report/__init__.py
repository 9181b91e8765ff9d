"""The HTML report: ``build_report(OUT)`` turns OUT/data into one self-contained OUT/index.html."""
from . import build as _build
from .build import COMMANDS, build_report, report_sections

__all__ = ["build_report", "report_sections", "SECTIONS", "COMMANDS"]


def __getattr__(name):
    if name == "SECTIONS":   # (id, title) of every section, in page order, from the study registry
        return _build.SECTIONS
    raise AttributeError(name)
