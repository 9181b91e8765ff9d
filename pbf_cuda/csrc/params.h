// Parameters of one simulation, flattened from the validated scene (pbf_cuda/scene.py).
// Plain data: it crosses the backend boundary by value. Units are SI (m, s, K, kg, kg/kg).
//
// Every parameter is declared once, in PBF_PARAMS below; the struct's fields, the Python bindings
// (bindings.cpp: Params attributes and core.declared_params()) and the copy from the scene
// (pbf_cuda/simulation.py: build_params) are generated from that list. Units, ranges and the meaning
// of a scene field are declared once too, in the scene schema (pbf_cuda/scene.py): the field named
// here is where a parameter's value comes from, and its default here is the schema's default
// (tests/test_params.py fails when the two drift apart).
//
//   S(type, name, scene field, default)               a scalar
//   A(type, name, length, scene field, defaults...)   a fixed-length array
//
// "scene field" is "section.field" when build_params copies the scene's value unchanged, or "" when it
// computes the value from the scene (pbf_cuda/simulation.py: DERIVED names what each one reads).
#pragma once
#include <cstddef>
#include <cstdint>

namespace pbf {

constexpr int kMaxLevels = 13;  // adaptive levels 0..12

#define PBF_PARAMS(S, A)                                                                                            \
    /* Domain and boundaries (section 5.1); y (index 1) is up */                                                   \
    A(float, domain, 3, "domain.size", 3200.0f, 3200.0f, 3200.0f)                                                  \
    A(bool, periodic, 3, "", true, false, true)            /* per axis, from domain.boundary */                    \
    /* Particles */                                                                                                \
    S(float, spacing, "", 1.0f)                            /* mean lattice spacing d of level 0, m */              \
    S(float, h0, "", 2.0f)                                 /* kernel radius of level 0, m */                       \
    S(float, rest_density, "particles.rest_density", 1.0f) /* rho0, kg/m^3 */                                      \
    S(float, mass0, "", 1.0f)                              /* level-0 mass m0, kg (full lattice density = rho0) */ \
    /* Time */                                                                                                     \
    S(float, dt, "time.dt", 2.0f)                          /* the first step; every step where cfl = 0, s */      \
    S(float, reference_dt, "time.reference_dt", 2.0f)      /* the step kappa and xsph are stated at, s */          \
    S(float, cfl, "time.cfl", 0.0f)                        /* > 0: dt = cfl min_i h_i / |v_i| each step */        \
    S(float, dt_min, "time.dt_min", 1e-6f)                 /* bounds of the controlled step, s */                 \
    S(float, dt_max, "time.dt_max", 1e3f)                                                                          \
    S(float, max_cfl, "time.max_cfl", 2.0f)                /* max_i |v_i| dt / h_i above this is unstable */      \
    S(int, check_every, "time.check_every", 1)                                                                     \
    /* PBF (Macklin & Mueller 2013; paper eq. 1-4) */                                                              \
    S(int, iterations, "pbf.iterations", 4)                                                                        \
    S(float, relaxation, "", 0.0f)                         /* epsilon in lambda's denominator, 1/(kg m^2) */       \
    S(float, lambda_ref, "", 1.0f)                         /* lambda of a unit violation, kg m^2 (scales s_corr) */\
    S(bool, unilateral, "pbf.unilateral", true)            /* C_i = max(rho_i / rho0 - 1, 0) */                    \
    S(bool, remove_column_drift, "pbf.remove_column_drift", true) /* velocity projection: sum m u_y = 0 */      \
    S(bool, remove_shift_drift, "pbf.remove_shift_drift", false) /* density solve: sum m dy = 0 (closed column) */\
    S(bool, shift_keeps_anomaly, "pbf.shift_keeps_anomaly", false) /* density shift dT = -Gamma_env dy */         \
    S(float, scorr_k, "pbf.scorr_k", 0.01f)                /* tensile term strength relative to lambda_ref */      \
    S(int, scorr_n, "pbf.scorr_n", 4)                                                                              \
    S(float, scorr_dq, "pbf.scorr_dq", 0.2f)               /* dq / h */                                            \
    S(float, scorr_fine, "pbf.scorr_fine", 1.0f)           /* s_corr weight on pairs with a particle finer than level 0 */\
    S(float, scorr_dt_power, "pbf.scorr_dt_power", 0.0f)   /* s_corr k times (dt / reference_dt)^power (time_step.h) */\
    S(bool, velocity_projection, "", false)                /* pbf.projection == "velocity" */                      \
    S(bool, neighbor_list, "pbf.neighbor_list", true)      /* per-step neighbour lists (neighbor_list.h) */        \
    S(int, divergence_iterations, "pbf.divergence_iterations", 4)                                                  \
    S(float, divergence_tolerance, "pbf.divergence_tolerance", 0.0f)                                               \
    S(bool, gradient_correction, "pbf.gradient_correction", false)                                                 \
    S(float, xsph, "pbf.xsph", 0.01f)                      /* XSPH viscosity c per reference_dt */                 \
    S(float, viscosity, "pbf.viscosity", 0.0f)             /* kinematic viscosity nu, m^2/s */                     \
    S(float, vorticity, "pbf.vorticity", 0.0f)             /* vorticity confinement epsilon, m/s */                \
    A(float, gravity, 3, "pbf.gravity", 0.0f, 0.0f, 0.0f)  /* constant body acceleration, m/s^2 */                 \
    S(float, max_velocity, "pbf.max_velocity", 1e3f)       /* m/s; faster is unstable */                           \
    S(float, max_density_error, "pbf.max_density_error", 10.0f)                                                    \
    /* Thermodynamics (section 4); off => no arrays, no kernels */                                                 \
    S(bool, thermodynamics, "", false)                     /* the scene has an [atmosphere] section */             \
    S(float, ground_temperature, "atmosphere.ground_temperature", 300.0f)  /* K */                                 \
    S(float, lapse_rate, "atmosphere.lapse_rate", 6.5e-3f)                 /* environment lapse, K/m */            \
    S(float, inversion_height, "atmosphere.inversion_height", 0.0f)        /* z_i, m; 0: none (environment.h) */   \
    S(float, inversion_depth, "atmosphere.inversion_depth", 200.0f)        /* delta, m */                          \
    S(float, inversion_strength, "atmosphere.inversion_strength", 0.0f)    /* dT across the inversion, K */        \
    S(float, lapse_rate_above, "atmosphere.lapse_rate_above", 6.5e-3f)     /* Gamma_a above it, K/m */             \
    S(float, vapor_ratio_above, "atmosphere.vapor_ratio_above", -1.0f)     /* k_v above it; < 0: as below */       \
    S(float, buoyancy, "atmosphere.buoyancy", 9.81f)                       /* k_b, m/s^2 (eq. 6) */                \
    S(float, cloud_gravity, "atmosphere.cloud_gravity", 9.81f)             /* k_g, m/s^2 per kg/kg (eq. 6) */      \
    S(float, dry_lapse_rate, "atmosphere.dry_lapse_rate", 9.8e-3f)         /* Gamma_d, K/m (eq. 7) */              \
    S(float, latent_heat, "atmosphere.latent_heat", 2489.0f)               /* Q, K (eq. 11) */                     \
    S(float, phase_rate, "atmosphere.phase_rate", 0.5f)                    /* alpha, 1/s (eq. 9) */                \
    A(float, saturation, 3, "", 1.795e5f, -4302.6f, -29.65f)  /* A (kg/kg), B (K), C (K) of eq. 10 */             \
    S(float, heating_rate, "atmosphere.heating_rate", 0.05f) /* S_e, K/s (eq. 5), of the air below heating_depth */ \
    S(float, heating_depth, "atmosphere.heating_depth", 100.0f) /* m; each particle heated by its layer's overlap */ \
    S(float, heating_layer, "", 0.0f)     /* vertical lattice spacing of level 0, m (a particle's layer: x (m/m0)^1/3) */ \
    S(float, noise_frequency, "atmosphere.noise_frequency", 0.00125f)      /* 1/m */                               \
    S(float, noise_amplitude, "atmosphere.noise_amplitude", 1.0f)                                                  \
    S(float, heating_patch_radius, "atmosphere.heating_patch_radius", 0.0f) /* m; 0: the whole ground */           \
    A(float, noise_offset, 2, "atmosphere.noise_offset", 0.0f, 0.0f)                                               \
    /* Large-scale forcing of the cycling example (docs/cycling.md, eq. C1-C3); 0 => off */                        \
    S(float, diurnal_period, "atmosphere.diurnal_period", 0.0f)            /* P of C1, s */                        \
    S(float, relaxation_time, "atmosphere.relaxation_time", 0.0f)          /* tau of C2, s */                      \
    S(float, autoconversion_rate, "atmosphere.autoconversion_rate", 0.0f)  /* k_auto of C3, 1/s */                 \
    S(float, autoconversion_threshold, "atmosphere.autoconversion_threshold", 5e-4f)  /* q_c0 of C3, kg/kg */      \
    S(float, initial_vapor_ratio, "atmosphere.initial_vapor_ratio", 0.5f)  /* k_v of section 5 (target v0(y)) */   \
    /* Large-scale forcing of BOMEX (Siebesma et al. 2003, eq. 4-6; scene [forcing]): piecewise-linear profiles */ \
    /* of height through 4 knots (heights non-decreasing, m); every value 0 => off (thermodynamics.h) */           \
    S(bool, large_scale_forcing, "", false)                /* the scene has a [forcing] section with a value != 0 */\
    A(float, subsidence_heights, 4, "forcing.subsidence_heights", 0.0f, 1000.0f, 2000.0f, 3000.0f)  /* m */       \
    A(float, subsidence_values, 4, "forcing.subsidence_values", 0.0f, 0.0f, 0.0f, 0.0f)  /* w_s, m/s (< 0: down) */\
    A(float, radiative_heights, 4, "forcing.radiative_heights", 0.0f, 1000.0f, 2000.0f, 3000.0f)    /* m */       \
    A(float, radiative_values, 4, "forcing.radiative_values", 0.0f, 0.0f, 0.0f, 0.0f)    /* dtheta/dt, K/s */      \
    A(float, moisture_heights, 4, "forcing.moisture_heights", 0.0f, 1000.0f, 2000.0f, 3000.0f)      /* m */       \
    A(float, moisture_values, 4, "forcing.moisture_values", 0.0f, 0.0f, 0.0f, 0.0f)      /* dq_v/dt, 1/s */        \
    S(bool, vapor_relative, "", true)                      /* v0 from T0(y) (true) or the ground temperature */    \
    /* Temperature smoothing (section 4.1); kappa = 0 => no pass */                                                \
    S(float, kappa, "", 0.0f)                                             /* kappa of eq. 17b per reference_dt */  \
    S(float, smoothing_beta, "", 0.0f)     /* kappa grad C_ii / |grad C_i|^2 of a full lattice (eq. 17) at reference_dt, m^2 */ \
    A(bool, smooth_fields, 3, "", true, false, false)      /* temperature, vapor, cloud */                         \
    S(float, smoothing_epsilon, "smoothing.epsilon", 0.01f)  /* epsilon of eq. 13 relative to h^2 */               \
    /* Adaptivity (section 5.2) */                                                                                 \
    S(bool, adaptive, "adaptive.enabled", false)                                                                   \
    S(int, max_level, "", 0)                                                                                       \
    S(bool, pair_kernel_mean_radius, "", false)  /* the pair kernel at (h_i + h_j)/2 instead of eq. 19 */        \
    S(float, k_p, "adaptive.k_p", 1.0f)                    /* eq. 20 */                                            \
    S(float, k_c, "adaptive.k_c", 2000.0f)                 /* eq. 20, 1/(kg/kg) */                                 \
    S(float, split_threshold, "adaptive.split_threshold", 0.3f)   /* alpha */                                      \
    S(float, merge_threshold, "adaptive.merge_threshold", 0.05f)  /* beta */                                       \
    S(float, min_distance, "adaptive.min_distance", 0.35f)  /* too-close threshold, times the new radius */        \
    S(float, lookahead_height, "", 0.0f)   /* refinement: 0 = the paper's eq. 20 on w; > 0 = look-ahead rise, m */ \
    S(bool, refine_warm_air, "", false)    /* refinement: also on the heat excess (T - T0(y)) / Q (thermal) */   \
    S(float, heating_time, "", 0.0f)       /* refinement: > 0 also on the ground heating below, S_e tau / Q */    \
    S(bool, coarse_near_walls, "adaptive.coarse_near_walls", true) /* level 0 within h0 of a wall */              \
    S(int, adapt_every, "adaptive.every", 1)               /* split and merge every this many steps */          \
    S(std::size_t, capacity, "", 0)                        /* preallocated particle slots */

struct Params {
#define PBF_PARAM_FIELD(type, name, source, value) type name = value;
#define PBF_PARAM_ARRAY_FIELD(type, name, length, source, ...) type name[length] = {__VA_ARGS__};
    PBF_PARAMS(PBF_PARAM_FIELD, PBF_PARAM_ARRAY_FIELD)
#undef PBF_PARAM_FIELD
#undef PBF_PARAM_ARRAY_FIELD
};

}  // namespace pbf
