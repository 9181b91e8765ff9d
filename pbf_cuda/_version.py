"""The installed cloudpbf version, from the package metadata (pyproject.toml's ``version``)."""
from __future__ import annotations

import importlib.metadata
import tomllib
from pathlib import Path


def version() -> str:
    """``importlib.metadata.version("cloudpbf")``; in a source tree that was never installed, the version
    in its pyproject.toml; else ``"0+unknown"``."""
    try:
        return importlib.metadata.version("cloudpbf")
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        project = Path(__file__).resolve().parent.parent / "pyproject.toml"
        return str(tomllib.loads(project.read_text())["project"]["version"])
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "0+unknown"


__version__ = version()
