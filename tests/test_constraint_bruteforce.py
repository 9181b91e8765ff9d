"""The PBF constraint solver against brute force on small mixed-level states (issue 54), CPU backend.

Levels 0-2 in one cluster (masses m0, m0/2, m0/4, radii h0 2^(-l/3), the symmetric kernel of eq. 19), no walls,
every other process off. numpy (tests/pbf_bruteforce.py) writes out, pair by pair, in float64:
  rho_i and lambda_i = -C_i / (sum_k |grad_k C_i|^2 / m_k + eps), k over the neighbours and i itself (eq. 1-4);
  dp_i = 1/rho0 sum_j (lambda_i m_j / m_i + lambda_j) grad W_ij (Macklin eq. 12-14);
  J (the density's rate of change, D = J u) and the velocity projection's preconditioned conjugate gradients.
The solver's projection impulse mu must give its velocity change as M^-1 J^T mu (the adjoint identity
<J u, mu> = <M^-1 J^T mu, M u> for every u), and no projection may raise the kinetic energy.
"""
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from pbf_cuda import load_scene
from pbf_bruteforce import (density_lambda, jacobian, mixed_cluster, one_step, params_of, position_correction,
                            projection_cg)

SETTINGS = settings(max_examples=20, deadline=None, derandomize=True)
BASE = dict(thermodynamics=False, unilateral=False, scorr_k=0.0, xsph=0.0, vorticity=0.0, viscosity=0.0, k_p=0.0,
            merge_threshold=0.0, remove_column_drift=False, gradient_correction=False, gravity=[0.0, 0.0, 0.0],
            max_velocity=1e9, max_cfl=1e9)


def scene():
    return load_scene("growing_adaptive", **{"domain.size": [1224.0, 1224.0, 1224.0]})


def kinetic_energy(m, u):
    return 0.5 * float(np.sum(m[:, None] * u * u))


@SETTINGS
@given(seed=st.integers(0, 2**16), relaxation=st.floats(0.05, 1.0), levels=st.sampled_from([(5, 8, 4), (3, 0, 10),
                                                                                             (8, 8, 0)]))
def test_density_lambda_and_position_correction(seed, relaxation, levels):
    sc = scene()
    rng = np.random.default_rng(seed)
    p = params_of(sc, **BASE, velocity_projection=False, iterations=1)
    p.relaxation = relaxation * params_of(sc).relaxation / sc.pbf.relaxation
    x, m = mixed_cluster(p, rng, *levels)
    out = one_step(p, x, np.zeros_like(x), m)
    rho, C, lam = density_lambda(p, x, m)
    assert np.abs(C).max() > 0.05                                    # a real violation to correct
    assert np.allclose(out["density"], rho, rtol=2e-5)
    dp = position_correction(p, x, m, lam)
    scale = np.abs(dp).max()
    assert scale > 1.0                                               # metres: the correction is not negligible
    assert np.abs(out["position"] - x - dp).max() < 2e-4 * scale
    # the correction moves no mass centre (sum m dp = 0: the pair terms are equal and opposite)
    assert np.abs(m @ (out["position"] - x)).max() < 1e-4 * scale * m.sum()


@SETTINGS
@given(seed=st.integers(0, 2**16), iterations=st.integers(1, 6))
def test_velocity_projection_is_the_conjugate_gradients_of_J(seed, iterations):
    sc = scene()
    rng = np.random.default_rng(seed)
    p = params_of(sc, **BASE, velocity_projection=True, iterations=0, divergence_iterations=iterations,
                  divergence_tolerance=0.0)
    x, m = mixed_cluster(p, rng, 5, 8, 4)
    v = rng.normal(0.0, 1.0, x.shape)
    out = one_step(p, x, v, m)
    xs = x + p.dt * v                                                # x*: no density iterations
    assert np.abs(out["position"] - xs).max() < 1e-3
    expect, mu = projection_cg(p, xs, m, v, iterations)
    scale = np.abs(expect - v).max()
    assert scale > 0.1
    assert np.abs(out["velocity"] - expect).max() < 2e-4 * scale
    assert np.allclose(out["solver"].get_float("projection_impulse")[out["order"]], mu,
                       rtol=2e-3, atol=2e-4 * np.abs(mu).max())
    # every iterate lowers the kinetic energy (CG minimises it along M-orthogonal directions)
    assert kinetic_energy(m, out["velocity"]) < kinetic_energy(m, v)


