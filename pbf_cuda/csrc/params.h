// Parameters of one simulation, flattened from the validated scene (pbf_cuda/scene.py).
// Plain data: it crosses the backend boundary by value. Units are SI (m, s, K, kg, kg/kg).
#pragma once
#include <cstddef>
#include <cstdint>

namespace pbf {

constexpr int kMaxLevels = 13;  // adaptive levels 0..12

struct Params {
    // Domain and boundaries (section 5.1)
    float domain[3] = {1, 1, 1};       // box edge lengths, m; y (index 1) is up
    bool periodic[3] = {true, false, true};
    // Particles
    float spacing = 1.0f;              // lattice spacing d of level 0, m
    float h0 = 2.0f;                   // kernel radius of level 0, m
    float rest_density = 1.0f;         // rho0, kg/m^3
    float mass0 = 1.0f;                // level-0 mass m0, kg (full lattice density = rho0)
    // Time
    float dt = 1.0f;                   // s
    int check_every = 1;               // steps between NaN / bound checks
    // PBF (Macklin & Mueller 2013; paper eq. 1-4)
    int iterations = 4;
    float relaxation = 0.0f;           // epsilon in lambda's denominator, 1/(kg m^2)
    float lambda_ref = 1.0f;           // lambda of a unit constraint violation, kg m^2 (scales s_corr)
    bool unilateral = true;            // C_i = max(rho_i / rho0 - 1, 0)
    float scorr_k = 0.0f;              // tensile term strength relative to lambda_ref
    int scorr_n = 4;
    float scorr_dq = 0.2f;             // dq / h
    bool velocity_projection = false;  // true: divergence-free velocity projection + position-only density
                                       // correction (closed domains); false: Macklin's PBF (free surfaces)
    int divergence_iterations = 2;     // most conjugate-gradient iterations of the velocity projection
    float divergence_tolerance = 0.0f; // stop when RMS(div v) dt is below this (relative density change per step)
    float xsph = 0.0f;                 // XSPH viscosity c
    float viscosity = 0.0f;            // kinematic viscosity nu, m^2/s (pairwise SPH Laplacian)
    float vorticity = 0.0f;            // vorticity confinement epsilon, m/s
    float gravity[3] = {0, 0, 0};      // constant body acceleration, m/s^2
    float max_velocity = 1e3f;         // m/s; faster is unstable
    float max_density_error = 10.0f;   // mean |rho/rho0 - 1| above this is unstable
    // Thermodynamics (section 4); off => no arrays, no kernels
    bool thermodynamics = false;
    float ground_temperature = 300.0f; // K
    float lapse_rate = 6.5e-3f;        // environment lapse, K/m
    float buoyancy = 9.81f;            // k_b, m/s^2 (eq. 6)
    float cloud_gravity = 9.81f;       // k_g, m/s^2 per kg/kg (eq. 6)
    float dry_lapse_rate = 9.8e-3f;    // Gamma_d, K/m (eq. 7)
    float latent_heat = 2489.0f;       // Q, K (eq. 11)
    float phase_rate = 0.5f;           // alpha, 1/s (eq. 9)
    float saturation[3] = {1.795e5f, -4302.6f, -29.65f};  // A (kg/kg), B (K), C (K) of eq. 10
    float heating_rate = 0.0f;         // S_e, K/s (eq. 5)
    float heating_depth = 0.0f;        // m
    float noise_frequency = 0.0f;      // 1/m
    float noise_amplitude = 0.0f;
    float heating_patch_radius = 0.0f; // m; 0: the whole ground is heated
    float noise_offset[2] = {0, 0};
    // Large-scale forcing of the cycling example (docs/cycling.md, eq. C1-C3); 0 => off
    float diurnal_period = 0.0f;       // P of C1, s: heating times max(0, sin(2 pi t / P))
    float relaxation_time = 0.0f;      // tau of C2, s: T and v relax toward T0(y), v0(y)
    float autoconversion_rate = 0.0f;  // k_auto of C3, 1/s
    float autoconversion_threshold = 0.0f;  // q_c0 of C3, kg/kg
    float initial_vapor_ratio = 0.0f;  // k_v of section 5 (the relaxation target v0(y))
    bool vapor_relative = true;        // v0 from T0(y) (true) or from the ground temperature
    // Temperature smoothing (section 4.1); kappa = 0 => no pass
    float kappa = 0.0f;
    float smoothing_beta = 0.0f;       // kappa grad C_ii / |grad C_i|^2 of a full lattice (eq. 17), m^2
    bool smooth_fields[3] = {true, false, false};  // temperature, vapor, cloud
    float smoothing_epsilon = 0.01f;   // epsilon of eq. 13 relative to h^2
    // Adaptivity (section 5.2)
    bool adaptive = false;
    int max_level = 0;
    float k_p = 1.0f, k_c = 1.0f;      // eq. 20
    float split_threshold = 1.0f;      // alpha
    float merge_threshold = 0.0f;      // beta
    float min_distance = 0.35f;        // too-close threshold, times the new particle's kernel radius
    float lookahead_height = 0.0f;     // refinement criterion: 0 = the paper's eq. 20 on w; > 0 = look-ahead rise, m
    std::size_t capacity = 0;          // preallocated particle slots
};

}  // namespace pbf
