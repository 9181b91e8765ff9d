"""Can this build's CUDA kernels run on this machine's GPU?

The compiled module records the CUDA architectures it was built for (CMake syntax: ``86-real`` is
SASS for sm_86, ``90-virtual`` PTX for compute_90, a bare ``80`` both).  A device of compute capability
``cc`` (major * 10 + minor) runs

* SASS built for ``a`` when ``a`` has the same major version and ``a <= cc`` (sm_80 code runs on sm_86),
* PTX built for ``a`` when ``a <= cc`` (the driver compiles it for the device at load time).

Otherwise every launch fails with "no kernel image is available for execution on the device";
:func:`cuda_problem` says so beforehand, naming the device and the compiled architectures.
"""
from __future__ import annotations

__all__ = ["parse_architectures", "supports", "compiled_architectures", "device_capability", "cuda_problem"]


def parse_architectures(text: str) -> list[tuple[int | None, str]]:
    """'75-real,90-virtual,86' -> [(75, 'real'), (90, 'virtual'), (86, 'both')]; names CMake resolves
    itself ('native', 'all', 'all-major') give (None, name)."""
    out = []
    for item in text.replace(";", ",").split(","):
        item = item.strip()
        if not item:
            continue
        number, _, kind = item.partition("-")
        if number.isdigit():
            out.append((int(number), kind or "both"))
        else:
            out.append((None, item))
    return out


def supports(capability: int, architectures: list[tuple[int | None, str]]) -> bool | None:
    """True when a device of this compute capability runs one of the architectures, False when none,
    None when the list holds names that are not numbers (``native``, ``all``): unknown, assume yes."""
    if any(a is None for a, _ in architectures):
        return None
    for arch, kind in architectures:
        if kind in ("real", "both") and arch // 10 == capability // 10 and arch <= capability:
            return True
        if kind in ("virtual", "both") and arch <= capability:
            return True
    return False


def _core():
    from . import _core as core
    return core


def compiled_architectures() -> str:
    """The architectures compiled into this build ('' for a build without CUDA)."""
    core = _core()
    return core.cuda_architectures() if hasattr(core, "cuda_architectures") else ""


def device_capability() -> int | None:
    """Compute capability of CUDA device 0 as major * 10 + minor (90 on an H100), None without one."""
    core = _core()
    if not core.cuda_built() or not hasattr(core, "cuda_device_capability"):
        return None
    cc = int(core.cuda_device_capability())
    return cc if cc >= 0 else None


def _cc_text(cc: int) -> str:
    return f"{cc // 10}.{cc % 10} (sm_{cc})"


def cuda_problem() -> str | None:
    """Why the CUDA backend cannot run here, or None when it can."""
    core = _core()
    if not core.cuda_built():
        return "the module was built without CUDA"
    if core.cuda_device_count() == 0:
        return "no CUDA device is visible"
    cc = device_capability()
    built = compiled_architectures()
    if cc is None or not built:
        return None
    if supports(cc, parse_architectures(built)) is False:
        return (f"the GPU {core.cuda_device_name()!r} has compute capability {_cc_text(cc)}, but this build "
                f"carries CUDA kernels only for {built} (CMake CUDA architectures), so no kernel image "
                f"would run on it; rebuild from source on this machine: "
                f"CUDAARCHS=native pip install --no-build-isolation -e . (or -DCMAKE_CUDA_ARCHITECTURES={cc})")
    return None