@SETTINGS
@given(seed=st.integers(0, 2**16))
def test_adjoint_identity_and_energy_of_the_converged_projection(seed):
    sc = scene()
    rng = np.random.default_rng(seed)
    p = params_of(sc, **BASE, velocity_projection=True, iterations=0, divergence_iterations=40,
                  divergence_tolerance=0.0)
    x, m = mixed_cluster(p, rng, 4, 6, 4, spread=0.6)
    v = rng.normal(0.0, 1.0, x.shape)
    xs = x + p.dt * v
    J = jacobian(p, xs, m)
    M = np.repeat(m, 3)
    A = J @ (J.T / M[:, None])
    # states the float32 conjugate gradients can converge on in 40 iterations (no particle without neighbours)
    assume(np.linalg.cond(A) < 1e5)
    out = one_step(p, x, v, m)
    mu = out["solver"].get_float("projection_impulse").astype(np.float64)[out["order"]]
    dv = (out["velocity"] - v).reshape(-1)                           # the solver's M^-1 J^T mu (ApplyJT)
    assert np.abs(dv).max() > 0.1
    # <J u, mu> = <M^-1 J^T mu, M u> for random u (ApplyJT is the transpose of the divergence J, mass-weighted)
    for u in rng.normal(size=(5, len(dv))):
        lhs, rhs = (J @ u) @ mu, dv @ (M * u)
        assert abs(lhs - rhs) < 2e-3 * np.linalg.norm(J @ u) * np.linalg.norm(mu)
    assert np.allclose(dv, (J.T @ mu) / M, atol=1e-3 * np.abs(dv).max())
    # converged: divergence-free, and the M-orthogonal projection's energy (the minimum over J u = 0)
    v1 = out["velocity"].reshape(-1)
    assert np.linalg.norm(J @ v1) < 1e-3 * np.linalg.norm(J @ v.reshape(-1))
    exact = v.reshape(-1) - (J.T @ np.linalg.solve(A, J @ v.reshape(-1))) / M
    assert np.abs(v1 - exact).max() < 2e-3 * np.abs(dv).max()
    assert kinetic_energy(m, out["velocity"]) <= kinetic_energy(m, v)
    # momentum: J^T mu sums to zero over the particles
    assert np.abs((M * dv).reshape(-1, 3).sum(axis=0)).max() < 1e-4 * np.sum(M * np.abs(dv))


@settings(max_examples=10, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**16))
def test_projection_never_raises_kinetic_energy_over_steps(seed):
    """Several steps with the warm start (the previous step's impulse applied first) on mixed levels."""
    sc = scene()
    rng = np.random.default_rng(seed)
    p = params_of(sc, **BASE, velocity_projection=True, iterations=2, divergence_iterations=3)
    x, m = mixed_cluster(p, rng, 6, 8, 6, spread=1.5)
    v = rng.normal(0.0, 1.0, x.shape)
    e0 = kinetic_energy(m, v)
    for _ in range(3):
        out = one_step(p, x, v, m)
        e1 = kinetic_energy(out["mass"], out["velocity"])
        assert e1 <= e0 * (1 + 1e-6)
        x, v, e0 = out["position"], out["velocity"], e1


@pytest.mark.gpu
def test_constraint_solver_against_brute_force_on_the_gpu(monkeypatch):
    import pbf_bruteforce
    monkeypatch.setattr(pbf_bruteforce, "BACKEND", "cuda")
    for seed in (0, 1, 2):
        test_density_lambda_and_position_correction.hypothesis.inner_test(seed=seed, relaxation=0.5,
                                                                          levels=(5, 8, 4))
        test_velocity_projection_is_the_conjugate_gradients_of_J.hypothesis.inner_test(seed=seed, iterations=4)
        test_adjoint_identity_and_energy_of_the_converged_projection.hypothesis.inner_test(seed=seed)
        test_projection_never_raises_kinetic_energy_over_steps.hypothesis.inner_test(seed=seed)
