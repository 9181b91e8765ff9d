"""Cloud statistics: known answers on synthetic fields, conservation of the deposition."""
import math

import numpy as np
import pandas as pd
import pytest

from cloudpbf import statistics as st
from cloudpbf.store.files import save_frame

# --------------------------------------------------------------------------------------------
# a box of cloud on a grid: every diagnostic has a closed form
# --------------------------------------------------------------------------------------------
SHAPE = (20, 30, 16)               # nx, ny (up), nz
CELL = np.array([100.0, 50.0, 100.0])  # m
W_BOX = 2e-4                        # kg/kg inside the box
BOX = (slice(4, 12), slice(10, 20), slice(0, 8))  # x cells 4..11, y cells 10..19 (500 m .. 1000 m), z 0..7


def box_fields(air_density=None):
    w = np.zeros(SHAPE)
    w[BOX] = W_BOX
    y = (np.arange(SHAPE[1]) + 0.5) * CELL[1]
    t = np.broadcast_to((300.0 - 0.0065 * y)[None, :, None], SHAPE).copy()
    fields = {"cloud": w, "vapor": np.full(SHAPE, 8e-3), "temperature": t,
              "cell_size": CELL, "origin": np.zeros(3)}
    if air_density is not None:
        fields["density"] = np.full(SHAPE, air_density)
    return fields


def test_box_of_cloud_known_answers():
    row = st.diagnostics(box_fields())
    columns = SHAPE[0] * SHAPE[2]
    cloudy_columns = 8 * 8
    assert row["cloud_cover"] == cloudy_columns / columns == 0.2
    assert row["cloud_base"] == 500.0 and row["cloud_top"] == 1000.0
    assert row["base_p10"] == 500.0 and row["top_p90"] == 1000.0
    # LWP of a cloudy column: rho w depth = 1 kg/m^3 * 2e-4 * 500 m
    assert row["lwp_max"] == pytest.approx(0.1, rel=1e-12)
    assert row["lwp_mean"] == pytest.approx(0.1 * 0.2, rel=1e-12)
    assert row["n_objects"] == 1
    volume = 8 * 10 * 8 * np.prod(CELL)
    assert row["cloudy_volume"] == pytest.approx(volume)
    assert row["object_volume_max"] == pytest.approx(volume)
    domain = np.prod(SHAPE) * np.prod(CELL)
    assert row["total_mass"] == pytest.approx(domain)
    assert row["total_water"] == pytest.approx(8e-3 * domain + W_BOX * volume, rel=1e-12)
    assert row["total_cloud"] == pytest.approx(W_BOX * volume, rel=1e-12)
    mean_t = np.mean(300.0 - 0.0065 * (np.arange(SHAPE[1]) + 0.5) * CELL[1])
    assert row["total_heat"] == pytest.approx(mean_t * domain, rel=1e-12)
    assert list(row) == list(st.DIAGNOSTIC_COLUMNS)


def test_box_of_cloud_density_scales_budgets_and_lwp():
    plain = st.diagnostics(box_fields())
    dense = st.diagnostics(box_fields(air_density=1.2))
    assert dense["lwp_mean"] == pytest.approx(1.2 * plain["lwp_mean"], rel=1e-12)
    assert dense["total_water"] == pytest.approx(1.2 * plain["total_water"], rel=1e-12)
    assert dense["cloud_cover"] == plain["cloud_cover"]
    # the uniform air_density argument is the same as a constant density grid
    assert st.diagnostics(box_fields(), air_density=1.2) == pytest.approx(dense)


def test_box_of_cloud_profiles():
    prof = st.vertical_profiles(box_fields())
    assert list(prof.columns) == list(st.PROFILE_COLUMNS)
    assert np.allclose(prof["z"], (np.arange(SHAPE[1]) + 0.5) * 50.0)
    expected = np.zeros(SHAPE[1])
    expected[10:20] = 0.2
    assert np.array_equal(prof["cloud_fraction"].to_numpy(), expected)
    assert np.allclose(prof["cloud"], expected * W_BOX, rtol=1e-12, atol=0)
    assert np.allclose(prof["vapor"], 8e-3)
    assert np.allclose(prof["temperature"], 300.0 - 0.0065 * prof["z"])


