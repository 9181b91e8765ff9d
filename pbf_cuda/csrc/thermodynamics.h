// Cloud dynamics of section 4, per particle:
//   ground heating        dT/dt = S_e(x, z)                            (eq. 5, simplex pattern)
//   adiabatic cooling     dT = -Gamma_d dy                             (eq. 7, dy = the step's rise)
//   phase transition      dw/dt = -dv/dt = alpha (v - gamma)           (eq. 8-9)
//                         gamma = min(A exp(B / (T + C)), v + w)      (eq. 10)
//   latent heat           dT = Q dw                                    (eq. 11)
//   buoyancy and gravity  du_y/dt = k_b (T - T0(y)) / T0(y) - k_g w    (eq. 6; T0(y): environment.h)
// Large-scale forcing of the cycling example (docs/cycling.md, eq. C1-C4; all off by default):
//   time of day           S_e(t) = S_e f(t), f(t) = max(0, sin(2 pi t / P))            (C1)
//   relaxation            dT/dt = -(T - T0(y)) / tau,  dv/dt = -(v - v0(y)) / tau      (C2)
//                         integrated exactly: X = X0 + (X - X0) exp(-dt / tau)
//   autoconversion        dw/dt = -k_auto max(0, w - q_c0), w removed as rain          (C3)
//                         integrated exactly: w = q_c0 + (w - q_c0) exp(-k_auto dt) above q_c0
// Large-scale forcing of BOMEX (Siebesma et al. 2003, eq. 4-6; scene [forcing], all off by default):
//   subsidence            dtheta/dt = -w_s(y) dtheta0/dy,  dv/dt = -w_s(y) dv0/dy                    (L1)
//   radiative cooling     dtheta/dt = R(y)                                                          (L2)
//   moisture tendency     dv/dt = M(y)                                                              (L3)
//   w_s, R, M piecewise linear in y through 4 knots (LinearProfile); forward Euler over dt. At a fixed
//   height dT = dtheta (theta = T + Gamma_d y), so the tendencies act on T. theta0(y) = T0(y) + Gamma_d y
//   and v0(y) are the environment profiles (environment.h, initial_vapor): the subsidence is the vertical
//   advection of the MEAN profile, -w_s d<theta>/dz as BOMEX prescribes it, with the model's mean profile
//   taken to be its environment (the buoyancy's reference T0(y)). Why not a displacement of the particles
//   by w_s, or the advection of each particle's own field: w_s(y) is divergent (dw_s/dy != 0, balanced by a
//   large-scale horizontal inflow outside the periodic box), which an incompressible particle set cannot
//   follow, and BOMEX applies it to the horizontal mean only, not to the anomalies (the resolved motion
//   advects those); a per-particle gradient would need a neighbour sum and carry the particles' noise.
//   The increments are a few ulps of T (at 300 K one ulp is 3e-5 K; 2 K/day at dt = 2 s is 1.5 ulp), so
//   round-to-nearest would bias them (1.5 ulp always becomes 2: +32%); they are added with stochastic
//   rounding instead (dithered_add: to a neighbouring multiple of the ulp, up or down with the probabilities
//   that make the mean exact, from a hash of the particle's id and the step). The budget books what was added.
// Order per step: heating, adiabatic, large-scale (L1-L3), relaxation, phase transition, autoconversion,
// buoyancy.
// The paper lists buoyancy before the adiabatic term. Here the buoyancy is evaluated last, with the
// temperature and cloud water that belong to the particle's new height: with the paper's order the
// force sees a temperature that is Gamma_d dy too warm for a rising particle (too cold for a sinking
// one), a force proportional to +u_y that makes every gravity wave grow (e-folding time
// T0 / (k_b Gamma_d dt), 1000 s at dt = 3 s). With this order the step is a symplectic Euler step
// of the oscillator and a wave's energy stays bounded.
// The phase transition is integrated exactly over the step for the linearised coupled system
// (deficit D = v - gamma decays at rate alpha (1 + Q dgamma/dT)), so it is stable for any
// alpha dt, and total water v + w is conserved by construction (v = q - w).
#pragma once
#include "common.h"
#include "environment.h"
#include "noise.h"

