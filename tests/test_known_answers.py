"""Known answers for each term of the particle solver's momentum and heat equations (issue 54), CPU backend.

Every test runs one step of the solver on a few particles and compares a term with the paper's formula evaluated
independently (float64 numpy, tests/pbf_bruteforce.py), over hypothesis-drawn parameters rather than one set:
  eq. 6   buoyancy and cloud-water loading   du_y = dt (k_b (T - T0(y)) / T0(y) - k_g w)
  eq. 7   adiabatic cooling                  dT = -Gamma_d dy
  eq. 9-11 phase transition, latent heat     the exact exponential of thermodynamics.h, dT = Q dw, v + w kept
  eq. 5   ground heating                     dT = S_e f dt, f the part of the particle's layer below the depth
  eq. 12-17 smoothing                        the pairwise exchange with the pair's mean beta, on mixed levels
  XSPH, vorticity confinement (Macklin eq. 15-17) on mixed levels.
Isolated particles (more than a kernel radius apart) feel no pair term, so the single-particle terms are exact.
"""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pbf_cuda import load_scene
from pbf_bruteforce import mixed_cluster, one_step, pair_kernels, params_of

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)


def scene():
    return load_scene("growing_adaptive", **{"domain.size": [1224.0, 1224.0, 1224.0]})


# Every process off; a test switches on the one it checks. No adaptation (k_p = 0: E = 0, never below a merge
# threshold of 0), no column drift removal (it would subtract the mean of the buoyancy), no gravity.
QUIET = dict(unilateral=True, heating_rate=0.0, phase_rate=0.0, kappa=0.0, smoothing_beta=0.0, xsph=0.0,
             vorticity=0.0, viscosity=0.0, k_p=0.0, merge_threshold=0.0, remove_column_drift=False, scorr_k=0.0,
             gravity=[0.0, 0.0, 0.0])


def params(sc, **overrides):
    return params_of(sc, **{**QUIET, **overrides})


def isolated(n, rng, sc, y_range=(300.0, 900.0)):
    """n <= 16 particles at heights spread over y_range, more than 2 h0 apart horizontally (no neighbours)."""
    h0 = sc.kernel_radius
    cells = np.array([(i, k) for i in range(4) for k in range(4)])[:n]
    x = np.empty((n, 3))
    x[:, [0, 2]] = 150.0 + cells * 2.2 * h0
    x[:, 1] = np.linspace(*y_range, n)
    return x


def environment(sc, y):
    return np.asarray(sc.environment_temperature(np.asarray(y, np.float64)), np.float64)


# ---- eq. 6: buoyancy and the weight of cloud water ------------------------------------------------------
@SETTINGS
@given(k_b=st.floats(0.5, 20.0), k_g=st.floats(0.5, 20.0), dt=st.floats(0.5, 5.0), seed=st.integers(0, 2**16))
def test_buoyancy_and_cloud_loading_on_a_resting_box(k_b, k_g, dt, seed):
    sc = scene()
    rng = np.random.default_rng(seed)
    n = 12
    x = isolated(n, rng, sc)
    T0 = environment(sc, x[:, 1])
    T = (T0 + rng.uniform(-5.0, 5.0, n)).astype(np.float32)
    w = rng.uniform(0.0, 5e-3, n).astype(np.float32)
    vapor = np.full(n, 1e-3, np.float32)
    p = params(sc, buoyancy=k_b, cloud_gravity=k_g, dt=dt)
    out = one_step(p, x, np.zeros_like(x), np.full(n, p.mass0), T, vapor, w)
    expect = dt * (k_b * (T.astype(np.float64) - T0) / T0 - k_g * w.astype(np.float64))
    assert np.allclose(out["position"], x, atol=1e-3)                       # at rest: nothing moved
    assert np.allclose(out["velocity"][:, 1], expect, rtol=2e-4, atol=2e-6 * k_b * dt)
    assert np.abs(out["velocity"][:, [0, 2]]).max() == 0.0
    assert np.array_equal(out["cloud"], w) and np.array_equal(out["temperature"], T)


