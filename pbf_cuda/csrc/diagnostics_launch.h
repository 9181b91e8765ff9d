// Launch code of the diagnostics: the step's energy and heat budget (StepBudget, mass-weighted sums in
// double precision) and the stability check that ends a run (NaN/Inf, speed, density error).
#pragma once
#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "solver_data.h"
#include "thermodynamics.h"

namespace pbf {
namespace PBF_BACKEND_NS {

// ---- the step budget ----------------------------------------------------------------------------
// Mass-weighted sums for the step budget (StepBudget), double precision.
struct BudgetSums {
    double m, my, ke, mT, mw, mq, heat, ape;
};

struct BudgetAdd {
    PBF_HD BudgetSums operator()(const BudgetSums& a, const BudgetSums& b) const {
        return BudgetSums{a.m + b.m, a.my + b.my, a.ke + b.ke, a.mT + b.mT, a.mw + b.mw, a.mq + b.mq,
                          a.heat + b.heat, a.ape + b.ape};
    }
};

struct BudgetTerms {
    AtmosphereParams a;
    const Float4* pos;
    const Float4* vel;          // nullptr: no kinetic energy
    const float* temperature;   // nullptr without thermodynamics
    const float* vapor;
    const float* cloud;
    bool with_heating;
    PBF_HD BudgetSums operator()(uint32_t i) const {
        Float4 p = pos[i];
        double m = p.w;
        BudgetSums s{m, m * p.y, 0, 0, 0, 0, 0, 0};
        if (vel) {
            Vec3 u = xyz(vel[i]);
            s.ke = 0.5 * m * double(dot(u, u));
        }
        if (temperature) {
            float T = temperature[i];
            s.mT = m * T;
            s.mw = m * cloud[i];
            s.mq = m * (double(vapor[i]) + double(cloud[i]));
            if (with_heating) s.heat = m * a.heating(xyz(p), p.w);
            float T0 = a.environment_temperature(p.y);
            double dT = double(T) - T0;
            // available potential energy k_b dT^2 / (2 T0 (Gamma_d - Gamma(y))) of a stable layer, else 0
            float stable = a.dry_lapse_rate - a.env.lapse(p.y);
            if (stable > 0.0f) s.ape = m * (a.buoyancy / T0) * dT * dT * (0.5f / stable);
        }
        return s;
    }
};

// Budget sums over the fluid particles at `positions` (pos or pred): with the kinetic energy (with_vel) and the
// ground heating the particles receive there (with_heating).
inline BudgetSums reduce_budget(const SolverData& d, const dvec<Float4>& positions, bool with_vel, bool with_heating) {
    const bool thermo = d.p.thermodynamics;
    BudgetTerms t{d.atm, raw(positions), with_vel ? raw(d.vel) : nullptr,
                  thermo ? raw(d.temperature) : nullptr, thermo ? raw(d.vapor) : nullptr,
                  thermo ? raw(d.cloud) : nullptr, with_heating};
    return reduce_over(d.n, t, BudgetSums{0, 0, 0, 0, 0, 0, 0, 0}, BudgetAdd{});
}

// The state's totals (no process has acted yet: every heat term 0).
inline void budget_state(StepBudget& b, const BudgetSums& now) {
    b.valid = true;
    double M = now.m > 0 ? now.m : 1.0;
    b.mass = now.m;
    b.mass_centre_height = now.my / M;
    b.kinetic_energy = now.ke;
    b.potential_energy = now.ape;
    b.mean_temperature = now.mT / M;
    b.total_water = now.mq;
}

// The step's budget from the sums at its start and end, the smoothing's heat and the forcing terms.
inline void record_budget(SolverData& d, const BudgetSums& start, const BudgetSums& end, double smoothing_heat,
                          const ForcingSums& forcing) {
    StepBudget& b = d.last_stats.budget;
    budget_state(b, end);
    double M = end.m > 0 ? end.m : 1.0;
    b.heat_source = end.heat / M;
    b.heat_smoothing = smoothing_heat / M;
    b.heat_adiabatic = (-double(d.p.dry_lapse_rate) * (end.my - start.my) + d.shift_heat) / M;
    // Cloud water removed as rain (C3) released no heat: it is no part of the latent term.
    b.heat_latent = double(d.p.latent_heat) * (end.mw - start.mw + forcing.rain) / M;
    b.heat_relaxation = forcing.heat_relax / M;
    b.water_relaxation = forcing.water_relax;
    b.water_rain = forcing.rain;
    if (!d.p.thermodynamics) b.heat_adiabatic = 0.0;
    b.totals[0] += b.heat_source;
    b.totals[1] += b.heat_latent;
    b.totals[2] += b.heat_adiabatic;
    b.totals[3] += b.heat_smoothing;
    b.totals[4] += b.heat_relaxation;
    b.totals[5] += b.water_relaxation;
    b.totals[6] += b.water_rain;
}

// ---- the stability check ------------------------------------------------------------------------
// Stability and diagnostics reduction over the fluid particles.
struct Reduced {
    float err_sum, err_max, speed2_max;
    float excess_sum, deficit_sum;  // sum max(C, 0), sum max(-C, 0): the two sides of the density error
    uint32_t bad;
    uint32_t why;   // OR of the BadKind bits of the bad particles
    float lo[3], hi[3];
};

// Which check a particle failed (ParticleCheck::kinds), named in the instability message.
enum BadKind : uint32_t { kBadPosition = 1, kBadVelocity = 2, kBadSpeed = 4, kBadTemperature = 8, kBadVapor = 16,
                          kBadCloud = 32 };

struct ReduceOp {
    PBF_HD Reduced operator()(const Reduced& a, const Reduced& b) const {
        Reduced r;
        r.err_sum = a.err_sum + b.err_sum;
        r.excess_sum = a.excess_sum + b.excess_sum;
        r.deficit_sum = a.deficit_sum + b.deficit_sum;
        r.err_max = fmaxf(a.err_max, b.err_max);
        r.speed2_max = fmaxf(a.speed2_max, b.speed2_max);
        r.bad = a.bad + b.bad;
        r.why = a.why | b.why;
        for (int k = 0; k < 3; ++k) { r.lo[k] = fminf(a.lo[k], b.lo[k]); r.hi[k] = fmaxf(a.hi[k], b.hi[k]); }
        return r;
    }
};

struct ParticleCheck {
    const Float4* pos;
    const Float4* vel;
    const float* density;
    const float* temperature;  // nullptr without thermodynamics
    const float* vapor;
    const float* cloud;
    float inv_rest_density;
    bool unilateral;
    float max_speed2;
    // BadKind bits of particle i (0: it passes): non-finite position, velocity or thermodynamic field
    // (a vapor or cloud value below zero counts too), or a speed above max_velocity.
    PBF_HD uint32_t kinds(uint32_t i) const {
        Vec3 x = xyz(pos[i]), v = xyz(vel[i]);
        float s2 = dot(v, v);
        uint32_t k = 0;
        if (!finite3(x)) k |= kBadPosition;
        if (!finite3(v)) k |= kBadVelocity;
        else if (!(isfinite(s2) && s2 <= max_speed2)) k |= kBadSpeed;
        if (temperature) {
            if (!isfinite(temperature[i])) k |= kBadTemperature;
            if (!(isfinite(vapor[i]) && vapor[i] >= 0.0f)) k |= kBadVapor;
            if (!(isfinite(cloud[i]) && cloud[i] >= 0.0f)) k |= kBadCloud;
        }
        return k;
    }
    PBF_HD bool is_bad(uint32_t i) const { return kinds(i) != 0; }
    PBF_HD Reduced operator()(uint32_t i) const {
        Reduced r;
        float c = density[i] * inv_rest_density - 1.0f;
        float e = unilateral ? fmaxf(c, 0.0f) : fabsf(c);
        Vec3 x = xyz(pos[i]), v = xyz(vel[i]);
        r.err_sum = e;
        r.err_max = e;
        r.excess_sum = fmaxf(c, 0.0f);
        r.deficit_sum = fmaxf(-c, 0.0f);
        r.speed2_max = dot(v, v);
        r.why = kinds(i);
        r.bad = r.why ? 1u : 0u;
        r.lo[0] = r.hi[0] = x.x;
        r.lo[1] = r.hi[1] = x.y;
        r.lo[2] = r.hi[2] = x.z;
        return r;
    }
};

struct IsBad {
    ParticleCheck check;
    PBF_HD bool operator()(uint32_t i) const { return check.is_bad(i); }
};

inline ParticleCheck make_check(const SolverData& d) {
    float vmax = d.p.max_velocity;
    const bool t = d.p.thermodynamics;
    return ParticleCheck{raw(d.pos), raw(d.vel), raw(d.density), t ? raw(d.temperature) : nullptr,
                         t ? raw(d.vapor) : nullptr, t ? raw(d.cloud) : nullptr, d.cp.inv_rest_density,
                         d.p.unilateral, vmax * vmax};
}

inline Reduced reduce_checks(const SolverData& d) {
    Reduced init;
    init.err_sum = 0.0f; init.err_max = 0.0f; init.excess_sum = 0.0f; init.deficit_sum = 0.0f; init.why = 0; init.speed2_max = 0.0f; init.bad = 0;
    for (int k = 0; k < 3; ++k) { init.lo[k] = INFINITY; init.hi[k] = -INFINITY; }
    return reduce_over(d.n, make_check(d), init, ReduceOp{});
}

// "" when the state passes (and the step becomes the last good one), else
// "unstable|<step>|<last good step>|<reason>|<id,id,...>" (solver_api.h).
inline std::string check(SolverData& d) {
    if (d.n == 0) return std::string();
    Reduced r = reduce_checks(d);
    double mean_err = double(r.err_sum) / double(d.n);
    std::string reason;
    if (r.bad > 0) {
        static const char* names[6] = {"NaN/Inf position", "NaN/Inf velocity", "speed above max_velocity",
                                       "NaN/Inf temperature", "NaN/Inf or negative vapor",
                                       "NaN/Inf or negative cloud"};
        std::string what;
        for (int k = 0; k < 6; ++k)
            if (r.why & (1u << k)) what += (what.empty() ? "" : ", ") + std::string(names[k]);
        reason = std::to_string(r.bad) + " particle(s) with " + what + " (max_velocity = " +
                 std::to_string(d.p.max_velocity) + " m/s)";
    } else if (!(mean_err <= d.p.max_density_error)) {
        reason = "mean density error " + std::to_string(mean_err) + " above max_density_error = " +
                 std::to_string(d.p.max_density_error);
    }
    if (reason.empty()) {
        d.last_good = d.step;
        return std::string();
    }
    std::vector<uint32_t> ids;
    if (r.bad > 0) {
        dvec<uint32_t> idx(d.n);
        auto end = thrust::copy_if(exec(), thrust::counting_iterator<uint32_t>(0),
                                   thrust::counting_iterator<uint32_t>(uint32_t(d.n)), idx.begin(),
                                   IsBad{make_check(d)});
        std::size_t nbad = std::min<std::size_t>(std::size_t(end - idx.begin()), 16);
        // Gather the ids on the device, then one copy to the host.
        dvec<uint32_t> bad_ids(nbad);
        thrust::gather(exec(), idx.begin(), idx.begin() + nbad, d.id.begin(), bad_ids.begin());
        ids.resize(nbad);
        thrust::copy(bad_ids.begin(), bad_ids.end(), ids.begin());
    }
    // Plain string building (no iostreams: their locale machinery is not safe in every link setup).
    std::string msg = "unstable|" + std::to_string(d.step) + "|" + std::to_string(d.last_good) + "|" + reason + "|";
    for (std::size_t k = 0; k < ids.size(); ++k) msg += (k ? "," : "") + std::to_string(ids[k]);
    return msg;
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