def test_threshold_is_a_parameter():
    fields = box_fields()
    assert st.diagnostics(fields, threshold=W_BOX)["cloud_cover"] == 0.0   # w > threshold is strict
    assert math.isnan(st.diagnostics(fields, threshold=W_BOX)["cloud_base"])
    with pytest.raises(ValueError, match="threshold"):
        st.diagnostics(fields, threshold=-1.0)


def test_no_cloud_gives_nan_heights_and_zero_cover():
    fields = box_fields()
    fields["cloud"] = np.zeros(SHAPE)
    row = st.diagnostics(fields)
    assert row["cloud_cover"] == 0.0 and row["n_objects"] == 0 and row["lwp_mean"] == 0.0
    assert all(math.isnan(row[k]) for k in ("cloud_base", "cloud_top", "base_p10", "top_p90"))


def test_percentiles_of_column_bases_and_tops():
    # column i (x) holds cloud from cell 2 + i to cell 10 + 2 i: bases and tops differ per column
    shape = (10, 40, 1)
    w = np.zeros(shape)
    for i in range(10):
        w[i, 2 + i:11 + 2 * i, 0] = 1e-3
    fields = {"cloud": w, "vapor": np.zeros(shape), "temperature": np.full(shape, 280.0)}
    row = st.diagnostics(fields, cell_size=(10.0, 10.0, 10.0), origin=(0.0, 100.0, 0.0))
    bases = 100.0 + 10.0 * (2 + np.arange(10))
    tops = 100.0 + 10.0 * (11 + 2 * np.arange(10))
    assert row["cloud_base"] == 120.0 and row["cloud_top"] == 100.0 + 10.0 * 29
    assert row["base_p10"] == pytest.approx(np.percentile(bases, 10))   # 129 m
    assert row["top_p90"] == pytest.approx(np.percentile(tops, 90))     # 372 m
    assert row["base_p10"] == pytest.approx(129.0) and row["top_p90"] == pytest.approx(372.0)


# --------------------------------------------------------------------------------------------
# cloud objects with periodic wrapping
# --------------------------------------------------------------------------------------------
def test_object_across_the_periodic_x_boundary_is_one_object():
    mask = np.zeros((12, 6, 10), dtype=bool)
    mask[-2:, 2:4, 3:5] = True     # right edge
    mask[:3, 2:4, 3:5] = True      # left edge: the same cloud, wrapped
    labels, sizes = st.cloud_objects(mask)
    assert len(sizes) == 1 and sizes[0] == mask.sum()
    # without periodic wrapping it would be two
    assert len(st.cloud_objects(mask, periodic=(False, False, False))[1]) == 2
    # a separate blob in the middle is a second object
    mask[6, 2, 5] = True
    labels, sizes = st.cloud_objects(mask)
    assert sorted(sizes) == [1, 5 * 2 * 2]
    assert set(np.unique(labels)) == {0, 1, 2}


def test_object_wrapping_in_x_and_z_at_a_corner():
    mask = np.zeros((8, 4, 8), dtype=bool)
    for i in (0, -1):
        for k in (0, -1):
            mask[i, 1, k] = True   # four corner cells: one cloud through both periodic faces
    assert len(st.cloud_objects(mask)[1]) == 1
    assert len(st.cloud_objects(mask, periodic=(True, False, False))[1]) == 2
    # y is a wall: cells at the bottom and top faces stay separate
    wall = np.zeros((4, 6, 4), dtype=bool)
    wall[1, 0, 1] = wall[1, -1, 1] = True
    assert len(st.cloud_objects(wall)[1]) == 2
    fields = {"cloud": np.where(mask, 1e-3, 0.0), "vapor": np.zeros(mask.shape),
              "temperature": np.full(mask.shape, 280.0)}
    assert st.diagnostics(fields, cell_size=1.0)["n_objects"] == 1
    two = np.zeros((8, 4, 8))
    two[0, 1, 0] = two[-1, 1, 0] = two[3:5, 1:3, 3:5] = 1e-3      # 2 cells wrapped, 8 cells in the middle
    volumes = st.object_volumes({"cloud": two}, cell_size=(10.0, 20.0, 10.0))
    assert volumes.tolist() == [8 * 2000.0, 2 * 2000.0]


