"""Small particle states stepped once by the solver, and the same step's terms in numpy (float64).

`one_step` runs the solver (pbf_cuda._core.Solver) on a handful of particles in an empty box (no boundary
particles: nothing but the listed particles interacts) with the scene's parameters and any solver parameter
overridden (csrc/params.h names). The numpy side writes the paper's formulas out directly, pair by pair, from
the kernels of csrc/kernels.h and the level radii h_l = h0 2^(-l/3) of section 5.2, so that a test compares the
solver's pass with an independent evaluation of the same equation.
"""
from __future__ import annotations

import numpy as np

from pbf_cuda import load_scene
from pbf_cuda.simulation import _core, build_params


# ---- the solver on a small state --------------------------------------------------------------
BACKEND = "cpu"   # one_step's backend (the GPU twins of the tests set it to "cuda")


def params_of(scene, capacity: int = 256, **overrides):
    """The solver's Params for `scene` (a name or a Scene) with `overrides` (csrc/params.h names)."""
    if isinstance(scene, str):
        scene = load_scene(scene)
    p = build_params(scene, capacity)
    for k, v in overrides.items():
        setattr(p, k, v)
    return p


def one_step(p, position, velocity, mass, temperature=None, vapor=None, cloud=None, steps: int = 1,
             backend: str | None = None):
    """The state after `steps` steps of a solver with Params p started from the given arrays (no boundary
    particles), ordered by particle id (the solver sorts its particles), with the density array."""
    n = len(position)
    f32 = lambda a: np.ascontiguousarray(a, np.float32)   # noqa: E731
    zeros = np.zeros(n, np.float32)
    s = _core().Solver(p, backend or BACKEND)
    s.set_boundary(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32))
    s.set_fluid(f32(position), f32(velocity), f32(zeros if temperature is None else temperature),
                f32(zeros if vapor is None else vapor), f32(zeros if cloud is None else cloud), f32(mass),
                np.arange(n, dtype=np.uint32))
    s.step(steps)
    pos4, vel4 = s.get_float4("position"), s.get_float4("velocity")
    out = {"position": pos4[:, :3].astype(np.float64), "mass": pos4[:, 3].astype(np.float64),
           "velocity": vel4[:, :3].astype(np.float64), "density": s.get_float("density").astype(np.float64),
           "id": s.get_uint("id")}
    if p.thermodynamics:
        for k in ("temperature", "vapor", "cloud"):
            out[k] = s.get_float(k).astype(np.float64)
    order = np.argsort(out["id"], kind="stable")
    out = {k: v[order] for k, v in out.items()}
    out["solver"] = s
    out["order"] = order          # solver index of the i-th particle by id: s.get_float(name)[order]
    return out


# ---- kernels (csrc/kernels.h) in float64 -----------------------------------------------------------
def poly6(r2, h):
    r2 = np.asarray(r2, np.float64)
    d = np.where(r2 < h * h, h * h - r2, 0.0)
    return 315.0 / (64.0 * np.pi * h ** 9) * d ** 3


def spiky_gradient(r, h):
    """grad_i W(x_i - x_j, h) for r = x_i - x_j, shape (..., 3)."""
    r = np.asarray(r, np.float64)
    rl = np.linalg.norm(r, axis=-1)
    inside = (rl < h) & (rl > 0.0)
    safe = np.where(inside, rl, 1.0)
    coef = np.where(inside, -(45.0 / np.pi) * (h - safe) ** 2 / (h ** 6 * safe), 0.0)
    return coef[..., None] * r


def level_radius(p, mass):
    """h_l = h0 2^(-l/3) with l from m = m0 2^(-l)."""
    level = np.rint(-np.log2(np.asarray(mass, np.float64) / p.mass0))
    return p.h0 * 2.0 ** (-level / 3.0)


def pair_kernels(p, x, mass, adaptive: bool = True):
    """Pairwise r_ij = x_i - x_j (no wrap: the states sit in the middle of the box), W_ij and grad_i W_ij with the
    symmetric kernel of eq. 19 (the mean of the kernels at h_i and h_j), support max(h_i, h_j)."""
    x = np.asarray(x, np.float64)
    h = level_radius(p, mass) if adaptive else np.full(len(x), p.h0)
    r = x[:, None, :] - x[None, :, :]
    r2 = np.einsum("ijk,ijk->ij", r, r)
    hi, hj = h[:, None], h[None, :]
    W = 0.5 * (poly6(r2, hi) + poly6(r2, hj))
    G = 0.5 * (spiky_gradient(r, hi) + spiky_gradient(r, hj))
    return r, r2, W, G, h