def test_cloud_water_is_a_drag_not_a_lift():
    sc = scene()
    x = isolated(4, None, sc, y_range=(500.0, 500.0))
    T = environment(sc, x[:, 1]).astype(np.float32)
    w = np.array([0.0, 1e-3, 2e-3, 4e-3], np.float32)
    p = params(sc, buoyancy=9.81, cloud_gravity=9.81, dt=2.0)
    out = one_step(p, x, np.zeros_like(x), np.full(4, p.mass0), T, np.full(4, 1e-3, np.float32), w)
    uy = out["velocity"][:, 1]
    assert abs(uy[0]) < 1e-6
    assert np.allclose(uy, -2.0 * 9.81 * w, rtol=1e-4, atol=1e-7)


# ---- eq. 7: adiabatic cooling ---------------------------------------------------------------------------
@SETTINGS
@given(gamma_d=st.floats(2e-3, 2e-2), dt=st.floats(0.5, 5.0), seed=st.integers(0, 2**16))
def test_adiabatic_cooling_of_a_rising_parcel(gamma_d, dt, seed):
    sc = scene()
    rng = np.random.default_rng(seed)
    n = 10
    x = isolated(n, rng, sc)
    uy = rng.uniform(-5.0, 5.0, n)
    v = np.zeros_like(x)
    v[:, 1] = uy
    T = environment(sc, x[:, 1]).astype(np.float32)
    p = params(sc, dry_lapse_rate=gamma_d, dt=dt, buoyancy=9.81, cloud_gravity=0.0)
    out = one_step(p, x, v, np.full(n, p.mass0), T, np.full(n, 1e-3, np.float32), np.zeros(n, np.float32))
    dy = out["position"][:, 1] - x[:, 1]
    assert np.allclose(dy, uy * dt, atol=1e-3)
    T1 = T - gamma_d * dy
    assert np.allclose(out["temperature"], T1, atol=2e-4)
    # the buoyancy at the new height and temperature (thermodynamics.h: evaluated last)
    T0 = environment(sc, out["position"][:, 1])
    assert np.allclose(out["velocity"][:, 1], uy + dt * 9.81 * (T1 - T0) / T0, atol=2e-5)


# ---- eq. 9-11: phase transition with latent heat ----------------------------------------------------------
def saturation(a, T):
    return a.saturation_a * np.exp(a.saturation_b / (T + a.saturation_c))


def phase_transition(a, T, v, w, alpha, Q, dt):
    """The exact exponential of the linearised coupled system (thermodynamics.h), float64."""
    q = v + w
    s = saturation(a, T)
    ds = s * (-a.saturation_b) / (T + a.saturation_c) ** 2
    gain = 1.0 + Q * ds
    dw = np.where(s < q, (v - s) * (-np.expm1(-alpha * gain * dt)) / gain, -w * (-np.expm1(-alpha * dt)))
    dw = np.maximum(dw, -w)
    return T + Q * dw, q - (w + dw), w + dw


