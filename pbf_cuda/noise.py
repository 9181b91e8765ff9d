"""2D simplex noise (Gustavson, "Simplex noise demystified", 2005), float64 numpy.

The reference for the ground-heating pattern of eq. 5.  The solver's C++ version
(`csrc/noise.h`) and the grid baseline's jax version implement the same
algorithm with the same permutation table; all three are checked against the
committed table `tests/data/noise_reference.csv`.

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
PERM = np.concatenate([PERMUTATION, PERMUTATION])
GRAD2 = np.array([[1, 1], [-1, 1], [1, -1], [-1, -1], [1, 0], [-1, 0], [1, 0], [-1, 0],
                  [0, 1], [0, -1], [0, 1], [0, -1]], dtype=np.float64)
F2 = 0.5 * (np.sqrt(3.0) - 1.0)
G2 = (3.0 - np.sqrt(3.0)) / 6.0


def _corner(gi, x, y):
    t = 0.5 - x * x - y * y
    g = GRAD2[gi]
    contrib = t ** 4 * (g[..., 0] * x + g[..., 1] * y)
    return np.where(t < 0.0, 0.0, contrib)


def simplex2(x, y):
    """Simplex noise at (x, y) (noise units), vectorised over arrays."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    s = (x + y) * F2
    i = np.floor(x + s)
    j = np.floor(y + s)
    t = (i + j) * G2
    x0 = x - (i - t)
    y0 = y - (j - t)
    i1 = (x0 > y0).astype(np.int64)
    j1 = 1 - i1
    x1 = x0 - i1 + G2
    y1 = y0 - j1 + G2
    x2 = x0 - 1.0 + 2.0 * G2
    y2 = y0 - 1.0 + 2.0 * G2
    ii = i.astype(np.int64) & 255
    jj = j.astype(np.int64) & 255
    gi0 = PERM[ii + PERM[jj]] % 12
    gi1 = PERM[ii + i1 + PERM[jj + j1]] % 12
    gi2 = PERM[ii + 1 + PERM[jj + 1]] % 12
    return 70.0 * (_corner(gi0, x0, y0) + _corner(gi1, x1, y1) + _corner(gi2, x2, y2))


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
