"""2D simplex noise (Gustavson, "Simplex noise demystified", 2005), float64 numpy.

The reference for the ground-heating pattern of eq. 5, and the one Python implementation of the
algorithm: :func:`lattice` and :func:`simplex_kernel` take the array namespace, so the grid
baseline runs the same code in jax.  The solver's C++ version (`csrc/noise.h`) implements the
same algorithm with the same permutation table; both are checked against the committed table
`tests/data/noise_reference.csv`.

Output range is about [-1, 1].
"""
from __future__ import annotations

import numpy as np

# Ken Perlin's reference permutation.
PERMUTATION = np.array([
    151, 160, 137, 91, 90, 15, 131, 13, 201, 95, 96, 53, 194, 233, 7, 225, 140, 36, 103, 30, 69, 142,
    8, 99, 37, 240, 21, 10, 23, 190, 6, 148, 247, 120, 234, 75, 0, 26, 197, 62, 94, 252, 219, 203, 117,
    35, 11, 32, 57, 177, 33, 88, 237, 149, 56, 87, 174, 20, 125, 136, 171, 168, 68, 175, 74, 165, 71,
    134, 139, 48, 27, 166, 77, 146, 158, 231, 83, 111, 229, 122, 60, 211, 133, 230, 220, 105, 92, 41,
    55, 46, 245, 40, 244, 102, 143, 54, 65, 25, 63, 161, 1, 216, 80, 73, 209, 76, 132, 187, 208, 89,
    18, 169, 200, 196, 135, 130, 116, 188, 159, 86, 164, 100, 109, 198, 173, 186, 3, 64, 52, 217, 226,
    250, 124, 123, 5, 202, 38, 147, 118, 126, 255, 82, 85, 212, 207, 206, 59, 227, 47, 16, 58, 17, 182,
    189, 28, 42, 223, 183, 170, 213, 119, 248, 152, 2, 44, 154, 163, 70, 221, 153, 101, 155, 167, 43,
    172, 9, 129, 22, 39, 253, 19, 98, 108, 110, 79, 113, 224, 232, 178, 185, 112, 104, 218, 246, 97,
    228, 251, 34, 242, 193, 238, 210, 144, 12, 191, 179, 162, 241, 81, 51, 145, 235, 249, 14, 239,
    107, 49, 192, 214, 31, 181, 199, 106, 157, 184, 84, 204, 176, 115, 121, 50, 45, 127, 4, 150, 254,
    138, 236, 205, 93, 222, 114, 67, 29, 24, 72, 243, 141, 128, 195, 78, 66, 215, 61, 156, 180,
], dtype=np.int64)
PERM = np.concatenate([PERMUTATION, PERMUTATION]).astype(np.int32)
GRAD2 = np.array([[1, 1], [-1, 1], [1, -1], [-1, -1], [1, 0], [-1, 0], [1, 0], [-1, 0],
                  [0, 1], [0, -1], [0, 1], [0, -1]], dtype=np.float64)
F2 = 0.5 * (np.sqrt(3.0) - 1.0)
G2 = (3.0 - np.sqrt(3.0)) / 6.0


def lattice(x, y, xp=np, index_dtype=np.int64):
    """The simplex cell of (x, y): lattice indices (ii, jj) (& 255, of `index_dtype`) and the in-cell
    offsets (x0, y0), in the floating dtype of x.  `xp`: the array namespace (numpy, or jax.numpy for
    the grid baseline: then floor values fit int32 for |x| < 2^31, and & 255 on two's complement
    matches numpy's int64 & 255)."""
    dt = x.dtype
    s = (x + y) * xp.asarray(F2, dtype=dt)
    i = xp.floor(x + s)
    j = xp.floor(y + s)
    t = (i + j) * xp.asarray(G2, dtype=dt)
    return i.astype(index_dtype) & 255, j.astype(index_dtype) & 255, x - (i - t), y - (j - t)


def _corner(gi, x, y, xp):
    g = xp.asarray(GRAD2, dtype=x.dtype)[gi]
    t = 0.5 - x * x - y * y
    t2 = t * t
    contrib = t2 * t2 * (g[..., 0] * x + g[..., 1] * y)
    return xp.where(t < 0.0, xp.zeros_like(contrib), contrib)


def simplex_kernel(ii, jj, x0, y0, xp=np):
    """Noise from the lattice cell (ii, jj) (ints, already & 255) and the in-cell offsets x0, y0, in
    their dtype; `xp` as in :func:`lattice`.  The one implementation of the algorithm in Python."""
    dt = x0.dtype
    perm = xp.asarray(PERM)
    g2 = xp.asarray(G2, dtype=dt)
    i1 = (x0 > y0).astype(xp.int32)
    j1 = 1 - i1
    x1 = x0 - i1.astype(dt) + g2
    y1 = y0 - j1.astype(dt) + g2
    x2 = x0 - 1.0 + 2.0 * g2
    y2 = y0 - 1.0 + 2.0 * g2
    gi0 = perm[ii + perm[jj]] % 12
    gi1 = perm[ii + i1 + perm[jj + j1]] % 12
    gi2 = perm[ii + 1 + perm[jj + 1]] % 12
    return 70.0 * (_corner(gi0, x0, y0, xp) + _corner(gi1, x1, y1, xp) + _corner(gi2, x2, y2, xp))


def simplex2(x, y):
    """Simplex noise at (x, y) (noise units), float64, vectorised over arrays."""
    return simplex_kernel(*lattice(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)))


def heating_pattern(x, z, frequency, amplitude, offset=(0.0, 0.0)):
    """Relative ground heating S/S_e = max(0, 1 + amplitude * noise(x f + ox, z f + oy)) (eq. 5)."""
    n = simplex2(np.asarray(x) * frequency + offset[0], np.asarray(z) * frequency + offset[1])
    return np.maximum(0.0, 1.0 + amplitude * n)


def noise_offset_for_seed(seed: int) -> list[float]:
    """Offset of the heating pattern for a noise seed (noise units); the same in both solvers."""
    if int(seed) == 0:
        return [0.0, 0.0]
    rng = np.random.default_rng(int(seed))
    return [float(v) for v in rng.uniform(0.0, 256.0, size=2)]