namespace pbf {

// A profile f(y) piecewise linear through (z[k], v[k]), k = 0..3 (z non-decreasing, m), constant below z[0]
// and above z[3]; a knot repeated at one height is a step.
struct LinearProfile {
    float z[4];
    float v[4];
    PBF_HD float at(float y) const {
        if (!(y > z[0])) return v[0];
        for (int k = 1; k < 4; ++k) {
            if (y <= z[k]) {
                float span = z[k] - z[k - 1];
                return span > 0.0f ? v[k - 1] + (v[k] - v[k - 1]) * ((y - z[k - 1]) / span) : v[k];
            }
        }
        return v[3];
    }
};

struct AtmosphereParams {
    EnvironmentProfile env;   // T0(y)
    float buoyancy, cloud_gravity, dry_lapse_rate, latent_heat, phase_rate;
    float sat_a, sat_b, sat_c;
    float heating_rate, heating_depth, noise_frequency, noise_amplitude, noise_offset[2];
    float heating_layer, mass0;            // level-0 layer thickness (m) and mass (kg)
    float patch_radius, patch_centre[2];   // heated patch (m); radius 0: the whole ground
    float dt;
    // Large-scale forcing (docs/cycling.md): diurnal factor of this step (C1), relaxation (C2),
    // autoconversion (C3), initial vapor profile v0(y) = vapor_ratio A exp(B / (T_ref + C)).
    float diurnal;            // f(t) at the step's mid-time; 1 without a diurnal cycle
    float relax_decay;        // exp(-dt / tau); 1 without relaxation
    float auto_decay;         // exp(-k_auto dt); 1 without autoconversion
    float auto_threshold;     // q_c0, kg/kg
    float vapor_ratio;        // k_v of section 5
    float vapor_ratio_above;  // k_v above a capping inversion (blended across its layer); < 0: k_v
    bool vapor_relative;      // v0 follows T0(y) (true) or the ground temperature (false)
    // Large-scale forcing of BOMEX (L1-L3 above): off unless large_scale.
    bool large_scale;
    LinearProfile subsidence; // w_s(y), m/s (< 0: subsiding)
    LinearProfile radiative;  // R(y), K/s
    LinearProfile moisture;   // M(y), kg/kg per s

