"""The HTML report: ``build_report(OUT)`` turns OUT/data into one self-contained OUT/index.html."""
from .build import COMMANDS, SECTIONS, build_report

__all__ = ["build_report", "SECTIONS", "COMMANDS"]
