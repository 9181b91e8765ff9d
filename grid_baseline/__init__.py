"""Grid baseline: a Miyazaki-style cloud model on jax-cfd, run from the particle solver's scene files.

    >>> from grid_baseline import GridSimulation
    >>> sim = GridSimulation("growing", resolution=(32, 32, 32))
    >>> sim.step(50); sim.stats()["total_cloud"]

See grid_baseline/README.md.  Modules: compat (jax-cfd shims), noise (simplex noise in jax),
projection (exact FFT/DCT pressure projection), model (the step), simulation (the API).
"""
from pbf_cuda.protocol import InstabilityError

from .simulation import GridSimulation, grid_shape

__all__ = ["GridSimulation", "InstabilityError", "grid_shape"]
