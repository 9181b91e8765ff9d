"""The HTML report: ``build_report(OUT)`` turns OUT/data into OUT/index.html.

The package's names load lazily, so a study can use ``bench.report.inference`` (scipy only) without importing
matplotlib and jinja2 with the page's builders."""

__all__ = ["build_report", "report_sections", "SECTIONS", "COMMANDS"]


def __getattr__(name):
    if name in __all__:   # SECTIONS: (id, title) of every section, in page order, from the study registry
        from . import build
        return getattr(build, name)
    raise AttributeError(name)