# --------------------------------------------------------------------------------------------
# deposition
# --------------------------------------------------------------------------------------------
def random_particles(n=3000, seed=1, size=(800.0, 600.0, 400.0)):
    rng = np.random.default_rng(seed)
    size = np.array(size)
    pos = rng.random((n, 3)) * size
    pos[:50, 1] = rng.choice([0.0, size[1], 1.0, size[1] - 1.0], 50)  # on and near the walls
    pos[50:60, 0] += size[0]                                          # outside a periodic face
    h = rng.uniform(20.0, 150.0, n)
    h[:100] = 5.0                                                     # reaches no cell centre
    mass = rng.uniform(0.5, 2.0, n) * 1e5
    fields = {"vapor": rng.uniform(0.0, 2e-2, n), "cloud": rng.uniform(0.0, 1e-3, n) * (rng.random(n) < 0.3),
              "temperature": rng.uniform(250.0, 300.0, n)}
    return pos, mass, h, fields, size


def test_deposition_conserves_mass_weighted_totals():
    pos, mass, h, fields, size = random_particles()
    shape = (16, 12, 8)
    grid = st.deposit(pos, mass, h, fields, shape, size / shape)
    dv = np.prod(size / shape)
    assert grid["density"].sum() * dv == pytest.approx(mass.sum(), rel=1e-12)
    for name, values in fields.items():
        assert np.sum(grid["density"] * grid[name]) * dv == pytest.approx(np.sum(mass * values), rel=1e-12), name
    row = st.diagnostics(grid)
    assert row["total_water"] == pytest.approx(np.sum(mass * (fields["vapor"] + fields["cloud"])), rel=1e-12)
    assert row["total_heat"] == pytest.approx(np.sum(mass * fields["temperature"]), rel=1e-12)


def test_deposition_reproduces_a_constant_field_exactly():
    pos, mass, h, fields, size = random_particles(seed=2)
    shape = (10, 9, 7)
    grid = st.deposit(pos, mass, h, {"temperature": np.full(len(pos), 287.3)}, shape, size / shape)
    filled = grid["density"] > 0
    assert filled.all()
    assert np.allclose(grid["temperature"], 287.3, rtol=1e-14, atol=0)


def test_uniform_lattice_deposits_the_rest_density():
    d, rho0 = 25.0, 1.3
    axes = [np.arange(n) * d + d / 2 for n in (8, 6, 10)]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    grid = st.deposit(pos, rho0 * d**3, 2.0 * d, {}, (8, 6, 10), d, periodic=(True, True, True))
    assert np.allclose(grid["density"], rho0, rtol=1e-12, atol=0)
    # with walls in y the mass stays in the box, mirror-symmetric about the mid-plane
    walled = st.deposit(pos, rho0 * d**3, 2.0 * d, {}, (8, 6, 10), d)
    assert walled["density"].sum() * d**3 == pytest.approx(rho0 * d**3 * len(pos), rel=1e-12)
    assert np.allclose(walled["density"], walled["density"][:, ::-1], rtol=1e-12)
    assert np.ptp(walled["density"], axis=(0, 2)).max() < 1e-12 * rho0   # uniform in each layer


def test_deposition_is_periodic_under_shifts():
    pos, mass, h, fields, size = random_particles(seed=3)
    shape = (16, 12, 8)
    cell = size / shape
    base = st.deposit(pos, mass, h, fields, shape, cell)
    shifted = st.deposit(pos + np.array([3 * cell[0], 0.0, -cell[2]]), mass, h, fields, shape, cell)
    rolled = np.roll(np.roll(base["cloud"], 3, axis=0), -1, axis=2)
    assert np.allclose(shifted["cloud"], rolled, rtol=1e-10, atol=1e-18)


