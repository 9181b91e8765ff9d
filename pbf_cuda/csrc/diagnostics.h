// The diagnostics' kernels: the step's energy and heat budget (mass-weighted sums in double precision), the
// stability check's reduction, and StepSums, every sum a step makes for the host, kept in device memory until
// the step's end (diagnostics_launch.h has the launch code).
#pragma once
#include <cmath>

#include "common.h"
#include "pbf_constraints.h"
#include "adaptivity.h"
#include "thermodynamics.h"

namespace pbf {

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

// The smoothing pass's change of sum m T, sum m (T_after - T_before) in double precision, kg K: 0 up to rounding,
// the pairwise form conserves it (smoothing.h).
struct SmoothingHeat {
    const Float4* pos;   // w: mass, kg
    const float* before;
    const float* after;
    PBF_HD double operator()(uint32_t i) const { return double(pos[i].w) * (double(after[i]) - double(before[i])); }
};

// ---- the stability check ------------------------------------------------------------------------
// Stability and diagnostics reduction over the fluid particles.
struct Reduced {
    float err_sum, err_max, speed2_max;
    float rate_max;                 // max |v_i| / h_i, 1/s: the CFL number is dt times this (time_step.h)
    float excess_sum, deficit_sum;  // sum max(C, 0), sum max(-C, 0): the two sides of the density error
    uint32_t bad;
    uint32_t why;   // OR of the BadKind bits of the bad particles
    float lo[3], hi[3];
};

// The physical range of an air parcel's temperature, K: far outside any atmosphere the scenes can state (the schema
// allows a ground temperature of 150-400 K), so only a broken state leaves it.
constexpr float kMinTemperature = 50.0f;
constexpr float kMaxTemperature = 1000.0f;

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
        r.rate_max = fmaxf(a.rate_max, b.rate_max);
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
    float h0, inv_mass0;        // level 0's kernel radius (m) and 1 / its mass (1/kg): h_i = h0 (m_i / m0)^(1/3)
    float lo[3], hi[3];         // the domain a particle may reach: walls' axes [-h0, L + h0], periodic axes unbounded
    // BadKind bits of particle i (0: it passes): a non-finite position or one outside the domain, a non-finite
    // velocity or a speed above max_velocity, a temperature outside its physical range, vapor or cloud water
    // outside [0, 1] kg/kg (or non-finite).
    PBF_HD uint32_t kinds(uint32_t i) const {
        Vec3 x = xyz(pos[i]), v = xyz(vel[i]);
        float s2 = dot(v, v);
        uint32_t k = 0;
        if (!finite3(x) || !(x.x >= lo[0] && x.x <= hi[0] && x.y >= lo[1] && x.y <= hi[1] && x.z >= lo[2] && x.z <= hi[2]))
            k |= kBadPosition;
        if (!finite3(v)) k |= kBadVelocity;
        else if (!(isfinite(s2) && s2 <= max_speed2)) k |= kBadSpeed;
        if (temperature) {
            float T = temperature[i];
            if (!(T >= kMinTemperature && T <= kMaxTemperature)) k |= kBadTemperature;
            if (!(vapor[i] >= 0.0f && vapor[i] <= 1.0f)) k |= kBadVapor;
            if (!(cloud[i] >= 0.0f && cloud[i] <= 1.0f)) k |= kBadCloud;
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
        r.rate_max = sqrtf(r.speed2_max) / (h0 * cbrtf(pos[i].w * inv_mass0));
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

// ---- what a step sums for the host ---------------------------------------------------------------
// Each sum is reduced into its field in device memory as the step goes (reduce_into), and the host copies the
// whole record once, at the step's end, for the budget and the check: no phase waits for its sum.
struct StepSums {
    BudgetSums start, end;                       // the budget at the step's start (x) and end (x*, with v)
    double smoothing_heat;                       // the smoothing pass's change of sum m T, kg K (SmoothingHeat)
    ForcingSums forcing;                         // the cloud dynamics' forcing terms
    double shift_heat;                           // the density solve's heat booked by the kept shift, kg K
    Double2 shift_before, shift_after;           // (sum m y, sum m) around the density iterations
    Double2 column;                              // (sum m u_y, sum m) before the column drift's removal
    float shift;                                 // the column's vertical shift to remove, m
    Reduced checks;                              // the stability check's sums, where the step is checked
    ListSize list_size;                          // the neighbour lists' size (neighbor_list.h), where built
    AdaptCounts adapt;                           // the splitting and merging's counts, where the step adapted
};

}  // namespace pbf
