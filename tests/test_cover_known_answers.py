"""Known answers of the cloud-field helpers of cloudpbf.statistics that the diagnostics row does not go through
(issue 54: a mutant of `cloud_cover`'s axis survived every test)."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cloudpbf.statistics import cloud_cover, cloud_fraction_profile, diagnostics


@settings(max_examples=20, deadline=None, derandomize=True)
@given(nx=st.integers(2, 7), ny=st.integers(2, 7), nz=st.integers(2, 7), seed=st.integers(0, 2**16))
def test_cloud_cover_is_the_fraction_of_cloudy_columns(nx, ny, nz, seed):
    rng = np.random.default_rng(seed)
    cloud = np.zeros((nx, ny, nz))                       # y (index 1) is up: a column is (x, z)
    columns = rng.uniform(size=(nx, nz)) < 0.4
    for i, k in zip(*np.nonzero(columns)):
        cloud[i, rng.integers(ny), k] = 1e-3             # one cloudy cell at a random height
    assert cloud_cover(cloud) == columns.mean()
    assert np.allclose(cloud_fraction_profile(cloud).sum() * nx * nz, columns.sum())
    # the diagnostics row (what every study records) says the same
    fields = {"cloud": cloud, "vapor": np.zeros_like(cloud), "temperature": np.full_like(cloud, 290.0)}
    row = diagnostics(fields, cell_size=(100.0, 50.0, 100.0))
    assert row["cloud_cover"] == columns.mean()