def test_kernel_footprint_of_one_particle():
    # one particle at a cell centre, h = 1.5 cells: the weights follow poly6 and sum to its mass
    cell = 10.0
    grid = st.deposit([[55.0, 55.0, 55.0]], 7.0, 15.0, {}, (11, 11, 11), cell, periodic=(True, True, True))
    rho = grid["density"]
    assert rho.sum() * cell**3 == pytest.approx(7.0)
    assert np.argmax(rho) == np.ravel_multi_index((5, 5, 5), (11, 11, 11))
    ratio = rho[6, 5, 5] / rho[5, 5, 5]
    assert ratio == pytest.approx(float(st.poly6(100.0, 15.0) / st.poly6(0.0, 15.0)))
    assert rho[7, 5, 5] == 0.0   # 20 m > h


def test_deposition_threads_give_the_same_grid():
    pos, mass, h, fields, size = random_particles(n=4000, seed=4)
    shape = (16, 12, 8)
    one = st.deposit(pos, mass, h, fields, shape, size / shape, workers=1)
    four = st.deposit(pos, mass, h, fields, shape, size / shape, workers=4)
    for key in ("density", "cloud", "temperature"):
        assert np.allclose(one[key], four[key], rtol=1e-12, atol=0)


def test_deposition_errors_name_the_field():
    pos = np.zeros((3, 3))
    with pytest.raises(ValueError, match="kernel_radius"):
        st.deposit(pos, 1.0, -1.0, {}, (2, 2, 2), 1.0)
    with pytest.raises(ValueError, match="positions"):
        st.deposit(np.array([[0.0, np.nan, 0.0]]), 1.0, 1.0, {}, (2, 2, 2), 1.0)
    with pytest.raises(ValueError, match=r"fields\['cloud'\]"):
        st.deposit(pos, 1.0, 1.0, {"cloud": np.zeros(4)}, (2, 2, 2), 1.0)
    with pytest.raises(ValueError, match="shape"):
        st.deposit(pos, 1.0, 1.0, {}, (2, 0, 2), 1.0)
    with pytest.raises(ValueError, match="cell_size"):
        st.deposit(pos, 1.0, 1.0, {}, (2, 2, 2), (1.0, -1.0, 1.0))


def test_empty_particle_set_gives_empty_grid():
    grid = st.deposit(np.zeros((0, 3)), np.zeros(0), np.zeros(0), {"cloud": np.zeros(0)}, (3, 4, 5), 1.0)
    assert grid["density"].shape == (3, 4, 5) and not grid["density"].any() and not grid["cloud"].any()


# --------------------------------------------------------------------------------------------
# both solvers through the same code
# --------------------------------------------------------------------------------------------
def lattice_state(scene, cloud):
    lo, hi = scene.fill_box()
    d = scene.particles.spacing
    axes = [np.arange(lo[a] + d / 2, hi[a], d) for a in range(3)]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    n = len(pos)
    return {"position": pos, "mass": np.full(n, scene.particles.rest_density * d**3),
            "kernel_radius": np.full(n, scene.kernel_radius), "temperature": scene.environment_temperature(pos[:, 1]),
            "vapor": np.full(n, 5e-3), "cloud": cloud(pos), "level": np.zeros(n, dtype=np.int32)}