    PBF_HD float environment_temperature(float y) const { return env.temperature(y); }
    // Temperature change of a density-constraint shift dy that ends at y (pbf.shift_keeps_anomaly): eq. 7 took
    // -Gamma_d dy over the whole displacement; the shift is no rise of the air, so it keeps the anomaly
    // T - T0 instead: + Gamma_d dy + T0(y) - T0(y - dy), i.e. (Gamma_d - Gamma) dy for the linear profile.
    PBF_HD float shift_change(float y, float dy) const {
        if (!env.has_inversion()) return (dry_lapse_rate - env.lapse_rate) * dy;
        return dry_lapse_rate * dy + env.change(y, dy);
    }
    PBF_HD float saturation(float T) const { return sat_a * expf(sat_b / (T + sat_c)); }
    // Relative heating S / S_e at ground position (x, z) (eq. 5).
    PBF_HD float heating_pattern(float x, float z) const {
        double n = simplex2(double(x) * noise_frequency + noise_offset[0],
                            double(z) * noise_frequency + noise_offset[1]);
        float s = 1.0f + noise_amplitude * float(n);
        if (patch_radius > 0.0f) {  // one heated patch: (1 - (r/R)^2)^2 inside r < R
            float dx = x - patch_centre[0], dz = z - patch_centre[1];
            float q = 1.0f - (dx * dx + dz * dz) / (patch_radius * patch_radius);
            s *= q > 0.0f ? q * q : 0.0f;
        }
        return s > 0.0f ? s : 0.0f;
    }
    // Fraction of the layer of a particle of mass m at height y that lies below heating_depth H: the
    // particle stands for the slab [y - d/2, y + d/2], d = heating_layer (m / m0)^(1/3) (its level's lattice
    // spacing), so a lattice column takes exactly H of heated air at any spacing, also where H < d.
    PBF_HD float heated_fraction(float y, float m) const {
        float d = heating_layer * (m == mass0 ? 1.0f : cbrtf(m / mass0));
        float f = (heating_depth - (y - 0.5f * d)) / d;
        return f <= 0.0f ? 0.0f : (f >= 1.0f ? 1.0f : f);
    }
    // Temperature change of one step from the ground heating of a particle of mass m at x (eq. 5), K.
    PBF_HD float heating(Vec3 x, float m) const {
        if (!(heating_rate > 0.0f) || !(heating_depth > 0.0f)) return 0.0f;
        float f = heated_fraction(x.y, m);
        if (f == 0.0f) return 0.0f;
        return heating_rate * f * diurnal * heating_pattern(x.x, x.z) * dt;   // eq. 5 with C1
    }
    // Buoyancy and the weight of cloud water, du_y/dt of eq. 6, m/s^2.
    PBF_HD float buoyancy_acceleration(float T, float w, float y) const {
        float T0 = environment_temperature(y);
        return buoyancy * (T - T0) / T0 - cloud_gravity * w;
    }
    // Initial (and relaxation target) vapor v0(y), kg/kg (section 5).
    PBF_HD float initial_vapor(float y) const { return vapor_ratio_at(y) * saturation(vapor_reference_temperature(y)); }
    // k_v at height y: k_v, blended across a capping inversion's layer to the ratio above it.
    PBF_HD float vapor_ratio_at(float y) const {
        float k = vapor_ratio;
        if (vapor_ratio_above >= 0.0f) k += (vapor_ratio_above - vapor_ratio) * env.inversion_fraction(y);
        return k;
    }
    // The temperature of v0's saturation: T0(y) for the relative profile, the ground's for the uniform one, K.
    PBF_HD float vapor_reference_temperature(float y) const {
        return vapor_relative ? environment_temperature(y) : env.ground_temperature;
    }
    // dtheta0/dy = Gamma_d - Gamma(y) of the environment's potential temperature theta0 = T0 + Gamma_d y, K/m.
    PBF_HD float potential_temperature_gradient(float y) const { return dry_lapse_rate - env.lapse(y); }
    // dv0/dy of initial_vapor, 1/m: k'(y) s + k s'(T) dT_ref/dy, s = A exp(B / (T + C)), s' = -B s / (T + C)^2,
    // dT_ref/dy = -Gamma(y) for the relative profile (0 for the uniform one); k' = (k_a - k_v) / delta inside
    // the inversion layer. At a kink, the lower segment's value (as env.lapse).
    PBF_HD float vapor_gradient(float y) const {
        float dk = 0.0f;
        if (vapor_ratio_above >= 0.0f) {
            float f = env.inversion_fraction(y);
            if (f > 0.0f && f < 1.0f) dk = (vapor_ratio_above - vapor_ratio) / env.inversion_depth;
        }
        float t_ref = vapor_reference_temperature(y);
        float s = saturation(t_ref);
        float ds = vapor_relative ? s * (-sat_b) / ((t_ref + sat_c) * (t_ref + sat_c)) * (-env.lapse(y)) : 0.0f;
        return dk * s + vapor_ratio_at(y) * ds;
    }
};

// What the large-scale forcing of one particle did in one step (mass-weighted sums in double).
struct ForcingSums {
    double heat_relax;   // sum m dT from the relaxation (C2), kg K
    double water_relax;  // sum m dv from the relaxation (C2), kg (vapor added: > 0)
    double rain;         // sum m dw removed by autoconversion (C3), kg (>= 0)
    double heat_subsidence;   // sum m dT from the subsidence (L1), kg K
    double heat_radiation;    // sum m dT from the radiative cooling (L2), kg K
    double water_subsidence;  // sum m dv from the subsidence (L1), kg
    double water_tendency;    // sum m dv from the moisture tendency (L3), kg
};

struct ForcingAdd {
    PBF_HD ForcingSums operator()(const ForcingSums& a, const ForcingSums& b) const {
        return ForcingSums{a.heat_relax + b.heat_relax, a.water_relax + b.water_relax, a.rain + b.rain,
                           a.heat_subsidence + b.heat_subsidence, a.heat_radiation + b.heat_radiation,
                           a.water_subsidence + b.water_subsidence, a.water_tendency + b.water_tendency};
    }
};

// Exact-exponential phase transition with latent heat (eq. 9-11) over dt; updates T, v, w.
PBF_INLINE void phase_transition(const AtmosphereParams& a, float& T, float& v, float& w) {
    float q = v + w;
    float s = a.saturation(T);
    float dw;
    if (s < q) {
        // gamma = s: D = v - s relaxes at k = alpha (1 + Q ds/dT)
        float ds_dT = s * (-a.sat_b) / ((T + a.sat_c) * (T + a.sat_c));
        float gain = 1.0f + a.latent_heat * ds_dT;
        float D = v - s;
        dw = D * (-expm1f(-a.phase_rate * gain * a.dt)) / gain;
    } else {
        // gamma = q (sub-saturated even with all cloud evaporated): w decays exponentially
        dw = -w * (-expm1f(-a.phase_rate * a.dt));
    }
    if (dw < -w) dw = -w;
    float w_new = w + dw;
    T += a.latent_heat * (w_new - w);
    w = w_new;
    v = q - w_new;
}

// x + dx rounded to a multiple of x's float spacing (its ulp), down or up at random so that the mean is x + dx:
// with u uniform in [0, 1), x + ulp floor(dx / ulp + u). Exact arithmetic while x stays in its binade.
PBF_INLINE float dithered_add(float x, float dx, float u) {
    int e;
    frexpf(x, &e);                        // x = m 2^e, 0.5 <= |m| < 1: ulp = 2^(e - 24)
    float ulp = ldexpf(1.0f, e - 24);
    return x + ulp * floorf(dx / ulp + u);
}

// The large-scale forcing L1-L3 of one step of a particle at height y (m) of mass m (kg): updates T and v (v kept
// >= 0) and books what each term added in f. seed: a hash of the particle's id and the step (the dither).
PBF_INLINE void large_scale_forcing(const AtmosphereParams& a, float y, double m, uint32_t seed, float& T, float& v,
                                    ForcingSums& f) {
    float T_sub = dithered_add(T, -a.subsidence.at(y) * a.potential_temperature_gradient(y) * a.dt,
                               hash_unit(seed));                                                        // L1
    float T_new = dithered_add(T_sub, a.radiative.at(y) * a.dt, hash_unit(seed + 0x9E3779B9u));         // L2
    float v_sub = fmaxf(dithered_add(v, -a.subsidence.at(y) * a.vapor_gradient(y) * a.dt,
                                     hash_unit(seed + 0x3C6EF372u)), 0.0f);                             // L1
    float v_new = fmaxf(dithered_add(v_sub, a.moisture.at(y) * a.dt, hash_unit(seed + 0xDAA66D2Bu)), 0.0f);  // L3
    f.heat_subsidence = m * (double(T_sub) - double(T));
    f.heat_radiation = m * (double(T_new) - double(T_sub));
    f.water_subsidence = m * (double(v_sub) - double(v));
    f.water_tendency = m * (double(v_new) - double(v_sub));
    T = T_new;
    v = v_new;
}

// Runs the cloud dynamics of particle i and returns what its forcing terms changed (thrust
// transform_reduce visits each particle exactly once, so the update and the budget are one pass).
struct CloudDynamics {
    AtmosphereParams a;
    const Float4* pos_old;   // positions at the start of the step
    const Float4* pos_new;   // positions after the PBF solve
    const float* shift_y;    // nullptr, or the density constraint's vertical shift (pbf.shift_keeps_anomaly)
    Float4* vel;
    float* temperature;
    float* vapor;
    float* cloud;
    const uint32_t* id;      // particle ids and the step: the large-scale forcing's dither (large_scale_forcing)
    uint32_t step;
    PBF_HD ForcingSums operator()(uint32_t i) const {
        Vec3 x = xyz(pos_new[i]);
        double m = pos_new[i].w;
        float T = temperature[i], v = vapor[i], w = cloud[i];
        ForcingSums f{};
        T += a.heating(x, pos_new[i].w);                                                    // eq. 5, C1
        T -= a.dry_lapse_rate * (x.y - pos_old[i].y);                                      // eq. 7
        if (shift_y) T += a.shift_change(x.y, shift_y[i]);                                 // shift: dT0 = -Gamma dy
        if (a.large_scale) large_scale_forcing(a, x.y, m, hash_u32(id[i] ^ hash_u32(step)), T, v, f);  // L1-L3
        float T0 = a.environment_temperature(x.y);
        if (a.relax_decay < 1.0f) {                                                        // C2
            float T_new = T0 + (T - T0) * a.relax_decay;
            float v0 = a.initial_vapor(x.y);
            float v_new = fmaxf(v0 + (v - v0) * a.relax_decay, 0.0f);
            f.heat_relax = m * (double(T_new) - double(T));
            f.water_relax = m * (double(v_new) - double(v));
            T = T_new;
            v = v_new;
        }
        phase_transition(a, T, v, w);                                                      // eq. 9-11
        if (a.auto_decay < 1.0f && w > a.auto_threshold) {                                 // C3
            float w_new = a.auto_threshold + (w - a.auto_threshold) * a.auto_decay;
            f.rain = m * (double(w) - double(w_new));
            w = w_new;
        }
        float accel = a.buoyancy_acceleration(T, w, x.y);                                  // eq. 6
        Float4 u = vel[i];
        vel[i] = Float4{u.x, u.y + a.dt * accel, u.z, u.w};
        temperature[i] = T;
        vapor[i] = v;
        cloud[i] = w;
        return f;
    }
};

}  // namespace pbf
