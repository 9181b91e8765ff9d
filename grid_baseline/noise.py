"""2D simplex noise in jax: the ground-heating pattern of eq. 5 on the grid.

Same algorithm (Gustavson 2005), same permutation table and gradient set as the
float64 numpy reference ``pbf_cuda/noise.py``; checked against the committed
table ``tests/data/noise_reference.csv`` (tests/test_grid_noise.py).

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

# Ken Perlin's reference permutation and the 2D gradients, shared with the float64 reference.
from pbf_cuda import noise as _reference  # noqa: E402

PERMUTATION = _reference.PERMUTATION.astype(np.int32)
_PERM = np.concatenate([PERMUTATION, PERMUTATION]).astype(np.int32)
_GRAD2 = _reference.GRAD2
_F2 = _reference.F2
_G2 = _reference.G2


def _corner(gi, x, y):
    g = jnp.asarray(_GRAD2, dtype=x.dtype)[gi]
    t = 0.5 - x * x - y * y
    t2 = t * t
    contrib = t2 * t2 * (g[..., 0] * x + g[..., 1] * y)
    return jnp.where(t < 0.0, jnp.zeros_like(contrib), contrib)


def _kernel(ii, jj, x0, y0):
    """Noise from the lattice cell (ii, jj) (ints, already & 255) and the in-cell offsets x0, y0."""
    dt = x0.dtype
    perm = jnp.asarray(_PERM)
    g2 = jnp.asarray(_G2, dtype=dt)
    i1 = (x0 > y0).astype(jnp.int32)
    j1 = 1 - i1
    x1 = x0 - i1.astype(dt) + g2
    y1 = y0 - j1.astype(dt) + g2
    x2 = x0 - 1.0 + 2.0 * g2
    y2 = y0 - 1.0 + 2.0 * g2
    gi0 = perm[ii + perm[jj]] % 12
    gi1 = perm[ii + i1 + perm[jj + j1]] % 12
    gi2 = perm[ii + 1 + perm[jj + 1]] % 12
    return 70.0 * (_corner(gi0, x0, y0) + _corner(gi1, x1, y1) + _corner(gi2, x2, y2))


def simplex2(x, y):
    """Simplex noise at (x, y) (noise units), jax, in the floating dtype of the inputs (traceable)."""
    x = jnp.asarray(x)
    y = jnp.asarray(y)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    y = y.astype(x.dtype)
    dt = x.dtype
    f2 = jnp.asarray(_F2, dtype=dt)
    g2 = jnp.asarray(_G2, dtype=dt)
    s = (x + y) * f2
    i = jnp.floor(x + s)
    j = jnp.floor(y + s)
    t = (i + j) * g2
    x0 = x - (i - t)
    y0 = y - (j - t)
    # floor values fit int32 for |x| < 2^31; & 255 on two's complement matches numpy's int64 & 255.
    ii = i.astype(jnp.int32) & 255
    jj = j.astype(jnp.int32) & 255
    return _kernel(ii, jj, x0, y0)


def simplex2_host(x, y, dtype=jnp.float32):
    """Simplex noise of float64 host coordinates, the cell search in float64 numpy, the rest in jax `dtype`.

    Returns a jax array of `dtype`. Use for coordinates known on the host (grid cell centres).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    s = (x + y) * _F2
    i = np.floor(x + s)
    j = np.floor(y + s)
    t = (i + j) * _G2
    x0 = x - (i - t)
    y0 = y - (j - t)
    ii = (i.astype(np.int64) & 255).astype(np.int32)
    jj = (j.astype(np.int64) & 255).astype(np.int32)
    return _kernel(jnp.asarray(ii), jnp.asarray(jj), jnp.asarray(x0, dtype=dtype), jnp.asarray(y0, dtype=dtype))


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
