// Launch code of the temperature smoothing (section 4.1, eq. 12-17; smoothing.h): one Jacobi pass over the
// smoothed fields (temperature, optionally vapor and cloud) at the predicted positions.
#pragma once
#include <thrust/functional.h>

#include <type_traits>

#include "device_memory.h"
#include "diagnostics_launch.h"
#include "parallel_for.h"
#include "pbf_constraints_launch.h"
#include "reduce.h"
#include "smoothing.h"
#include "solver_data.h"

namespace pbf {
namespace PBF_BACKEND_NS {

// The pass runs with thermodynamics, kappa > 0 and at least one field to smooth.
inline bool smoothing_active(const Params& p) {
    return p.thermodynamics && p.kappa > 0.0f && (p.smooth_fields[0] || p.smooth_fields[1] || p.smooth_fields[2]);
}

inline SmoothingPair smoothing_pair(const SolverData& d) {
    return SmoothingPair{d.p.h0, d.cp.inv_rest_density, d.rates.smoothing_beta, d.p.smoothing_epsilon};
}

// The limiter's pass is needed where the weights can pass its cap S_cap (smoothing.h): mixed levels, or kappa above
// S_cap (a lattice's S_i is about 0.9 kappa < kappa, so at kappa <= S_cap it would scale no pair and is skipped).
template <class Policy>
bool smoothing_limited(const SolverData& d) {
    return d.smoothing && (!std::is_same<Policy, UniformPolicy>::value || d.rates.kappa > kSmoothingWeightCap);
}

// The limiter's weight sums S_i as a sum for the XSPH pass to take along (out == nullptr where none is needed).
template <class Policy>
LimiterWeight<Policy> limiter_weight_sums(SolverData& d) {
    return LimiterWeight<Policy>{smoothing_pair(d), smoothing_limited<Policy>(d) ? raw(d.float_tmp) : nullptr};
}

// Smooths the fields, with the vorticity confinement taken along (confinement, pbf_constraints_launch.h; timed with
// the smoothing); the change of sum m T the pass made (kg K, 0 up to rounding: the pairwise form conserves it) goes
// to the step's StepSums. weight_sums_ready: the XSPH pass has written the limiter's S_i (limiter_weight_sums);
// otherwise the limiter's pass runs here, where needed.
template <class Policy>
void smooth_fields(SolverData& d, bool weight_sums_ready) {
    if (!d.smoothing) return;
    StepSums* sums = raw(d.step_sums);
    d.clock.begin(kPhaseSmoothing);
    dvec<float>* fields[3] = {&d.temperature, &d.vapor, &d.cloud};
    SmoothingFields sf{};
    for (int k = 0; k < 3; ++k) {
        if (!d.p.smooth_fields[k]) continue;
        sf.in[k] = raw(*fields[k]);
        sf.out[k] = raw(d.smooth_out[k]);
    }
    CellRanges fluid = d.fluid_ranges(d.pred);
    const SmoothingPair pair = smoothing_pair(d);
    const float* weight_sum = nullptr;
    if (smoothing_limited<Policy>(d)) {
        if (!weight_sums_ready)
            parallel_for(d.n, SmoothingWeightSums<Policy>{d.grid, fluid, d.radii, limiter_weight_sums<Policy>(d)});
        weight_sum = raw(d.float_tmp);
    }
    parallel_for(d.n, SmoothScalars<Policy>{d.grid, fluid, d.radii, pair, d.atm.env, weight_sum, sf, confinement(d)});
    d.clock.end(kPhaseSmoothing);
    if (d.p.smooth_fields[0])
        reduce_into(d.n, SmoothingHeat{raw(d.pred), sf.in[0], sf.out[0]}, 0.0, thrust::plus<double>(), &sums->smoothing_heat);
    for (int k = 0; k < 3; ++k)
        if (d.p.smooth_fields[k]) fields[k]->swap(d.smooth_out[k]);
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