def test_particle_and_grid_diagnostics_on_a_uniformly_cloudy_box():
    from pbf_cuda.scene import load_scene
    scene = load_scene("parcel")   # 1600 x 1600 x 300 m, spacing 50 m, y walls
    state = lattice_state(scene, lambda p: np.full(len(p), 1e-3))
    shape, cell = st.grid_for_scene(scene)
    assert shape == (32, 32, 6) and np.allclose(cell, 50.0)
    row = st.particle_diagnostics(state, scene)
    height = scene.domain.size[1]
    assert row["cloud_cover"] == 1.0 and row["n_objects"] == 1
    assert row["cloud_base"] == 0.0 and row["cloud_top"] == height
    assert row["lwp_mean"] == pytest.approx(1e-3 * 1.0 * height, rel=1e-9)
    total = np.sum(state["mass"] * (state["vapor"] + state["cloud"]))
    assert row["total_water"] == pytest.approx(total, rel=1e-12)
    # the grid solver's fields of the same atmosphere give the same row
    y = (np.arange(shape[1]) + 0.5) * cell[1]
    fields = {"cloud": np.full(shape, 1e-3), "vapor": np.full(shape, 5e-3),
              "temperature": np.broadcast_to(scene.environment_temperature(y)[None, :, None], shape),
              "velocity": np.zeros(shape + (3,)), "cell_size": cell, "origin": np.zeros(3)}
    grid_row = st.grid_diagnostics(fields, scene)
    for key in ("cloud_cover", "cloud_base", "cloud_top", "n_objects", "lwp_mean", "total_water", "total_mass"):
        assert grid_row[key] == pytest.approx(row[key], rel=1e-9), key
    # profiles agree away from the walls; within a kernel radius of a wall the Shepard
    # average of a linear T(y) is biased by at most lapse rate * h
    prof = st.particle_profiles(state, scene)["temperature"].to_numpy()
    grid_prof = st.grid_profiles(fields, scene)["temperature"].to_numpy()
    assert np.allclose(prof[2:-2], grid_prof[2:-2], rtol=1e-12)
    assert np.abs(prof - grid_prof).max() <= scene.atmosphere.lapse_rate * scene.kernel_radius


def test_particle_layer_of_cloud_found_at_its_height():
    from pbf_cuda.scene import load_scene
    scene = load_scene("parcel")
    state = lattice_state(scene, lambda p: np.where((p[:, 1] > 800) & (p[:, 1] < 1200), 1e-3, 0.0))
    row = st.particle_diagnostics(state, scene)
    # particles at 825..1175 m; the kernel (h = 100 m) spreads w over at most 100 m more
    assert 700.0 <= row["cloud_base"] <= 825.0 and 1175.0 <= row["cloud_top"] <= 1300.0
    assert row["cloud_cover"] == 1.0
    assert row["lwp_mean"] == pytest.approx(1e-3 * 400.0, rel=1e-9)   # water is conserved by deposition
    with pytest.raises(KeyError, match="atmosphere"):
        st.particle_diagnostics({"position": state["position"], "mass": state["mass"],
                                 "kernel_radius": state["kernel_radius"]}, scene)


def test_grid_for_scene_resolutions():
    from pbf_cuda.scene import load_scene
    scene = load_scene("parcel")
    assert st.grid_for_scene(scene, 16)[0] == (16, 16, 3)
    shape, cell = st.grid_for_scene(scene, (8, 4, 2))
    assert shape == (8, 4, 2) and np.allclose(cell, [200.0, 400.0, 150.0])
    with pytest.raises(ValueError, match="resolution"):
        st.grid_for_scene(scene, 0)


