"""grid_baseline.projection: exact FFT/DCT pressure projection on the MAC grid.

Stated bounds on the relative divergence max|div u| * h / max|u| after one projection:
float64 below 1e-10 (observed ~1e-15), float32 below 1e-5 (observed ~5e-7).
"""
import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("jax_cfd")
import jax.numpy as jnp  # noqa: E402

from grid_baseline import projection as P  # noqa: E402

BOUND = {"float64": 1e-10, "float32": 1e-5}
LAYOUTS = [(True, False, True), (False, False, False), (True, True, True), (False, True, True)]


@pytest.fixture(scope="module", autouse=True)
def x64():
    jax.config.update("jax_enable_x64", True)   # left on (see test_grid_noise.py)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("periodic", LAYOUTS)
def test_divergence_after_projection(dtype, periodic):
    shape, steps = (12, 10, 6), (100.0, 50.0, 70.0)
    rng = np.random.default_rng(1)
    vel = tuple(jnp.asarray(rng.normal(size=shape), dtype) for _ in range(3))
    inv = P.laplacian_eigenvalues(shape, steps, periodic, dtype)
    proj = jax.jit(lambda v: P.project(v, steps, periodic, inv)[0])
    out = proj(vel)
    assert all(u.dtype == jnp.dtype(dtype) for u in out)
    rel = float(jax.jit(lambda v: P.relative_divergence(v, steps, periodic))(out))
    assert rel < BOUND[dtype], rel
    # idempotent
    again = proj(out)
    scale = max(float(jnp.max(jnp.abs(u))) for u in out)
    assert max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(out, again)) < 50 * BOUND[dtype] * scale
    # no flow through walls
    for a, per in enumerate(periodic):
        if not per:
            assert float(jnp.max(jnp.abs(jnp.take(out[a], -1, axis=a)))) == 0.0


def test_gradient_is_removed_and_solenoidal_field_kept():
    shape, steps, periodic = (10, 8, 6), (1.0, 2.0, 1.5), (True, False, True)
    rng = np.random.default_rng(2)
    inv = P.laplacian_eigenvalues(shape, steps, periodic, jnp.float64)
    p = jnp.asarray(rng.normal(size=shape))
    grad = P.gradient_faces(p, steps, periodic)
    out, _ = P.project(grad, steps, periodic, inv)
    assert max(float(jnp.max(jnp.abs(u))) for u in out) < 1e-12
    sol, _ = P.project(tuple(jnp.asarray(rng.normal(size=shape)) for _ in range(3)), steps, periodic, inv)
    kept, _ = P.project(sol, steps, periodic, inv)
    assert max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(sol, kept)) < 1e-12


@pytest.mark.parametrize("periodic", [(True, False, True), (False, False, False)])
def test_poisson_solve_matches_dense_matrix(periodic):
    """The transform solve equals a dense solve of div(grad p) = rhs (mean-free), i.e. the
    eigenvalues and transforms are the MAC Laplacian's with Neumann walls."""
    shape, steps = (5, 4, 3), (1.0, 0.5, 2.0)
    n = int(np.prod(shape))
    rng = np.random.default_rng(3)
    rhs = rng.normal(size=shape)
    rhs -= rhs.mean()
    inv = P.laplacian_eigenvalues(shape, steps, periodic, jnp.float64)
    p = np.asarray(P.solve_poisson(jnp.asarray(rhs), inv, periodic))
    # dense Laplacian from the same divergence/gradient operators applied to unit vectors
    op = jax.jit(jax.vmap(lambda e: P.divergence(P.gradient_faces(e.reshape(shape), steps, periodic),
                                                  steps, periodic).ravel()))
    L = np.asarray(op(jnp.eye(n))).T
    np.testing.assert_allclose(L @ p.ravel(), rhs.ravel(), atol=1e-10)
    assert abs(p.mean()) < 1e-12