@SETTINGS
@given(alpha=st.floats(0.01, 2.0), Q=st.floats(500.0, 3000.0), dt=st.floats(0.5, 5.0), seed=st.integers(0, 2**16))
def test_phase_transition_and_latent_heat(alpha, Q, dt, seed):
    sc = scene()
    a = sc.atmosphere
    rng = np.random.default_rng(seed)
    n = 16
    x = isolated(n, rng, sc)
    T = (environment(sc, x[:, 1]) + rng.uniform(-3.0, 3.0, n)).astype(np.float32)
    s = saturation(a, T.astype(np.float64))
    vapor = (s * rng.uniform(0.7, 1.3, n)).astype(np.float32)        # sub- and supersaturated
    cloud = np.where(rng.uniform(size=n) < 0.5, 0.0, rng.uniform(0.0, 2e-3, n)).astype(np.float32)
    p = params(sc, phase_rate=alpha, latent_heat=Q, dt=dt, buoyancy=0.0, cloud_gravity=0.0)
    out = one_step(p, x, np.zeros_like(x), np.full(n, p.mass0), T, vapor, cloud)
    T1, v1, w1 = phase_transition(a, T.astype(np.float64), vapor.astype(np.float64), cloud.astype(np.float64),
                                  alpha, Q, dt)
    scale = float(np.abs(w1 - cloud).max()) + 1e-9
    assert np.allclose(out["cloud"], w1, atol=2e-3 * scale + 1e-8)
    assert np.allclose(out["temperature"], T1, atol=2e-3 * Q * scale + 1e-4)
    # total water kept, latent heat Q per unit of condensed water, condensation where supersaturated
    assert np.allclose(out["vapor"] + out["cloud"], vapor.astype(np.float64) + cloud, rtol=0, atol=1e-8)
    dw = out["cloud"] - cloud
    assert np.allclose(out["temperature"] - T, Q * dw, atol=1e-4 + 1e-3 * Q * np.abs(dw).max())
    supersaturated = vapor > s * 1.02
    assert np.all(dw[supersaturated] > 0.0)
    assert np.all(dw[(vapor < s * 0.98)] <= 0.0)


# ---- eq. 5: ground heating ---------------------------------------------------------------------------------
@SETTINGS
@given(rate=st.floats(0.005, 0.5), depth=st.floats(20.0, 300.0), dt=st.floats(0.5, 5.0), seed=st.integers(0, 2**16))
def test_ground_heating_is_rate_times_heated_fraction(rate, depth, dt, seed):
    sc = scene()
    rng = np.random.default_rng(seed)
    n = 16
    x = isolated(n, rng, sc, y_range=(1.0, 1.5 * depth + 60.0))
    m = np.where(rng.uniform(size=n) < 0.5, 1.0, 0.125)              # levels 0 and 3: layers d and d / 2
    T = environment(sc, x[:, 1]).astype(np.float32)
    p = params(sc, heating_rate=rate, heating_depth=depth, noise_amplitude=0.0, dt=dt, buoyancy=0.0,
                  cloud_gravity=0.0, heating_patch_radius=0.0)
    mass = p.mass0 * m
    out = one_step(p, x, np.zeros_like(x), mass, T, np.full(n, 1e-4, np.float32), np.zeros(n, np.float32))
    d = p.heating_layer * np.cbrt(m)
    f = np.clip((depth - (x[:, 1] - 0.5 * d)) / d, 0.0, 1.0)
    assert np.allclose(out["temperature"] - T, rate * f * dt, atol=1e-4)
    assert (f > 0.0).any() and (f == 0.0).any()       # heated and unheated layers both tested


def per_step(c, dt, reference_dt):
    """A relaxation by the fraction c per reference_dt applied over dt: 1 - (1 - c)^(dt / reference_dt)."""
    return -np.expm1((dt / reference_dt) * np.log1p(-c))


# ---- eq. 12-17: smoothing on mixed levels ------------------------------------------------------------------
def smoothing_exchange(p, sc, x, mass, T, beta, cap=0.5):
    """dT_i = -sum_j c_ij (T_i - T_j - (T0(y_i) - T0(y_j))) with c_ij = (beta_i + beta_j)/2 (m_j / rho0) s_ij,
    beta_l = beta_0 (h_l / h0)^2, s_ij = x_ij . grad W_ij / (|x_ij|^2 + eps h_i h_j), and the limiter's scaling
    min(1, cap / max(S_i, S_j)), S_i = sum_j c_ij (smoothing.h)."""
    r, r2, _, G, h = pair_kernels(p, x, mass)
    beta = beta * (h / p.h0) ** 2                            # beta_l = beta_0 (h_l / h0)^2
    s = np.einsum("ijk,ijk->ij", r, G) / (r2 + p.smoothing_epsilon * h[:, None] * h[None, :])
    c = 0.5 * (beta[:, None] + beta[None, :]) * mass[None, :] / p.rest_density * s
    np.fill_diagonal(c, 0.0)
    S = np.maximum(c, 0.0).sum(axis=1)
    top = np.maximum(S[:, None], S[None, :])
    c = np.where(top > cap, c * cap / np.where(top > cap, top, 1.0), c)
    anomaly = T - environment(sc, x[:, 1])
    return -(c * (anomaly[:, None] - anomaly[None, :])).sum(axis=1)


