"""The environment profile T0(y) of section 4 (the air at rest), shared by the scene, the initial state, the
diagnostics and the grid baseline.

The paper's profile is linear, T0(y) = T_g - Gamma y. A capping inversion makes it piecewise linear and
continuous (docs/validation.md, "Shallow cumulus")::

    T0(y) = T_g - Gamma y                               y <= z_i
          = T0(z_i) + dT (y - z_i) / delta              z_i < y <= z_i + delta   (the inversion layer)
          = T0(z_i) + dT - Gamma_a (y - z_i - delta)    above

z_i = ``inversion_height`` (0: no inversion), delta = ``inversion_depth``, dT = ``inversion_strength``,
Gamma_a = ``lapse_rate_above``. Above the inversion the initial vapor may be drier (``vapor_ratio_above``,
the free troposphere over a boundary layer: :func:`vapor_ratio`). The solver's twin is
``pbf_cuda/csrc/environment.h`` (with ``AtmosphereParams::initial_vapor`` in thermodynamics.h).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EnvironmentProfile:
    """T0(y) in K of heights y in m (hashable: the grid baseline keeps it in its static parameters)."""
    ground_temperature: float          # T_g, K
    lapse_rate: float                  # Gamma below the inversion, K/m
    inversion_height: float = 0.0      # z_i, m; 0: no inversion
    inversion_depth: float = 200.0     # delta, m
    inversion_strength: float = 0.0    # dT, K
    lapse_rate_above: float = 6.5e-3   # Gamma_a, K/m

    @classmethod
    def of(cls, atmosphere) -> "EnvironmentProfile":
        """The profile of a scene's [atmosphere] section."""
        a = atmosphere
        return cls(float(a.ground_temperature), float(a.lapse_rate), float(a.inversion_height),
                   float(a.inversion_depth), float(a.inversion_strength), float(a.lapse_rate_above))

    @property
    def has_inversion(self) -> bool:
        return self.inversion_height > 0.0

    @property
    def kinks(self) -> tuple:
        """Heights (m) where the profile changes slope: with the ends of a column, where T0 has its extremes."""
        if not self.has_inversion:
            return ()
        return (self.inversion_height, self.inversion_height + self.inversion_depth)

    def temperature(self, y):
        """T0(y), K (float64 array of y's shape)."""
        y = np.asarray(y, dtype=np.float64)
        linear = self.ground_temperature - self.lapse_rate * y
        if not self.has_inversion:
            return linear
        base = self.ground_temperature - self.lapse_rate * self.inversion_height
        above = y - self.inversion_height
        layer = base + self.inversion_strength * above / self.inversion_depth
        top = base + self.inversion_strength - self.lapse_rate_above * (above - self.inversion_depth)
        return np.where(above <= 0.0, linear, np.where(above <= self.inversion_depth, layer, top))

    def inversion_fraction(self, y):
        """How far y is through the inversion layer: 0 below it (and without an inversion), 1 above it."""
        y = np.asarray(y, dtype=np.float64)
        if not self.has_inversion:
            return np.zeros_like(y)
        return np.clip((y - self.inversion_height) / self.inversion_depth, 0.0, 1.0)

    def lapse(self, y):
        """Gamma(y) = -dT0/dy, K/m (at a kink the lower segment's)."""
        y = np.asarray(y, dtype=np.float64)
        if not self.has_inversion:
            return np.full_like(y, self.lapse_rate)
        above = y - self.inversion_height
        return np.where(above <= 0.0, self.lapse_rate,
                        np.where(above <= self.inversion_depth, -self.inversion_strength / self.inversion_depth,
                                 self.lapse_rate_above))


def vapor_ratio(profile: EnvironmentProfile, below: float, above: float, y):
    """k_v(y) of the initial vapor v0 = k_v A exp(B / (T + C)) (section 5): `below` under a capping inversion,
    `above` over it (the dry free troposphere; < 0: `below` everywhere), blended linearly across its layer."""
    y = np.asarray(y, dtype=np.float64)
    if above < 0.0 or not profile.has_inversion:
        return np.full_like(y, below)
    return below + (above - below) * profile.inversion_fraction(y)
