"""Both solvers speak one simulation protocol (pbf_cuda.protocol): the same calls, a checkpoint that
restores the run bit-exactly, and the same InstabilityError when a run goes past its speed bound."""
import numpy as np
import pytest

from pbf_cuda.protocol import InstabilityError, SimulationProtocol
from pbf_cuda.scene import load_scene

SCENE = {"domain.size": [800.0, 800.0, 800.0], "particles.spacing": 100.0, "atmosphere.heating_rate": 0.5,
         "time.check_every": 1}


def make(solver, **overrides):
    scene = load_scene("growing", **{**SCENE, **overrides})
    if solver == "particles":
        pytest.importorskip("pbf_cuda._core", reason="the particle solver is not built")
        from pbf_cuda import Simulation
        return Simulation(scene, backend="cpu", seed=3)
    pytest.importorskip("jax")
    pytest.importorskip("jax_cfd")
    from grid_baseline import GridSimulation
    return GridSimulation(scene, seed=3, dtype="float64", device="cpu")


def by_id(state):
    order = np.argsort(state["id"], kind="stable")
    return {k: v[order] for k, v in state.items()}


@pytest.mark.parametrize("solver", ["particles", pytest.param("grid", marks=pytest.mark.slow)])  # grid: ~17 s of jit
def test_one_protocol_checkpoint_and_instability(solver, tmp_path):
    sim = make(solver)
    assert isinstance(sim, SimulationProtocol)
    sim.step(2)
    assert sim.step_count == 2 and sim.time == pytest.approx(2 * sim.scene.time.dt) and sim.size > 0
    assert sim.stats()["step"] == 2 and all("mean_ms" in t for t in sim.timings().values())
    sim.save(tmp_path / "c.npz")
    again = type(sim).load(tmp_path / "c.npz")
    assert again.step_count == 2 and again.size == sim.size
    sim.step(2)
    again.step(2)
    a, b = by_id(sim.state()), by_id(again.state())
    for name in ("position", "velocity", "temperature", "vapor", "cloud"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    # the same error from both solvers once a speed passes pbf.max_velocity (the grid reads the bound
    # at each check; the particle solver's is compiled into its parameters: a new run)
    if solver == "grid":
        sim.scene = sim.scene.replace(**{"pbf.max_velocity": 1e-3})
        start = sim.step_count
    else:
        sim, start = make(solver, **{"pbf.max_velocity": 1e-3}), 0
    with pytest.raises(InstabilityError) as err:
        sim.step(5)
    assert start < err.value.step <= start + 5 and err.value.last_good_step < err.value.step
    assert "max_velocity" in err.value.reason