@SETTINGS
@given(kappa=st.floats(0.1, 0.9), dt=st.sampled_from([2.0, 0.7, 3.1]), seed=st.integers(0, 2**16))
def test_smoothing_matches_the_pairwise_exchange_on_mixed_levels(kappa, dt, seed):
    sc = scene()
    rng = np.random.default_rng(seed)
    p = params(sc, iterations=0, buoyancy=0.0, cloud_gravity=0.0, kappa=kappa, smooth_fields=[True, False, False],
               dt=dt, reference_dt=2.0)
    beta0 = params_of(sc).smoothing_beta / float(np.float32(sc.smoothing.kappa))   # beta of eq. 17 per unit kappa
    p.smoothing_beta = float(np.float32(kappa)) * beta0
    x, mass = mixed_cluster(p, rng, n0=5, n1=8, n2=5, spread=1.2)
    T = (environment(sc, x[:, 1]) + rng.uniform(-5.0, 5.0, len(x))).astype(np.float32)
    out = one_step(p, x, np.zeros_like(x), mass, T, np.full(len(x), 1e-4, np.float32), np.zeros(len(x), np.float32))
    # kappa is stated per reference_dt: over dt it is 1 - (1 - kappa)^(dt / reference_dt), and beta with it
    kappa_dt = per_step(float(np.float32(kappa)), dt, p.reference_dt)
    dT = smoothing_exchange(p, sc, x, mass, T.astype(np.float64), beta=kappa_dt * beta0)
    assert np.abs(dT).max() > 0.05 * kappa_dt                        # the exchange is not negligible
    assert np.allclose(out["temperature"] - T, dT, atol=2e-3 * np.abs(dT).max() + 1e-4)
    # antisymmetric exchange: sum m T is conserved (to float32 rounding of T ~ 300 K)
    assert abs(np.sum(mass * (out["temperature"] - T))) < 1e-4 * np.sum(mass)


# ---- XSPH and vorticity confinement on mixed levels -----------------------------------------------------------
def cross(a, b):
    return np.cross(a, b)


@SETTINGS
@given(xsph=st.floats(0.01, 0.2), eps=st.floats(0.0, 2.0), dt=st.sampled_from([2.0, 0.7, 3.1]),
       seed=st.integers(0, 2**16))