# --------------------------------------------------------------------------------------------
# time series
# --------------------------------------------------------------------------------------------
def test_onset_time_and_timeseries_frame(tmp_path):
    rows = [{"time_s": t, "cloud_cover": c} for t, c in [(30.0, 0.3), (0.0, 0.0), (10.0, 0.0), (20.0, 0.1)]]
    df = st.timeseries_frame(rows, solver="particles", mode="adaptive", seed=3)
    assert list(df.columns[:3]) == ["solver", "mode", "seed"]
    assert df["time_s"].tolist() == [0.0, 10.0, 20.0, 30.0]
    assert st.onset_time(df) == 20.0
    never = st.timeseries_frame([{"time_s": 0.0, "cloud_cover": 0.0}], solver="grid", mode="grid", seed=0)
    assert math.isnan(st.onset_time(never))
    both = pd.concat([df, never])
    onsets = st.onset_times(both)
    assert onsets.set_index("solver")["onset_s"]["particles"] == 20.0
    assert math.isnan(onsets.set_index("solver")["onset_s"]["grid"])
    for suffix in ("csv", "parquet"):
        path = save_frame(both, tmp_path / f"series.{suffix}")
        back = pd.read_csv(path) if suffix == "csv" else pd.read_parquet(path)
        assert len(back) == len(both) and list(back.columns) == list(both.columns)
    with pytest.raises(ValueError, match="csv or .parquet"):
        save_frame(both, tmp_path / "series.txt")
    with pytest.raises(KeyError, match="cloud_cover"):
        st.onset_time(pd.DataFrame({"time_s": [0.0]}))


@pytest.mark.parametrize("spacing, depth", [(45.0, 20.0), (68.0, 100.0), (100.0, 100.0), (100.0, 150.0),
                                            (137.0, 333.0), (230.0, 400.0)])
def test_heated_mass_fraction_of_a_lattice_at_rest_is_one(spacing, depth):
    """Eq. 5's layer weights give a lattice at rest exactly a full heated layer at any spacing, also where
    heating_depth is below one spacing or falls between two layers (the fraction is then the lattice's own
    density m_0 / (rho0 d^3)); a lattice lifted by half a spacing holds half a spacing's worth less of it (so
    the diagnostic sees a column leaving the floor)."""
    from pbf_cuda import load_scene
    from pbf_cuda.initial_state import fluid_particles, lattice_mass, lattice_spacings
    scene = load_scene("growing").replace(**{"domain.size": [1400.0, 1600.0, 1400.0], "particles.spacing": spacing,
                                             "atmosphere.heating_depth": depth})
    full = lattice_mass(scene) / (scene.particles.rest_density * float(np.prod(lattice_spacings(scene))))
    state = fluid_particles(scene)
    assert st.heated_mass_fraction(state, scene) == pytest.approx(full, rel=1e-5)
    dy = float(lattice_spacings(scene)[1])
    lifted = dict(state, position=state["position"] + np.array([0.0, 0.5 * dy, 0.0], dtype=np.float32))
    assert st.heated_mass_fraction(lifted, scene) == pytest.approx(full * max(0.0, 1.0 - 0.5 * dy / depth), rel=1e-5,
                                                                   abs=1e-7)


# ---- relative L2 error (the error of the sweep, adaptive and time-to-solution studies) ----------------------

from hypothesis import given, settings, strategies as hst  # noqa: E402


@settings(max_examples=40, deadline=None)
@given(n=hst.integers(2, 50), scale=hst.floats(1e-3, 1e3), eps=hst.floats(-0.5, 0.5), seed=hst.integers(0, 2**31))
def test_relative_l2_is_the_relative_size_of_a_perturbation(n, scale, eps, seed):
    reference = scale * (1.0 + np.random.default_rng(seed).random(n))
    assert st.relative_l2(reference, reference) == 0.0
    assert st.relative_l2(reference * (1.0 + eps), reference) == pytest.approx(abs(eps), rel=1e-9, abs=1e-12)
    assert st.relative_l2(reference * 7.0, reference * 7.0 * (1.0 + eps)) >= 0.0       # never negative


def test_relative_l2_nonfinite_samples_propagate_or_are_skipped():
    ref, val = np.array([1.0, 2.0, np.nan]), np.array([1.0, 2.0 * 1.1, 5.0])
    assert math.isnan(st.relative_l2(val, ref))                                   # one gap: no error
    assert st.relative_l2(val, ref, skip_nonfinite=True) == pytest.approx(0.2 / math.sqrt(5.0))
    assert math.isnan(st.relative_l2([1.0, 2.0], [0.0, 0.0]))                      # no scale to be relative to
    assert math.isnan(st.relative_l2([np.nan], [np.nan], skip_nonfinite=True))
