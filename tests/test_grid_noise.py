"""grid_baseline.noise: the jax simplex noise reproduces the committed reference table."""
from pathlib import Path

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("jax_cfd")
import jax.numpy as jnp  # noqa: E402

from grid_baseline import noise  # noqa: E402
from pbf_cuda import noise as reference_noise  # noqa: E402

TABLE = Path(__file__).resolve().parent / "data" / "noise_reference.csv"


@pytest.fixture(scope="module")
def table():
    d = np.loadtxt(TABLE, delimiter=",", comments="#", skiprows=2)
    assert d.shape[1] == 3 and len(d) > 100
    return d[:, 0], d[:, 1], d[:, 2]


@pytest.fixture(scope="module")
def x64():
    # Left on afterwards, as a float64 GridSimulation does (turning it off under live float64 arrays
    # of another test would be worse); see grid_baseline.simulation.
    jax.config.update("jax_enable_x64", True)


def test_float64_matches_table(table, x64):
    x, y, ref = table
    out = noise.simplex2(jnp.asarray(x, jnp.float64), jnp.asarray(y, jnp.float64))
    assert out.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(out), ref, rtol=0, atol=1e-12)
    host = noise.simplex2_host(x, y, dtype=jnp.float64)
    np.testing.assert_allclose(np.asarray(host), ref, rtol=0, atol=1e-12)


def test_float32_matches_table(table):
    x, y, ref = table
    # host coordinates (how the grid evaluates its heating pattern): any |x|
    host = noise.simplex2_host(x, y, dtype=jnp.float32)
    assert host.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(host, np.float64), ref, rtol=0, atol=1e-5)
    # fully traced float32: the coordinates themselves round to ~|x| * 6e-8, so compare near the origin
    near = (np.abs(x) <= 16) & (np.abs(y) <= 16)
    assert near.sum() >= 20
    out = jax.jit(noise.simplex2)(jnp.asarray(x[near], jnp.float32), jnp.asarray(y[near], jnp.float32))
    assert out.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(out, np.float64), ref[near], rtol=0, atol=1e-5)


def test_same_permutation_as_particle_solver():
    np.testing.assert_array_equal(noise.PERMUTATION, reference_noise.PERMUTATION)


def test_heating_pattern_matches_reference(x64):
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 3200, 500)
    z = rng.uniform(0, 3200, 500)
    ref = reference_noise.heating_pattern(x, z, 1.0 / 800.0, 1.5, offset=(17.25, 203.5))
    out = noise.heating_pattern(x, z, 1.0 / 800.0, 1.5, offset=(17.25, 203.5), dtype=jnp.float64)
    np.testing.assert_allclose(np.asarray(out), ref, rtol=0, atol=1e-12)
    assert ref.min() >= 0.0 and ref.max() > 1.5


def test_seed_offsets_are_the_particle_solvers():
    for seed in (0, 1, 7, 12345):
        assert noise.noise_offset_for_seed(seed) == reference_noise.noise_offset_for_seed(seed)