def test_xsph_and_vorticity_confinement_match_their_sums(xsph, eps, dt, seed):
    sc = scene()
    rng = np.random.default_rng(seed)
    p = params(sc, thermodynamics=False, velocity_projection=False, iterations=1, unilateral=True,
               xsph=xsph, vorticity=eps, dt=dt, reference_dt=2.0)
    xsph = per_step(xsph, dt, p.reference_dt)              # XSPH's c is stated per reference_dt
    x, mass = mixed_cluster(p, rng, n0=4, n1=6, n2=6, spread=0.8)
    p.rest_density = 1e3 * p.rest_density                  # far below it (unilateral): no position correction
    v = rng.normal(0.0, 1.0, x.shape)
    out = one_step(p, x, v, mass)
    xs = out["position"]                                    # x* (no wrap: the cluster sits mid-box)
    u = (xs - x) / p.dt                                     # the position projection's velocity
    rho = out["density"]                                    # the solver's last density iteration's
    _, _, W, G, _ = pair_kernels(p, xs, mass)
    np.fill_diagonal(W, 0.0)
    V = mass / rho
    du = u[None, :, :] - u[:, None, :]                      # u_j - u_i
    visc = np.einsum("ij,ijk->ik", W * V[None, :], du)
    omega = np.einsum("j,ijk->ik", V, cross(G, du))
    mag = np.linalg.norm(omega, axis=1)
    eta = np.einsum("ij,ijk->ik", V[None, :] * (mag[None, :] - mag[:, None]), G)
    length = np.linalg.norm(eta, axis=1, keepdims=True)
    N = np.where(length > 1e-20, eta / np.where(length > 1e-20, length, 1.0), 0.0)
    confinement = p.dt * eps * cross(N, omega)
    expect = u + xsph * visc + confinement
    scale = np.abs(expect - u).max()
    assert scale > 1e-4
    # u is read back from float32 positions of ~600 m: a velocity quantum of ulp(x) / dt each
    quantum = float(np.spacing(np.float32(np.abs(xs).max()))) / p.dt
    tol = 2e-3 * scale + 2 * quantum
    # N = eta / |eta| is ill-conditioned where eta's terms nearly cancel: there only the force's size is known
    terms = np.einsum("ij,ij->i", np.abs(V[None, :] * (mag[None, :] - mag[:, None])), np.linalg.norm(G, axis=2))
    well = length[:, 0] > 1e-3 * terms
    assert well.sum() >= len(well) // 2 and (W > 0).sum(axis=1).mean() > 2   # neighbours, mostly well-conditioned
    assert np.allclose(out["velocity"][well], expect[well], atol=tol)
    forced = np.linalg.norm(out["velocity"] - u - xsph * visc, axis=1)
    assert np.all(forced <= p.dt * eps * mag + 2 * tol)
    # the confinement force is perpendicular to the vorticity it confines
    assert np.abs(np.einsum("ik,ik->i", out["velocity"] - u - xsph * visc, omega)).max() < 3 * tol * mag.max()


def test_xsph_leaves_a_uniform_flow_alone():
    sc = scene()
    rng = np.random.default_rng(3)
    p = params(sc, thermodynamics=False, velocity_projection=False, iterations=1, unilateral=True,
               xsph=0.2, vorticity=1.0)
    x, mass = mixed_cluster(p, rng, n0=4, n1=6, n2=6, spread=0.8)
    p.rest_density = 1e3 * p.rest_density                  # no position correction
    v = np.tile([1.5, -0.5, 2.0], (len(x), 1))
    out = one_step(p, x, v, mass)
    assert np.allclose(out["velocity"], v, atol=1e-4)


# ---- the same known answers on the CUDA backend ---------------------------------------------------------------
@pytest.mark.gpu
def test_known_answers_on_the_gpu(monkeypatch):
    import pbf_bruteforce
    monkeypatch.setattr(pbf_bruteforce, "BACKEND", "cuda")
    for seed in (0, 1):
        test_buoyancy_and_cloud_loading_on_a_resting_box.hypothesis.inner_test(k_b=9.81, k_g=9.81, dt=2.0, seed=seed)
        test_adiabatic_cooling_of_a_rising_parcel.hypothesis.inner_test(gamma_d=9.8e-3, dt=2.0, seed=seed)
        test_phase_transition_and_latent_heat.hypothesis.inner_test(alpha=0.5, Q=2489.0, dt=2.0, seed=seed)
        test_ground_heating_is_rate_times_heated_fraction.hypothesis.inner_test(rate=0.05, depth=100.0, dt=2.0,
                                                                                seed=seed)
        test_smoothing_matches_the_pairwise_exchange_on_mixed_levels.hypothesis.inner_test(kappa=0.3, dt=0.7, seed=seed)
        test_xsph_and_vorticity_confinement_match_their_sums.hypothesis.inner_test(xsph=0.05, eps=0.5, dt=3.1,
                                                                                   seed=seed)
    test_cloud_water_is_a_drag_not_a_lift()
