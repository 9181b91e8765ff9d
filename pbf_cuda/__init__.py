"""cloudpbf particle solver: Position Based Fluids clouds on CUDA and on the CPU.

The compiled module `pbf_cuda._core` holds both backends built from one C++
source; this package holds the Python API around it.
"""
import os

# OpenMP threads of the CPU backend sleep instead of spinning while they wait: spinning threads
# slow every step by an order of magnitude as soon as anything else shares the cores.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from ._version import __version__
from .scene import Scene, SceneError, list_scenes, load_scene, scene_from_dict
from .simulation import InstabilityError, Simulation, available_backends

__all__ = [
    "__version__", "Scene", "SceneError", "list_scenes", "load_scene", "scene_from_dict",
    "Simulation", "InstabilityError", "available_backends",
]
