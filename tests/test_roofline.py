"""The step's bandwidth roofline (cloudpbf.roofline) and the scaling study's roofline columns."""
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as st

from cloudpbf import roofline
from pbf_cuda import load_scene

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@settings(max_examples=30, deadline=None)
@given(iterations=st.integers(1, 60), cg=st.integers(1, 60))
def test_each_density_and_cg_iteration_adds_its_two_passes(iterations, cg):
    # A density iteration reads x* and writes lambda and rho, then reads x* and lambda and writes x*: 24 + 36 B.
    # A CG iteration reads x* and p, writes g (36 B), then reads x*, g, v and r, mu, p, writes v and r, mu, p
    # (88 B).
    base = load_scene("growing").replace(**{"pbf.iterations": iterations, "pbf.divergence_iterations": cg})
    more_density = base.replace(**{"pbf.iterations": iterations + 1})
    more_cg = base.replace(**{"pbf.divergence_iterations": cg + 1})
    assert roofline.step_bytes(more_density) - roofline.step_bytes(base) == 60
    assert roofline.step_bytes(more_cg) - roofline.step_bytes(base) == 36 + 88


def test_passes_follow_the_scene():
    growing = load_scene("growing")
    dam = load_scene("dam_break")
    names = [p for p, _, _ in roofline.step_passes(growing)]
    assert "cloud dynamics (eq. 5-11)" in names and "v = (x* - x) / dt" not in names
    dam_names = [p for p, _, _ in roofline.step_passes(dam)]
    assert "v = (x* - x) / dt" in dam_names and "cloud dynamics (eq. 5-11)" not in dam_names
    assert all(r > 0 and w > 0 for _, r, w in roofline.step_passes(growing))


def test_roofline_is_linear_in_particles_and_inverse_in_bandwidth():
    scene = load_scene("growing")
    one = roofline.roofline_ms(scene, 1_000_000, 2e12)
    assert one == pytest.approx(1e3 * 1e6 * roofline.step_bytes(scene) / 2e12)
    assert roofline.roofline_ms(scene, 2_000_000, 2e12) == pytest.approx(2 * one)
    assert roofline.roofline_ms(scene, 1_000_000, 4e12) == pytest.approx(one / 2)
    assert roofline.roofline_ms(scene, 1_000_000, None) is None


def test_cpu_copy_bandwidth_is_measured():
    bw = roofline.copy_bandwidth("cpu", nbytes=1 << 26, repeats=8)
    assert 1e8 < bw < 1e13          # bytes/s, read + written


def test_no_step_beats_its_roofline(tmp_path):
    from cloudpbf.studies.scaling import pbf_scaling
    frame = pbf_scaling([2000, 6000], backend="cpu", runs_root=tmp_path, timing_steps=2, quiet=True)
    assert frame["roofline_ms"].notna().all() and (frame["roofline_ms"] > 0).all()
    assert (frame["step_ms"] >= frame["roofline_ms"]).all()
    assert (frame["roofline_ratio"] >= 1.0).all()
    assert frame["bytes_per_particle"].isna().all()          # measured on CUDA only
    assert frame["step_bytes_per_particle"].nunique() == 1


@pytest.mark.gpu
def test_cuda_run_reports_its_peak_memory_and_roofline(tmp_path):
    from cloudpbf.studies.scaling import pbf_scaling
    frame = pbf_scaling([200_000], backend="cuda", runs_root=tmp_path, timing_steps=3, quiet=True)
    row = frame.iloc[0]
    # The solver's arrays are ~224-250 B per slot, plus sort scratch, lists and the boundary: a few hundred B.
    assert 150 < row["bytes_per_particle"] < 3000
    assert row["copy_bandwidth_gbs"] > 100
    assert row["step_ms"] >= row["roofline_ms"]


def test_memory_estimate_against_the_measured_peak():
    # The device memory an H100 run held per particle (pbf_scaling.csv, bytes_per_particle, 16M particles and
    # more, where the fixed costs are small): the estimate that gates every run is at or above it, and close.
    from pathlib import Path
    from pbf_cuda.memory import estimate_memory
    data = pd.read_csv(Path(__file__).resolve().parents[1] / "reports/gpu/data/pbf_scaling.csv")
    rows = data[(data["particles"] >= 16_000_000) & data["bytes_per_particle"].notna()]
    assert len(rows) >= 2 and (~rows["neighbor_list"]).any()
    for _, r in rows.iterrows():
        scene = load_scene("growing").replace(**{"pbf.neighbor_list": bool(r["neighbor_list"])})
        est = estimate_memory(scene.with_particle_count(int(r["particles"])), "cuda")
        ratio = est.device_bytes / est.fluid / r["bytes_per_particle"]
        assert 0.97 <= ratio <= 1.3, (r["particles"], r["neighbor_list"], ratio)
