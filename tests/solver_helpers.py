"""Helpers shared by the solver tests: backend parametrisation and small scenes."""
import numpy as np
import pytest

BACKENDS = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]

# A capping inversion's layer filling a box (pbf_cuda/environment.py): from 1 m up, T0 rises by 100 K over
# 100 km, i.e. Gamma(y) = -1e-3 K/m, so the whole column has the inversion layer's stratification.
INVERSION_EVERYWHERE = {"atmosphere.inversion_height": 1.0, "atmosphere.inversion_depth": 1e5,
                        "atmosphere.inversion_strength": 100.0}


def atmosphere_at_rest(overrides: dict, jitter: float = 5.0, backend: str = "cpu"):
    """The `stratified` box at rest in its environment (T = T0(y), no wave) with `overrides`, its particles moved
    from the lattice by up to `jitter` m (so that the density constraint shifts them): (statistics at the start,
    after 1 step, after 10 steps; the temperature anomaly T - T0(y) at the end, K)."""
    from pbf_cuda import Simulation, load_scene
    scene = load_scene("stratified").replace(**{"wave.amplitude": 0.0, **overrides})
    st = Simulation(scene, backend="cpu").state()
    rng = np.random.default_rng(1)
    p = st["position"] + rng.uniform(-jitter, jitter, st["position"].shape).astype(np.float32)
    p[:, 1] = np.clip(p[:, 1], 1.0, scene.domain.size[1] - 1.0)
    st["position"] = p
    st["temperature"] = scene.environment_temperature(p[:, 1]).astype(np.float32)
    sim = Simulation.from_arrays(scene, st, backend=backend)
    out = [sim.stats()]
    sim.step(1)
    out.append(sim.stats())
    sim.step(9)
    out.append(sim.stats())
    end = sim.state()
    return out, end["temperature"].astype(np.float64) - scene.environment_temperature(end["position"][:, 1])


def by_id(state: dict) -> dict:
    """State arrays reordered by particle id (the solver re-sorts particles every step)."""
    order = np.argsort(state["id"], kind="stable")
    return {k: v[order] for k, v in state.items()}


def model_lcl(atmosphere, surface_temperature, q):
    """The model's lifting condensation level (m): z = (T_s - T_d) / Gamma_d with the dew point of the
    saturation law of eq. 10, s(T_d) = q  =>  T_d = B / ln(q / A) - C."""
    a = atmosphere
    dew_point = a.saturation_b / np.log(q / a.saturation_a) - a.saturation_c
    return (surface_temperature - dew_point) / a.dry_lapse_rate


def cloud_base_of_layers(z, cloud):
    """Cloud base (m) of a layer-mean cloud-water profile (cloud[k] at height z[k]): the zero of the straight
    line through the two lowest cloudy layers (cloud water grows linearly with the supersaturation above the
    base, so this resolves the base inside a layer)."""
    j = int(np.nonzero(np.asarray(cloud) > 0.0)[0][0])
    return float(z[j] - cloud[j] * (z[j + 1] - z[j]) / (cloud[j + 1] - cloud[j]))
