"""Where results came from: device, backend, commit, versions (OUT/data/environment.json)."""
from __future__ import annotations

import datetime as _dt
import functools
import importlib.metadata
import os
import platform
import subprocess
import sys
from pathlib import Path

from cloudpbf_io.files import atomic_write_json
from pbf_cuda._version import version

REPO_ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("numpy", "pandas", "pyarrow", "scipy", "jax", "jaxlib", "jax-cfd", "dask", "distributed",
            "matplotlib", "pyvista", "vtk", "jinja2", "typer", "tqdm", "xarray", "h5netcdf", "zarr")
SCALES = ("cpu-smoke", "cpu", "gpu")


def _run(cmd: list[str]) -> str | None:
    try:
        out = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@functools.lru_cache(maxsize=None)
def commit() -> str:
    """Short commit of the repository, '+dirty' when tracked files differ from it; 'unknown' outside git.
    $CLOUDPBF_COMMIT overrides it (a copy of the tree without .git, e.g. on a remote GPU machine)."""
    if os.environ.get("CLOUDPBF_COMMIT"):
        return os.environ["CLOUDPBF_COMMIT"]
    head = _run(["git", "rev-parse", "--short=12", "HEAD"])
    if head is None:
        return "unknown"
    dirty = _run(["git", "status", "--porcelain", "--untracked-files=no"])
    return head + ("+dirty" if dirty else "")


@functools.lru_cache(maxsize=None)
def cpu_name() -> str:
    name = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    name = name or platform.processor() or platform.machine()
    return f"{name} ({os.cpu_count()} threads)"


@functools.lru_cache(maxsize=None)
def gpu_names() -> tuple[str, ...]:
    """Names of the visible NVIDIA GPUs (nvidia-smi; honours CUDA_VISIBLE_DEVICES when it holds indices)."""
    out = _run(["nvidia-smi", "--query-gpu=index,name", "--format=csv,noheader"])
    if not out:
        return ()
    rows = [line.split(",", 1) for line in out.splitlines() if "," in line]
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None and all(v.strip().isdigit() for v in visible.split(",") if v.strip()):
        keep = [v.strip() for v in visible.split(",") if v.strip()]
        rows = [r for r in rows if r[0].strip() in keep]
    return tuple(r[1].strip() for r in rows)


def gpu_count() -> int:
    return len(gpu_names())


def device_description(backend: str) -> str:
    """Human name of the device a backend runs on: the GPU's name for 'cuda', the CPU model for 'cpu'."""
    if backend == "cuda":
        names = gpu_names()
        return names[0] if names else "CUDA device"
    return cpu_name()


def versions() -> dict[str, str | None]:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    out["cloudpbf"] = version()          # package metadata (works from a wheel, not only a checkout)
    return out


def lock_check(path: str | Path | None = None) -> dict | None:
    """Installed versions against the lock file (constraints.txt of the checkout): ``{"file", "matches",
    "differs": {package: {"locked", "installed"}}}``; None where there is no lock file (a wheel install)."""
    path = Path(path) if path is not None else REPO_ROOT / "constraints.txt"
    if not path.is_file():
        return None
    differs = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" not in line:
            continue
        name, locked = (part.strip() for part in line.split("==", 1))
        try:
            installed = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            installed = None
        if installed != locked:
            differs[name] = {"locked": locked, "installed": installed}
    return {"file": path.name, "matches": not differs, "differs": differs}


def environment(scale: str, backend: str) -> dict:
    """The environment.json record: device, backend, commit, date, python, versions, scale."""
    if scale not in SCALES:
        raise ValueError(f"scale = {scale!r}: allowed {', '.join(SCALES)}")
    return {"device": device_description(backend), "backend": backend, "commit": commit(),
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "python": sys.version.split()[0], "platform": platform.platform(), "cpu": cpu_name(),
            "gpus": list(gpu_names()), "versions": versions(), "lock": lock_check(), "scale": scale}


def write_environment(out_dir: str | Path, scale: str, backend: str) -> Path:
    return atomic_write_json(Path(out_dir) / "data" / "environment.json", environment(scale, backend))
