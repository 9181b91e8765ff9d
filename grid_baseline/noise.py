"""2D simplex noise in jax: the ground-heating pattern of eq. 5 on the grid.

The algorithm (Gustavson 2005) is written once, in ``pbf_cuda/noise.py``, over an array
namespace; here it runs in jax.  Checked against the committed table
``tests/data/noise_reference.csv`` (tests/test_grid_noise.py).

Two entry points:

* :func:`simplex2` -- traced jax code, evaluated in the dtype of its inputs.
  In float32 the input coordinates themselves carry a rounding error of
  ~|x| * 6e-8 (1.5e-5 at |x| ~ 256), which the noise amplifies by its slope
  (up to ~3), so far from the origin float32 agrees with float64 to ~1e-4.
* :func:`simplex2_host` -- for coordinates that exist on the host in float64
  (the grid's cell centres): the skew and the integer lattice cell are computed
  in float64 numpy, only the small in-cell offsets (in [0, 1)) are handed to
  the jax kernel, so the result in float32 matches float64 to ~1e-6 for any x.
  The grid uses this once at start-up (the heating pattern does not change).

Output range is about [-1, 1].
"""
from __future__ import annotations

import numpy as np

import jax.numpy as jnp

__all__ = ["simplex2", "simplex2_host", "heating_pattern", "noise_offset_for_seed", "PERMUTATION"]

# The algorithm, the permutation and the gradients are the particle solver's (one implementation).
from pbf_cuda import noise as _reference  # noqa: E402

PERMUTATION = _reference.PERMUTATION.astype(np.int32)


def simplex2(x, y):
    """Simplex noise at (x, y) (noise units), jax, in the floating dtype of the inputs (traceable)."""
    x = jnp.asarray(x)
    y = jnp.asarray(y)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    y = y.astype(x.dtype)
    return _reference.simplex_kernel(*_reference.lattice(x, y, xp=jnp, index_dtype=jnp.int32), xp=jnp)


def simplex2_host(x, y, dtype=jnp.float32):
    """Simplex noise of float64 host coordinates, the cell search in float64 numpy, the rest in jax `dtype`.

    Returns a jax array of `dtype`. Use for coordinates known on the host (grid cell centres).
    """
    ii, jj, x0, y0 = _reference.lattice(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    return _reference.simplex_kernel(jnp.asarray(ii.astype(np.int32)), jnp.asarray(jj.astype(np.int32)),
                                     jnp.asarray(x0, dtype=dtype), jnp.asarray(y0, dtype=dtype), xp=jnp)


def heating_pattern(x, z, frequency, amplitude, offset=(0.0, 0.0), dtype=jnp.float32):
    """Relative ground heating S/S_e = max(0, 1 + amplitude * noise(x f + ox, z f + oy)) (eq. 5).

    x, z: host coordinates in m (float64 numpy); returns a jax array of `dtype`.
    """
    xn = np.asarray(x, dtype=np.float64) * frequency + offset[0]
    zn = np.asarray(z, dtype=np.float64) * frequency + offset[1]
    n = simplex2_host(xn, zn, dtype=dtype)
    return jnp.maximum(0.0, 1.0 + amplitude * n).astype(dtype)


def noise_offset_for_seed(seed: int) -> list[float]:
    """Offset of the heating pattern for a noise seed (noise units): the particle solver's own function."""
    return _reference.noise_offset_for_seed(seed)
