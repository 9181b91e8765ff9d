"""Conservation through merges (section 5.2; issue 54), CPU backend.

Pairs of level-1 and level-2 particles, each particle with its own random velocity, temperature, vapour and
cloud water (partners that are not the two halves of one split, so no field is equal between them), merged by the
split/merge phase alone (Simulation.adapt: adapt_now). Mass, momentum, heat (sum m T) and water (sum m v, sum m w)
must be what they were, to float32 precision, and merges must have happened.
"""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pbf_cuda import load_scene
from pbf_bruteforce import params_of
from pbf_cuda.simulation import _core


def pairs_state(p, rng, n_side=4, level_mix=0.5):
    """Pairs of same-level particles (level 1 or 2) 0.4 h_l apart, their midpoints on a jittered lattice of
    spacing h0 (every other particle farther than the too-close distance from a midpoint), random directions."""
    h0 = p.h0
    centres = []
    lo = np.array(p.domain) / 2 - 0.5 * (n_side - 1) * h0
    for i in range(n_side):
        for j in range(n_side):
            for k in range(n_side):
                centres.append(lo + np.array([i, j, k]) * h0 + rng.uniform(-0.05, 0.05, 3) * h0)
    pos, mass = [], []
    for c in centres:
        level = 1 if rng.uniform() < level_mix else 2
        hl = h0 * 2.0 ** (-level / 3.0)
        d = rng.normal(size=3)
        d *= 0.2 * hl / np.linalg.norm(d)
        pos += [c + d, c - d]
        mass += [p.mass0 / 2 ** level] * 2
    n = len(pos)
    return {
        "position": np.array(pos, np.float32), "mass": np.array(mass, np.float32),
        "velocity": rng.normal(0.0, 2.0, (n, 3)).astype(np.float32),
        "temperature": rng.uniform(285.0, 305.0, n).astype(np.float32),
        "vapor": rng.uniform(2e-3, 1.5e-2, n).astype(np.float32),
        "cloud": rng.uniform(0.0, 2e-5, n).astype(np.float32),          # E = k_p (1 - exp(-k_c w)) below beta
    }


def totals(st):
    m = st["mass"].astype(np.float64)
    return {
        "mass": m.sum(),
        "momentum": (m[:, None] * st["velocity"].astype(np.float64)).sum(axis=0),
        "heat": (m * st["temperature"]).sum(),
        "vapor": (m * st["vapor"]).sum(),
        "cloud": (m * st["cloud"]).sum(),
    }


def scales(st):
    m = st["mass"].astype(np.float64)
    return {"momentum": (m[:, None] * np.abs(st["velocity"])).sum(), "heat": (m * st["temperature"]).sum(),
            "vapor": (m * st["vapor"]).sum(), "cloud": (m * st["cloud"]).sum()}


def merged(p, st, backend="cpu"):
    s = _core().Solver(p, backend)
    s.set_boundary(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32))
    n = len(st["mass"])
    s.set_fluid(st["position"], st["velocity"], st["temperature"], st["vapor"], st["cloud"], st["mass"],
                np.arange(n, dtype=np.uint32))
    s.adapt_now()
    pos4, vel4 = s.get_float4("position"), s.get_float4("velocity")
    out = {"position": pos4[:, :3], "mass": pos4[:, 3], "velocity": vel4[:, :3],
           "temperature": s.get_float("temperature"), "vapor": s.get_float("vapor"), "cloud": s.get_float("cloud")}
    return out, s.stats()


def check_merge_conservation(seed, backend="cpu"):
    sc = load_scene("growing_adaptive", **{"domain.size": [1224.0, 1224.0, 1224.0]})
    p = params_of(sc, capacity=512)
    p.split_threshold = 0.9
    p.coarse_near_walls = False
    rng = np.random.default_rng(seed)
    st0 = pairs_state(p, rng)
    out, stats = merged(p, st0, backend)
    n0, n1 = len(st0["mass"]), len(out["mass"])
    assert stats["merges_last_step"] == n0 - n1
    assert n0 - n1 >= n0 // 4                                       # most pairs merged
    a, b, sc_ = totals(st0), totals(out), scales(st0)
    assert b["mass"] == a["mass"]                                   # powers of two: exact
    assert np.abs(b["momentum"] - a["momentum"]).max() < 1e-6 * sc_["momentum"]
    for key in ("heat", "vapor", "cloud"):
        assert abs(b[key] - a[key]) < 1e-6 * sc_[key], key
    # the merged particles carry their parents' mean (equal masses): velocities of a merge are no parent's own
    lighter = np.setdiff1d(np.round(out["mass"], 3), np.round(st0["mass"], 3))
    assert len(lighter) > 0                                         # new, coarser levels exist


@settings(max_examples=8, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**16))
def test_merges_conserve_mass_momentum_heat_and_water(seed):
    check_merge_conservation(seed)


@pytest.mark.gpu
def test_merges_conserve_on_the_gpu():
    for seed in range(3):
        check_merge_conservation(seed, backend="cuda")
