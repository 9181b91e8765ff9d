"""The ``cloudpbf`` console script: runs ``cloudpbf.cli``, or says which extra to install.

The command line needs the ``harness`` extra (typer, pandas, dask, ...); some commands need more
(``grid`` for the grid baseline, ``viz`` for renders and VTK exports, ``io`` for NetCDF/zarr).  A
missing one gives a one-line message naming the extra instead of a traceback (exit code 1).
``cloudpbf --version`` answers before the harness is imported, so it works with no extra installed.
"""
from __future__ import annotations

import sys

from pbf_cuda._version import version

# top-level module -> the extra of pyproject.toml that installs it
EXTRA_OF = {
    "click": "harness", "typer": "harness", "pandas": "harness", "pyarrow": "harness", "matplotlib": "harness",
    "jinja2": "harness", "tqdm": "harness", "dask": "harness", "distributed": "harness", "scipy": "harness",
    "filelock": "harness", "platformdirs": "harness",
    "jax": "grid", "jaxlib": "grid", "jax_cfd": "grid", "tree_math": "grid",
    "pyvista": "viz", "vtk": "viz",
    "xarray": "io", "h5netcdf": "io", "h5py": "io", "zarr": "io",
    "PIL": "harness", "psutil": "harness",        # pillow: matplotlib's dependency
    "dask_cuda": "multigpu", "pysplishsplash": "peers",
}


def missing_extra_message(exc: ModuleNotFoundError) -> str | None:
    """'cloudpbf: ... pip install "cloudpbf[harness]"' for a module an extra provides, else None."""
    top = (exc.name or "").split(".")[0]
    extra = EXTRA_OF.get(top)
    if extra is None:
        return None
    return (f"cloudpbf: this needs the Python package '{top}', which the '{extra}' extra installs:\n"
            f"    pip install \"cloudpbf[{extra}]\"     (or \"cloudpbf[all]\" for everything; from a checkout: "
            f"pip install -e \".[{extra}]\")")


def installed_version() -> str:
    """The distribution's version from its metadata, else (a source tree never installed) pyproject.toml's;
    no import of the harness."""
    return version()


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if args in (["--version"], ["-V"]):
        print(f"cloudpbf {installed_version()}")
        return 0
    try:
        from cloudpbf.cli import main as cli_main  # harness extra (typer)
        return cli_main(argv)
    except ModuleNotFoundError as exc:
        message = missing_extra_message(exc)
        if message is None:
            raise
        print(message, file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
