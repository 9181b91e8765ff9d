// Launch code of the diagnostics: the step's energy and heat budget (StepBudget, mass-weighted sums in
// double precision) and the stability check that ends a run: a particle's state out of range (NaN/Inf, outside
// the domain, speed, temperature, water), the mean density error, the CFL number, a collapsed fluid, and
// mechanical energy created where nothing forces the fluid.
#pragma once
#include <thrust/copy.h>
#include <thrust/gather.h>
#include <thrust/iterator/counting_iterator.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "device_memory.h"
#include "diagnostics.h"
#include "parallel_for.h"
#include "reduce.h"
#include "solver_data.h"

namespace pbf {
namespace PBF_BACKEND_NS {

// ---- the step budget ----------------------------------------------------------------------------
// Budget sums over the fluid particles at `positions` (pos or pred): with the kinetic energy (with_vel) and the
// ground heating the particles receive there (with_heating).
inline BudgetTerms budget_terms(const SolverData& d, const dvec<Float4>& positions, bool with_vel, bool with_heating) {
    const bool thermo = d.p.thermodynamics;
    return BudgetTerms{d.atm, raw(positions), with_vel ? raw(d.vel) : nullptr,
                       thermo ? raw(d.temperature) : nullptr, thermo ? raw(d.vapor) : nullptr,
                       thermo ? raw(d.cloud) : nullptr, with_heating};
}
// ... read by the host now (the statistics before the first step).
inline BudgetSums reduce_budget(const SolverData& d, const dvec<Float4>& positions, bool with_vel, bool with_heating) {
    return reduce_over(d.n, budget_terms(d, positions, with_vel, with_heating), BudgetSums{0, 0, 0, 0, 0, 0, 0, 0},
                       BudgetAdd{});
}
// ... into *out in device memory (a field of the step's StepSums).
inline void reduce_budget_into(const SolverData& d, const dvec<Float4>& positions, bool with_vel, bool with_heating,
                               BudgetSums* out) {
    reduce_into(d.n, budget_terms(d, positions, with_vel, with_heating), BudgetSums{0, 0, 0, 0, 0, 0, 0, 0},
                BudgetAdd{}, out);
}

// The step's start sums over the fluid at x. The start needs what the last step's end summed (at x*, which the commit
// made x) wherever nothing has changed the particles since: no merge or split, no state set from the host, no wrap
// on the vertical axis (d.end_budget_is_next_start). Then the end record serves (bitwise the same sums: the same
// particles in the same order; record_budget reads only its mass, height and water sums) and the step makes one
// reduction over the particles fewer.
struct StartFromEnd {
    StepSums* s;
    PBF_HD void operator()() const { s->start = s->end; }
};
inline void start_budget(SolverData& d) {
    StepSums* sums = raw(d.step_sums);
    if (d.end_budget_is_next_start) run_once(StartFromEnd{sums});
    else reduce_budget_into(d, d.pos, false, false, &sums->start);
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

// The step's budget from its StepSums (copied to the host at the step's end): the sums at its start and end, the
// smoothing's heat (the change of sum m T it made; 0 up to rounding, the pairwise form conserves it), the
// density solve's kept shift and the forcing terms.
inline void record_budget(SolverData& d, const StepSums& s) {
    const BudgetSums& start = s.start;
    const BudgetSums& end = s.end;
    const ForcingSums forcing = d.p.thermodynamics ? s.forcing : ForcingSums{};
    const double smoothing_heat = d.smoothing && d.p.smooth_fields[0] ? s.smoothing_heat : 0.0;
    const double shift_heat = d.shift_y.empty() ? 0.0 : s.shift_heat;
    StepBudget& b = d.last_stats.budget;
    budget_state(b, end);
    double M = end.m > 0 ? end.m : 1.0;
    b.heat_source = end.heat / M;
    b.heat_smoothing = smoothing_heat / M;
    b.heat_adiabatic = (-double(d.p.dry_lapse_rate) * (end.my - start.my) + shift_heat) / M;
    // Cloud water removed as rain (C3) released no heat: it is no part of the latent term.
    b.heat_latent = double(d.p.latent_heat) * (end.mw - start.mw + forcing.rain) / M;
    b.heat_relaxation = forcing.heat_relax / M;
    b.water_relaxation = forcing.water_relax;
    b.water_rain = forcing.rain;
    b.heat_subsidence = forcing.heat_subsidence / M;
    b.heat_radiation = forcing.heat_radiation / M;
    b.water_subsidence = forcing.water_subsidence;
    b.water_tendency = forcing.water_tendency;
    if (!d.p.thermodynamics) b.heat_adiabatic = 0.0;
    b.totals[0] += b.heat_source;
    b.totals[1] += b.heat_latent;
    b.totals[2] += b.heat_adiabatic;
    b.totals[3] += b.heat_smoothing;
    b.totals[4] += b.heat_relaxation;
    b.totals[5] += b.water_relaxation;
    b.totals[6] += b.water_rain;
    b.totals[7] += b.heat_subsidence;
    b.totals[8] += b.heat_radiation;
    b.totals[9] += b.water_subsidence;
    b.totals[10] += b.water_tendency;
}

// ---- the stability check ------------------------------------------------------------------------
inline ParticleCheck make_check(const SolverData& d) {
    float vmax = d.p.max_velocity;
    const bool t = d.p.thermodynamics;
    ParticleCheck c{raw(d.pos), raw(d.vel), raw(d.density), t ? raw(d.temperature) : nullptr,
                    t ? raw(d.vapor) : nullptr, t ? raw(d.cloud) : nullptr, d.cp.inv_rest_density,
                    d.p.unilateral, vmax * vmax, d.p.h0, 1.0f / d.p.mass0};
    for (int k = 0; k < 3; ++k) {
        c.lo[k] = d.p.periodic[k] ? -INFINITY : -d.p.h0;
        c.hi[k] = d.p.periodic[k] ? INFINITY : d.p.domain[k] + d.p.h0;
    }
    return c;
}

PBF_HD inline Reduced no_checks() {
    Reduced init;
    init.err_sum = 0.0f; init.err_max = 0.0f; init.excess_sum = 0.0f; init.deficit_sum = 0.0f; init.why = 0; init.speed2_max = 0.0f; init.rate_max = 0.0f; init.bad = 0;
    for (int k = 0; k < 3; ++k) { init.lo[k] = INFINITY; init.hi[k] = -INFINITY; }
    return init;
}
inline Reduced reduce_checks(const SolverData& d) { return reduce_over(d.n, make_check(d), no_checks(), ReduceOp{}); }
// The check over the particles that are there, where the step adapted and the count is still in device memory
// (SolverData::adapt_waiting: d.n is a bound, the particles the count in the step's sums).
template <class F>
struct CheckBelowCount {
    F check;
    const uint32_t* count;
    PBF_HD Reduced operator()(uint32_t i) const { return i < *count ? check(i) : no_checks(); }
};
inline void reduce_checks_into(const SolverData& d, Reduced* out) {
    if (d.adapt_waiting)
        reduce_into(d.n, CheckBelowCount<ParticleCheck>{make_check(d), &raw(d.step_sums)->adapt.alive}, no_checks(),
                    ReduceOp{}, out);
    else
        reduce_into(d.n, make_check(d), no_checks(), ReduceOp{}, out);
}

// The fluid's bounding box (each walled axis's extent plus one lattice spacing, a periodic axis's whole length)
// over its rest volume sum m / rho0. A fluid whose density stays near rho0 fills at least its rest volume, so a
// box below kMinVolumeFraction of it is a collapsed fluid (every particle pressed onto a wall or into a plane),
// whatever its density error reads.
constexpr double kMinVolumeFraction = 0.5;
inline double box_volume_fraction(const SolverData& d, const Reduced& r, double mass) {
    double box = 1.0;
    for (int k = 0; k < 3; ++k)
        box *= d.p.periodic[k] ? double(d.p.domain[k]) : std::max(double(r.hi[k]) - r.lo[k], 0.0) + d.p.spacing;
    return mass > 0.0 ? box * d.p.rest_density / mass : 1.0;
}

// Mechanical energy sum m |v|^2 / 2 + sum m |g| y of a fluid nothing forces (no thermodynamics, no vorticity
// confinement, gravity along y only), J. Walls are at rest and the solver dissipates, so the energy may not rise
// above its value when the state was set by more than kEnergySlack of that energy's scale (the potential energy of
// the fluid lifted by one kernel radius, plus the kinetic energy of every particle moving 1% of h0 per step). A
// compressed start (particles closer than the rest lattice) releases the constraint's stored energy as motion, most
// of it in the first step, so the reference is the larger of the energy when the state was set and after its first
// checked step; the slack is wide (a dam break jittered by 0.3 spacings gains 7% more over its next steps), and a run
// that creates energy grows past any such bound within a few steps.
constexpr double kEnergySlack = 0.5;
inline bool energy_checked(const Params& p) {
    return !p.thermodynamics && !(p.vorticity > 0.0f) && p.gravity[0] == 0.0f && p.gravity[2] == 0.0f;
}
inline double mechanical_energy(const Params& p, const BudgetSums& s) { return s.ke - double(p.gravity[1]) * s.my; }
inline double energy_scale(const Params& p, double mass) {
    const double creep = 0.01 * p.h0 / p.dt;
    return mass * (std::fabs(double(p.gravity[1])) * p.h0 + 0.5 * creep * creep);
}

// "" when the state passes (and the step becomes the last good one), else
// "unstable|<step>|<last good step>|<reason>|<id,id,...>" (solver_api.h). r: the check's sums of this state; end:
// the step's budget sums at its end (mass, height, kinetic energy).
inline std::string check(SolverData& d, const Reduced& r, const BudgetSums& end) {
    if (d.n == 0) return std::string();
    double mean_err = double(r.err_sum) / double(d.n);
    const double cfl = double(d.p.dt) * r.rate_max;
    const double volume_fraction = box_volume_fraction(d, r, end.m);
    std::string reason;
    if (r.bad > 0) {
        static const char* names[6] = {"NaN/Inf or out-of-domain position", "NaN/Inf velocity",
                                       "speed above max_velocity", "NaN/Inf or out-of-range temperature (50-1000 K)",
                                       "NaN/Inf or out-of-range vapor (0-1 kg/kg)",
                                       "NaN/Inf or out-of-range cloud (0-1 kg/kg)"};
        std::string what;
        for (int k = 0; k < 6; ++k)
            if (r.why & (1u << k)) what += (what.empty() ? "" : ", ") + std::string(names[k]);
        reason = std::to_string(r.bad) + " particle(s) with " + what + " (max_velocity = " +
                 std::to_string(d.p.max_velocity) + " m/s)";
    } else if (!(mean_err <= d.p.max_density_error)) {
        reason = "mean density error " + std::to_string(mean_err) + " above max_density_error = " +
                 std::to_string(d.p.max_density_error);
    } else if (!(cfl <= d.p.max_cfl)) {
        reason = "CFL number (largest speed x dt / kernel radius) " + std::to_string(cfl) + " above time.max_cfl = " +
                 std::to_string(d.p.max_cfl) + " (dt = " + std::to_string(d.p.dt) + " s)";
    } else if (!(volume_fraction >= kMinVolumeFraction)) {
        reason = "the fluid collapsed: its bounding box holds " + std::to_string(volume_fraction) +
                 " of its rest volume (at least " + std::to_string(kMinVolumeFraction) + ")";
    } else if (energy_checked(d.p)) {
        const double e = mechanical_energy(d.p, end);
        if (d.energy_settling) {   // the first check after set-up: the start's stored energy released in its step
            d.energy_reference = std::max(d.energy_reference, e);
            d.energy_settling = false;
        }
        const double allowed = d.energy_reference + kEnergySlack * (std::fabs(d.energy_reference) + energy_scale(d.p, end.m));
        if (!(e <= allowed))
            reason = "mechanical energy " + std::to_string(e) + " J rose above its initial " +
                     std::to_string(d.energy_reference) + " J in a scene nothing forces";
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