# ---- the density constraint (eq. 1-4, 18; Macklin & Mueller eq. 12-14) --------------------------------
def density_lambda(p, x, mass):
    """rho_i, C_i and lambda_i = -C_i / (sum_k |grad_k C_i|^2 / m_k + eps) of eq. 4 with k running over the
    neighbours AND i itself."""
    m = np.asarray(mass, np.float64)
    _, _, W, G, _ = pair_kernels(p, x, m)
    rho = W @ m
    C = rho / p.rest_density - 1.0
    if p.unilateral:
        C = np.maximum(C, 0.0)
    gj = (m[None, :, None] / p.rest_density) * G          # -grad_j C_i = (m_j / rho0) grad W_ij
    grad_i = gj.sum(axis=1)                                # grad_i C_i
    denom = (np.einsum("ik,ik->i", grad_i, grad_i) / m                       # k = i
             + (np.einsum("ijk,ijk->ij", gj, gj) / m[None, :]).sum(axis=1)   # k = j != i
             + p.relaxation)
    lam = np.where(denom > 0.0, -C / denom, 0.0)
    return rho, C, lam


def position_correction(p, x, mass, lam):
    """dp_i = 1/rho0 sum_j (lambda_i m_j / m_i + lambda_j) grad W_ij (no tensile term, no walls)."""
    m = np.asarray(mass, np.float64)
    _, _, _, G, _ = pair_kernels(p, x, m)
    coef = lam[:, None] * m[None, :] / m[:, None] + lam[None, :]
    np.fill_diagonal(coef, 0.0)
    return np.einsum("ij,ijk->ik", coef, G) / p.rest_density


# ---- the velocity projection's Jacobian (pbf_constraints.h) --------------------------------------------
def jacobian(p, x, mass):
    """J (n x 3n): (J u)_i = D_i = 1/rho0 sum_j m_j (u_i - u_j) . grad W_ij, the density's rate of change."""
    m = np.asarray(mass, np.float64)
    n = len(m)
    _, _, _, G, _ = pair_kernels(p, x, m)
    a = (m[None, :, None] / p.rest_density) * G            # a_ij = m_j grad W_ij / rho0
    J = -a                                                 # d D_i / d u_j
    J[np.arange(n), np.arange(n)] = a.sum(axis=1)          # d D_i / d u_i (grad W_ii = 0)
    return J.reshape(n, 3 * n)


def projection_cg(p, x, mass, velocity, iterations: int):
    """The velocity projection as the solver runs it from a zero impulse: Jacobi-preconditioned conjugate
    gradients on (J M^-1 J^T) mu = -J v, v += M^-1 J^T (alpha p) per iteration. Returns (v, mu)."""
    m = np.asarray(mass, np.float64)
    J = jacobian(p, x, m)
    Minv = np.repeat(1.0 / m, 3)
    v = np.asarray(velocity, np.float64).reshape(-1).copy()
    diag = (J * J * Minv[None, :]).sum(axis=1)
    r = -J @ v
    z = np.where(diag > 0, r / np.where(diag > 0, diag, 1.0), 0.0)
    d = z.copy()
    rz = r @ z
    mu = np.zeros(len(m))
    for _ in range(iterations):
        g = Minv * (J.T @ d)
        q = J @ g
        pAp = d @ q
        if not pAp > 0:
            break
        alpha = rz / pAp
        v += alpha * g
        r -= alpha * q
        mu += alpha * d
        z = np.where(diag > 0, r / np.where(diag > 0, diag, 1.0), 0.0)
        rz_new = r @ z
        d = z + (rz_new / rz) * d
        rz = rz_new
    return v.reshape(-1, 3), mu


# ---- small states ------------------------------------------------------------------------------------
def mixed_cluster(p, rng, n0: int = 6, n1: int = 10, n2: int = 0, spread: float = 0.9, centre=None):
    """A compact cluster of level-0, level-1 (and level-2) particles at random positions within `spread` h0 of
    `centre` (default: the box's middle), at least 0.3 h_l apart."""
    centre = np.array(p.domain, np.float64) / 2 if centre is None else np.asarray(centre, np.float64)
    masses = np.concatenate([np.full(n0, p.mass0), np.full(n1, p.mass0 / 2), np.full(n2, p.mass0 / 4)])
    pts = []
    while len(pts) < len(masses):
        q = centre + rng.uniform(-spread, spread, 3) * p.h0
        if all(np.linalg.norm(q - o) > 0.3 * p.h0 for o in pts):
            pts.append(q)
    return np.array(pts), masses
