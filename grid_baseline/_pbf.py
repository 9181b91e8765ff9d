"""Access to the particle solver's pure-Python scene schema and noise reference.

grid_baseline reads the same scene files as the particle solver, through
``pbf_cuda.scene`` and ``pbf_cuda.noise`` (pure Python: stdlib + numpy).  Importing
the ``pbf_cuda`` package also imports its Simulation module; where that fails
(the compiled solver or part of its Python side missing, e.g. on a machine that
only runs the grid baseline), the two files are loaded directly from the source
tree instead, under private module names.  Scene objects are then matched by
their fields (duck typing), never by class identity.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_PBF_DIR = Path(__file__).resolve().parent.parent / "pbf_cuda"


def _load_file(name: str):
    key = f"grid_baseline._pbf_{name}"
    if key in sys.modules:
        return sys.modules[key]
    spec = importlib.util.spec_from_file_location(key, _PBF_DIR / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[key] = mod
    spec.loader.exec_module(mod)
    return mod


try:  # the normal case: the particle solver's package imports
    from pbf_cuda import scene as scene_module  # noqa: F401
    from pbf_cuda import noise as noise_module  # noqa: F401
    from pbf_cuda import files as files_module  # noqa: F401
    from pbf_cuda import export as export_module  # noqa: F401
except Exception:  # pragma: no cover - depends on the state of pbf_cuda on this machine
    for _k in [k for k in sys.modules if k == "pbf_cuda" or k.startswith("pbf_cuda.")]:
        if sys.modules.get(_k) is None or not hasattr(sys.modules[_k], "__file__"):
            sys.modules.pop(_k, None)
    scene_module = _load_file("scene")
    noise_module = _load_file("noise")
    files_module = _load_file("files")
    export_module = _load_file("export")

load_scene = scene_module.load_scene
scene_from_dict = scene_module.scene_from_dict
SceneError = scene_module.SceneError
noise_offset_for_seed = noise_module.noise_offset_for_seed
reference_simplex2 = noise_module.simplex2
atomic_savez = files_module.atomic_savez
fields_to_xarray = export_module.fields_to_xarray


def is_scene(obj) -> bool:
    return all(hasattr(obj, a) for a in ("domain", "particles", "time", "pbf", "atmosphere", "to_dict"))
