"""Pressure projection on the staggered (MAC) grid, written in jax: exact fast Poisson solve.

Why not ``jax_cfd.base.pressure.projection``: with a wall axis its
``solve_fast_diag`` falls back to a dense (n x n) matrix product on the
non-periodic axis, and ``solve_cg`` is iterative, so after it float32 leaves
~1e-5 relative divergence at the walls.  The discrete Laplacian div(grad p)
of the MAC grid is diagonalised exactly by the FFT along periodic axes and by
the DCT-II along wall axes (homogeneous Neumann for p, no flux through the
wall), so one forward and one inverse transform solve it to rounding:
float64 leaves ~1e-15 relative divergence, float32 ~1e-7.

Array layout (shared with grid_baseline.model): axis 0 = x, 1 = y (up), 2 = z;
scalars at cell centres; velocity component a at the upper face of each cell
along axis a, i.e. offset 1 (jax-cfd's ``grid.cell_faces``).  On a periodic axis
the face at the domain start is the last entry (wrap-around); on a wall axis the
last entry lies on the upper wall and is kept at 0, and the lower-wall face
(also 0) is not stored.
"""
from __future__ import annotations

import numpy as np

import jax.numpy as jnp
from jax.scipy import fft as jfft

__all__ = ["divergence", "laplacian_eigenvalues", "solve_poisson", "gradient_faces", "project",
           "relative_divergence", "zero_wall_faces"]


def _lower_face(u, axis, periodic):
    """The face values one cell down along `axis` (u at offset 0 of each cell)."""
    if periodic:
        return jnp.roll(u, 1, axis=axis)
    zeros = jnp.zeros_like(jnp.take(u, jnp.arange(1), axis=axis))
    return jnp.concatenate([zeros, jnp.take(u, jnp.arange(u.shape[axis] - 1), axis=axis)], axis=axis)


def zero_wall_faces(u, axis, periodic):
    """Set the stored upper-wall face of a wall-normal component to 0 (no-penetration)."""
    if periodic:
        return u
    idx = [slice(None)] * u.ndim
    idx[axis] = -1
    return u.at[tuple(idx)].set(0.0)


def divergence(vel, steps, periodic):
    """Cell-centred divergence (1/s) of the face velocities vel = (ux, uy, uz)."""
    out = None
    for a, (u, h, per) in enumerate(zip(vel, steps, periodic)):
        d = (u - _lower_face(u, a, per)) / h
        out = d if out is None else out + d
    return out


def laplacian_eigenvalues(shape, steps, periodic, dtype):
    """Eigenvalues of the MAC Laplacian in the transformed basis (rfft on the last periodic axis).

    Periodic axis, FFT index m: -(2 sin(pi m / n) / h)^2; wall axis, DCT-II index l: -(2 sin(pi l / 2n) / h)^2.
    Returned with the shape of the transformed array; the constant mode has eigenvalue 0.
    """
    per_axes = [a for a in range(len(shape)) if periodic[a]]
    last = per_axes[-1] if per_axes else None
    total = np.zeros([1] * len(shape))
    for a, (n, h) in enumerate(zip(shape, steps)):
        if periodic[a]:
            m = np.arange(n // 2 + 1) if a == last else np.arange(n)
            lam = -(2.0 * np.sin(np.pi * m / n) / h) ** 2
        else:
            lam = -(2.0 * np.sin(np.pi * np.arange(n) / (2.0 * n)) / h) ** 2
        sh = [1] * len(shape)
        sh[a] = lam.size
        total = total + lam.reshape(sh)
    inv = np.zeros_like(total)
    nz = total != 0.0
    inv[nz] = 1.0 / total[nz]
    return jnp.asarray(inv, dtype=dtype)


def solve_poisson(rhs, inv_eig, periodic):
    """p with div(grad p) = rhs (mean-free part; the constant null mode set to 0)."""
    wall_axes = [a for a in range(rhs.ndim) if not periodic[a]]
    per_axes = [a for a in range(rhs.ndim) if periodic[a]]
    r = rhs
    for a in wall_axes:
        r = jfft.dct(r, type=2, axis=a, norm="ortho")
    if per_axes:
        rh = jnp.fft.rfftn(r, axes=per_axes)
        rh = rh * inv_eig
        r = jnp.fft.irfftn(rh, s=[rhs.shape[a] for a in per_axes], axes=per_axes).astype(rhs.dtype)
    else:
        r = r * inv_eig
    for a in wall_axes:
        r = jfft.idct(r, type=2, axis=a, norm="ortho")
    return r


def gradient_faces(p, steps, periodic):
    """grad p at the faces (the velocity components' positions); 0 on stored wall faces."""
    out = []
    for a, (h, per) in enumerate(zip(steps, periodic)):
        if per:
            g = (jnp.roll(p, -1, axis=a) - p) / h
        else:
            upper = jnp.concatenate([jnp.take(p, jnp.arange(1, p.shape[a]), axis=a),
                                     jnp.take(p, jnp.arange(p.shape[a] - 1, p.shape[a]), axis=a)], axis=a)
            g = (upper - p) / h   # last entry: p - p = 0 on the wall face
        out.append(g)
    return tuple(out)


def project(vel, steps, periodic, inv_eig):
    """Divergence-free part of vel (the pressure is absorbed; returns (vel, p))."""
    vel = tuple(zero_wall_faces(u, a, per) for a, (u, per) in enumerate(zip(vel, periodic)))
    p = solve_poisson(divergence(vel, steps, periodic), inv_eig, periodic)
    grad = gradient_faces(p, steps, periodic)
    return tuple(u - g for u, g in zip(vel, grad)), p


def relative_divergence(vel, steps, periodic):
    """max |div u| * min(h) / max |u|: 0 for a discretely divergence-free field, ~eps after projection."""
    div = divergence(vel, steps, periodic)
    umax = jnp.maximum(jnp.max(jnp.stack([jnp.max(jnp.abs(u)) for u in vel])), jnp.finfo(div.dtype).tiny)
    return jnp.max(jnp.abs(div)) * min(steps) / umax
