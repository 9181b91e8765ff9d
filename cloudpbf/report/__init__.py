"""The HTML report's primitives: the page model, the reader of OUT/data, tables, figures, images, the verdict
cards and the page assembly (``build.build_report(OUT, catalogue)``).  The studies declare their sections
(cloudpbf.report.catalogue); cloudpbf.studies.page hands them to the assembly.  This package never imports the studies.

The package's names load lazily, so a study can use ``cloudpbf.report.inference`` (scipy only) without importing
matplotlib and jinja2 with the page's builders."""

__all__ = ["build_report", "report_sections"]


def __getattr__(name):
    if name in __all__:
        from . import build  # harness extra (matplotlib, pandas)
        return getattr(build, name)
    raise AttributeError(name)
