"""SPH kernels of the solver, evaluated from Python (the C++ functions in csrc/kernels.h).

poly6 W(r, h) = 315 / (64 pi h^9) (h^2 - r^2)^3 for density (eq. 1);
spiky gradient grad W = -45 / (pi h^6) (h - r)^2 r_hat for constraint gradients.
Radii in m, W in 1/m^3, grad W in 1/m^4.
"""
from __future__ import annotations

import numpy as np


def _core():
    from .buildinfo import checked_core
    return checked_core()


def poly6(r, h):
    """W(r, h) in 1/m^3 (vectorised)."""
    return _core().poly6(np.ascontiguousarray(r, dtype=np.float32), float(h))


def spiky_gradient(offsets, h):
    """grad_i W(x_i - x_j, h) for offsets x_i - x_j of shape (N, 3), in 1/m^4."""
    return _core().spiky_gradient(np.ascontiguousarray(offsets, dtype=np.float32), float(h))


def reference_gradient_norm2(h: float, spacing: float, mass: float, rest_density: float) -> float:
    """sum_k |grad_k C_i|^2 / m_k for a particle with a full lattice neighbourhood (1/(kg m^2))."""
    return float(_core().reference_gradient_norm2(float(h), float(spacing), float(mass), float(rest_density)))
