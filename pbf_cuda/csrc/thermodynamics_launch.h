// Launch code of the cloud dynamics (section 4, eq. 5-11, the large-scale forcing C1-C3 of
// docs/cycling.md and L1-L3 of BOMEX; thermodynamics.h): one pass over the fluid particles that updates T, v, w and the
// vertical velocity and sums what the forcing terms changed.
#pragma once
#include <cmath>

#include "device_memory.h"
#include "reduce.h"
#include "solver_data.h"
#include "thermodynamics.h"

namespace pbf {
namespace PBF_BACKEND_NS {

inline EnvironmentProfile make_environment_profile(const Params& p) {
    return EnvironmentProfile{p.ground_temperature, p.lapse_rate,       p.inversion_height,
                              p.inversion_depth,    p.inversion_strength, p.lapse_rate_above};
}

inline AtmosphereParams make_atmosphere_params(const Params& p) {
    AtmosphereParams atm{};
    atm.env = make_environment_profile(p);
    atm.buoyancy = p.buoyancy;
    atm.cloud_gravity = p.cloud_gravity;
    atm.dry_lapse_rate = p.dry_lapse_rate;
    atm.latent_heat = p.latent_heat;
    atm.phase_rate = p.phase_rate;
    atm.sat_a = p.saturation[0];
    atm.sat_b = p.saturation[1];
    atm.sat_c = p.saturation[2];
    atm.heating_rate = p.heating_rate;
    atm.heating_depth = p.heating_depth;
    atm.heating_layer = p.heating_layer;
    atm.mass0 = p.mass0;
    atm.noise_frequency = p.noise_frequency;
    atm.noise_amplitude = p.noise_amplitude;
    atm.noise_offset[0] = p.noise_offset[0];
    atm.noise_offset[1] = p.noise_offset[1];
    atm.patch_radius = p.heating_patch_radius;
    atm.patch_centre[0] = 0.5f * p.domain[0];
    atm.patch_centre[1] = 0.5f * p.domain[2];
    atm.dt = p.dt;
    atm.diurnal = 1.0f;
    atm.relax_decay = p.relaxation_time > 0.0f ? float(std::exp(-double(p.dt) / p.relaxation_time)) : 1.0f;
    atm.auto_decay = p.autoconversion_rate > 0.0f ? float(std::exp(-double(p.autoconversion_rate) * p.dt)) : 1.0f;
    atm.auto_threshold = p.autoconversion_threshold;
    atm.vapor_ratio = p.initial_vapor_ratio;
    atm.vapor_ratio_above = p.vapor_ratio_above;
    atm.vapor_relative = p.vapor_relative;
    atm.large_scale = p.large_scale_forcing;
    for (int k = 0; k < 4; ++k) {
        atm.subsidence.z[k] = p.subsidence_heights[k];
        atm.subsidence.v[k] = p.subsidence_values[k];
        atm.radiative.z[k] = p.radiative_heights[k];
        atm.radiative.v[k] = p.radiative_values[k];
        atm.moisture.z[k] = p.moisture_heights[k];
        atm.moisture.v[k] = p.moisture_values[k];
    }
    return atm;
}

// Time-of-day factor f(t) = max(0, sin(2 pi t / P)) of the surface heating (docs/cycling.md C1).
inline float diurnal_factor(const Params& p, double t) {
    if (!(p.diurnal_period > 0.0f)) return 1.0f;
    double s = std::sin(2.0 * 3.14159265358979323846 * t / double(p.diurnal_period));
    return s > 0.0 ? float(s) : 0.0f;
}

// Heating, adiabatic cooling, relaxation, phase transition, autoconversion, buoyancy (thermodynamics.h has the
// order and why); the forcing terms' sums go to the step's StepSums, for the budget.
inline void cloud_dynamics(SolverData& d) {
    if (!d.p.thermodynamics) return;
    d.clock.begin(kPhaseCloudDynamics);
    reduce_into(d.n, CloudDynamics{d.atm, raw(d.pos), raw(d.pred), d.shift_y.empty() ? nullptr : raw(d.shift_y),
                                   raw(d.vel), raw(d.temperature), raw(d.vapor), raw(d.cloud), raw(d.id),
                                   uint32_t(d.step)},
                ForcingSums{}, ForcingAdd{}, &raw(d.step_sums)->forcing);
    d.clock.end(kPhaseCloudDynamics);
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
