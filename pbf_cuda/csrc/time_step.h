// The time step: operators stated per step turned into rates per unit time, and the CFL-controlled step.
//
// Operators per unit time. Two of the step's operators are relaxations whose strength the paper states per
// step: eq. 17's kappa (the smoothing moves a particle's temperature toward its neighbours' by a fraction of the
// difference each step) and XSPH's c (the velocity toward the neighbours' mean). Applied once per step with a
// fixed coefficient, halving dt doubles the mixing per simulated second, so the model would not converge as dt
// shrinks. Both are stated at a reference step dt_ref (time.reference_dt, the paper's 2 s for the cloud scenes)
// and applied over dt with the same decay per second:
//     c(dt) = 1 - (1 - c)^(dt / dt_ref)                    (exactly c at dt = dt_ref)
// i.e. the rate -ln(1 - c) / dt_ref, 1/s. Two steps of dt/2 relax a uniform difference as one step of dt does,
// and c(dt) < 1 for every dt. Eq. 17's h^2 dependence is unchanged: beta_l = beta_0 (h_l / h0)^2 at every level,
// each scaled by the same c(dt) / c.
// The density constraint and its tensile term s_corr keep their per-iteration form: together they project the
// particles onto rho = rho0 with a regular arrangement, correcting the disorder the step's motion made (which
// scales with dt), not adding a displacement per unit time. Stated as a rate instead (its displacement times
// dt / dt_ref), a halved step regularised the arrangement less, and the stratified scene's wave lost energy at
// less than first order in dt (at dt = 2.5 s 0.81 of its loss at 5 s; 0.44 with s_corr per iteration). Every
// other operator of the step is already a rate times dt or integrated exactly over dt (thermodynamics.h:
// heating, buoyancy, phase change, relaxation, autoconversion; pbf_constraints.h: viscosity nu dt, vorticity
// confinement eps dt).
//
// CFL-controlled steps (time.cfl > 0): after each step, from the largest |v_i| / h_i of the state (reduced with the
// step's check, h_i the particle's kernel radius, read with the step's sums: no added host read),
//     dt_next = clamp(cfl / max_i(|v_i| / h_i), dt_min, dt_max),  at most 1.25 dt of the step before,
// as SPlisHSPlasH's CFL method (factor, minimum, maximum) and DualSPHysics' variable step do. The CFL number
// max_i |v_i| dt / h_i of every step is in the statistics, with or without control, and a state whose CFL number
// exceeds time.max_cfl ends the run as unstable (diagnostics_launch.h: check).
#pragma once
#include <algorithm>
#include <cmath>

#include "params.h"

namespace pbf {

// The per-step coefficients at the step in use.
struct StepRates {
    float xsph;             // XSPH c(dt)
    float kappa;            // eq. 17b's kappa(dt)
    float smoothing_beta;   // beta_0 at dt (eq. 17), m^2
    float scorr = 1.0f;     // s_corr's k at dt relative to its stated value: (dt / dt_ref)^pbf.scorr_dt_power
};

// c(dt) = 1 - (1 - c)^(dt / dt_ref): a relaxation by the fraction c per dt_ref, applied over dt.
inline double per_step_fraction(double c, double dt, double dt_ref) {
    if (!(c > 0.0)) return 0.0;
    if (dt == dt_ref) return c;
    if (c >= 1.0) return 1.0;
    return -std::expm1((dt / dt_ref) * std::log1p(-c));
}

inline StepRates step_rates(const Params& p) {
    StepRates r;
    const double dt = p.dt, ref = p.reference_dt;
    r.xsph = float(per_step_fraction(p.xsph, dt, ref));
    r.kappa = float(per_step_fraction(p.kappa, dt, ref));
    r.smoothing_beta = p.smoothing_beta;
    if (dt != ref && p.kappa > 0.0f) r.smoothing_beta = float(double(p.smoothing_beta) * (double(r.kappa) / p.kappa));
    if (dt != ref && p.scorr_dt_power > 0.0f) r.scorr = float(std::pow(dt / ref, double(p.scorr_dt_power)));
    return r;
}

// The step after one (p.dt) whose state has the largest |v_i| / h_i = rate_max, 1/s.
inline float next_time_step(const Params& p, float rate_max) {
    double next = rate_max > 0.0f ? double(p.cfl) / rate_max : double(p.dt_max);
    next = std::min(next, 1.25 * double(p.dt));
    next = std::min(std::max(next, double(p.dt_min)), double(p.dt_max));
    return float(next);
}

}  // namespace pbf
