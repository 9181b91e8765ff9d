// The solver, written once over Thrust and compiled twice: by nvcc for the CUDA backend
// (backend_cuda.cu) and by g++ with Thrust's OpenMP device system for the CPU backend
// (backend_cpu.cpp). The including file defines PBF_BACKEND_NS (and PBF_BACKEND_CUDA for CUDA).
//
// One step (section 3-5 of the paper, Macklin & Mueller 2013 Algorithm 1):
//   pbf:            predict x* = x + dt (v + dt g); sort by cell of x*; cell ranges        [neighbors]
//                   iterations { rho, lambda (eq. 1-4, 18); dp with s_corr; walls }     [solver]
//                   v = (x* - x) / dt (position projection only); XSPH, viscosity; vorticity confinement
//   smoothing:      temperature (and optionally vapor, cloud) smoothing (eq. 12-17), conservative
//   cloud_dynamics: heating, adiabatic cooling, phase transition, latent heat, buoyancy (eq. 5-11)
//   pbf:            velocity projection only: v = P(v + dt g), divergence-free at x*        [solver]
//   commit x = x* (wrapped on periodic axes)
//   splitting / merging (section 5.2), then compaction
//
// Two ways to keep the fluid incompressible (Params::velocity_projection):
//  - position projection (Macklin & Mueller): the velocity is (x* - x) / dt after the density
//    constraint moved x*. Right for free surfaces (unilateral constraint), but every density error
//    left by the few Jacobi iterations comes back as velocity in the next step: it adds energy.
//  - velocity projection (closed domains, the atmosphere): the velocity is projected onto J v = 0
//    (divergence-free, pbf_constraints.h) after all forces, and the density constraint only moves
//    positions. The projection is M-orthogonal, so it removes only the compressing part of the flow
//    and never adds kinetic energy; the density constraint is bilateral, so heated air cannot leave a
//    rarefied layer behind.
#include <thrust/copy.h>
#include <thrust/device_vector.h>
#include <thrust/execution_policy.h>
#include <thrust/fill.h>
#include <thrust/for_each.h>
#include <thrust/functional.h>
#include <thrust/gather.h>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/scan.h>
#include <thrust/sequence.h>
#include <thrust/sort.h>
#include <thrust/transform_reduce.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <string>
#include <vector>

#include "adaptivity.h"
#include "common.h"
#include "grid.h"
#include "kernels.h"
#include "params.h"
#include "pbf_constraints.h"
#include "smoothing.h"
#include "solver_api.h"
#include "thermodynamics.h"

#ifdef PBF_BACKEND_CUDA
#include <cuda_runtime.h>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

#ifdef THRUST_CUB_WRAPPED_NAMESPACE
// Each backend wraps Thrust/CUB in its own namespace (set by CMake) so the two never collide.
namespace thrust = ::THRUST_CUB_WRAPPED_NAMESPACE::thrust;
#endif

template <class T>
using dvec = thrust::device_vector<T>;
template <class T>
T* raw(dvec<T>& v) { return thrust::raw_pointer_cast(v.data()); }
template <class T>
const T* raw(const dvec<T>& v) { return thrust::raw_pointer_cast(v.data()); }

template <class F>
void parallel_for(std::size_t n, const F& f) {
    if (n == 0) return;
    thrust::for_each(thrust::device, thrust::counting_iterator<uint32_t>(0),
                     thrust::counting_iterator<uint32_t>(uint32_t(n)), f);
}

// f(t, team) for t in [0, n): one team per item (common.h), a warp on the GPU, a thread on the CPU.
#ifdef PBF_BACKEND_CUDA
template <class F>
__global__ void team_kernel(uint32_t n, F f) {
    uint32_t t = (blockIdx.x * blockDim.x + threadIdx.x) / WarpTeam::kSize;
    if (t >= n) return;  // whole warps leave together: blockDim is a multiple of the warp size
    f(t, WarpTeam{threadIdx.x % WarpTeam::kSize});
}

template <class F>
void parallel_for_teams(std::size_t n, const F& f) {
    if (n == 0) return;
    const unsigned block = 128;
    std::size_t threads = n * WarpTeam::kSize;
    team_kernel<<<unsigned((threads + block - 1) / block), block>>>(uint32_t(n), f);
    cudaError_t err = cudaGetLastError();
    if (err != cudaSuccess) throw std::runtime_error(std::string("team kernel launch: ") + cudaGetErrorString(err));
}
#else
template <class F>
struct AsSerialTeam {
    F f;
    void operator()(uint32_t t) const { f(t, SerialTeam{}); }
};

template <class F>
void parallel_for_teams(std::size_t n, const F& f) {
    parallel_for(n, AsSerialTeam<F>{f});
}
#endif

// ---- phase timers: CUDA events on the GPU, steady clock on the CPU ------------------------------
#ifdef PBF_BACKEND_CUDA
class PhaseClock {
public:
    ~PhaseClock() {
        for (auto& e : events_) cudaEventDestroy(e);
    }
    void begin(int p) { open_[p] = record(); }
    void end(int p) {
        pairs_.push_back({p, open_[p], record()});
        ran_[p] = true;
    }
    // Called once per step after the device work was issued: waits and accumulates.
    void collect(PhaseTotals& totals) {
        if (!pairs_.empty()) cudaEventSynchronize(events_[pairs_.back().stop]);
        for (auto& pr : pairs_) {
            float ms = 0.0f;
            cudaEventElapsedTime(&ms, events_[pr.start], events_[pr.stop]);
            totals.total_ms[pr.phase] += ms;
        }
        for (int p = 0; p < kNumPhases; ++p)
            if (ran_[p]) totals.count[p] += 1, ran_[p] = false;
        pairs_.clear();
        used_ = 0;
    }

private:
    struct Pair { int phase, start, stop; };
    int record() {
        if (used_ == events_.size()) {
            cudaEvent_t e;
            cudaEventCreate(&e);
            events_.push_back(e);
        }
        cudaEventRecord(events_[used_]);
        return int(used_++);
    }
    std::vector<cudaEvent_t> events_;
    std::size_t used_ = 0;
    std::vector<Pair> pairs_;
    int open_[kNumPhases] = {};
    bool ran_[kNumPhases] = {};
};
#else
class PhaseClock {
public:
    void begin(int p) { open_[p] = std::chrono::steady_clock::now(); }
    void end(int p) {
        pending_[p] += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - open_[p]).count();
        ran_[p] = true;
    }
    void collect(PhaseTotals& totals) {
        for (int p = 0; p < kNumPhases; ++p) {
            totals.total_ms[p] += pending_[p];
            pending_[p] = 0.0;
            if (ran_[p]) totals.count[p] += 1, ran_[p] = false;
        }
    }

private:
    std::chrono::steady_clock::time_point open_[kNumPhases];
    double pending_[kNumPhases] = {};
    bool ran_[kNumPhases] = {};
};
#endif

// ---- small per-particle functors ----------------------------------------------------------------
struct Predict {
    Float4* vel;
    const Float4* pos;
    Float4* pred;
    Vec3 gravity;
    float dt;
    PBF_HD void operator()(uint32_t i) const {
        Float4 v = vel[i];
        Vec3 u = xyz(v) + dt * gravity;
        vel[i] = make_float4(u, v.w);
        Float4 p = pos[i];
        pred[i] = make_float4(xyz(p) + dt * u, p.w);
    }
};

// Sort key of particle i: its cell (uniform runs) or its nested sub-cell cell * 8 + sub (adaptive runs, grid.h).
struct ComputeKeys {
    GridGeometry g;
    const Float4* pos;
    uint32_t* keys;
    bool nested;
    PBF_HD void operator()(uint32_t i) const {
        Vec3 x = xyz(pos[i]);
        keys[i] = nested ? nested_key(g, x) : cell_key(g, x);
    }
};

struct MarkCellRanges {
    const uint32_t* keys;
    uint32_t n;
    uint32_t* start;
    uint32_t* end;
    PBF_HD void operator()(uint32_t i) const {
        uint32_t k = keys[i];
        if (i == 0 || keys[i - 1] != k) start[k] = i;
        if (i == n - 1 || keys[i + 1] != k) end[k] = i + 1;
    }
};

// Largest kernel radius per sub-cell (adaptive runs): thread s scans sub-cell s's range.
struct SubCellRadius {
    LevelRadii radii;
    const Float4* pos;
    const uint32_t* start;
    const uint32_t* end;
    float* radius;
    PBF_HD void operator()(uint32_t s) const {
        float h = 0.0f;
        for (uint32_t j = start[s]; j < end[s]; ++j) h = fmaxf(h, radii.radius_of_mass(pos[j].w));
        radius[s] = h;
    }
};

// Per cell: the cell's particle range and largest radius from its eight sub-cells.
struct CellFromSubCells {
    const uint32_t* sub_start;
    const uint32_t* sub_end;
    const float* sub_radius;
    uint32_t* start;
    uint32_t* end;
    float* radius;
    PBF_HD void operator()(uint32_t c) const {
        uint32_t b = 0, e = 0;
        float h = 0.0f;
        bool any = false;
        for (uint32_t s = c * kSubCells; s < (c + 1) * kSubCells; ++s) {
            if (sub_start[s] == sub_end[s]) continue;
            if (!any) b = sub_start[s];
            e = sub_end[s];
            any = true;
            h = fmaxf(h, sub_radius[s]);
        }
        start[c] = b;
        end[c] = e;
        radius[c] = h;
    }
};

struct UpdateVelocity {
    const Float4* pos;
    const Float4* pred;
    Float4* vel;
    float inv_dt;
    PBF_HD void operator()(uint32_t i) const {
        vel[i] = make_float4(inv_dt * (xyz(pred[i]) - xyz(pos[i])), 0.0f);
    }
};

struct Commit {
    GridGeometry g;
    const Float4* pred;
    Float4* pos;
    PBF_HD void operator()(uint32_t i) const {
        Float4 p = pred[i];
        pos[i] = make_float4(wrap_position(g, xyz(p)), p.w);
    }
};

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

// Bit (cx % 3) + 3 (cy % 3) + 9 (cz % 3) of the merge pass that holds particle i's cell, when i has a
// merge partner (0 otherwise); OR-reduced to skip passes with nothing to merge.
struct MergePassBit {
    GridGeometry g;
    const uint32_t* keys;
    const uint32_t* partner;
    PBF_HD uint32_t operator()(uint32_t i) const {
        if (partner[i] == 0xffffffffu) return 0u;
        uint32_t c[3];
        cell_coords(g, keys[i] / kSubCells, c);  // adaptive runs sort by nested keys (grid.h)
        return 1u << ((c[0] % 3) + 3 * (c[1] % 3) + 9 * (c[2] % 3));
    }
};

struct BitOr {
    PBF_HD uint32_t operator()(uint32_t a, uint32_t b) const { return a | b; }
};

struct IsAlive {
    const uint8_t* flags;
    PBF_HD bool operator()(uint32_t i) const { return !(flags[i] & kDead); }
};

struct HasFlag {
    const uint8_t* flags;
    uint8_t flag;
    PBF_HD bool operator()(uint32_t i) const { return (flags[i] & flag) != 0; }
};

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
    float ape_scale;            // 1 / (2 (Gamma_d - Gamma_env)) for a stable stratification, else 0
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
            if (with_heating) s.heat = m * a.heating(xyz(p));
            float T0 = a.environment_temperature(p.y);
            double dT = double(T) - T0;
            s.ape = m * (a.buoyancy / T0) * dT * dT * ape_scale;
        }
        return s;
    }
};

// Conjugate-gradient helpers of the velocity projection (z = r / diag is the Jacobi preconditioner).
struct CgStart {
    float* r;
    const float* diag;
    float* p;
    PBF_HD void operator()(uint32_t i) const {
        r[i] = -r[i];
        p[i] = diag[i] > 0.0f ? r[i] / diag[i] : 0.0f;
    }
};
struct CgDot {
    const float* a;
    const float* b;
    PBF_HD double operator()(uint32_t i) const { return double(a[i]) * double(b[i]); }
};
// r . D^-1 r (inv_diag set), or p . D p (diag_mul set).
struct CgPrecDot {
    const float* r;
    const float* inv_diag;
    const float* diag_mul;
    PBF_HD double operator()(uint32_t i) const {
        if (diag_mul) return double(r[i]) * r[i] * diag_mul[i];
        return inv_diag[i] > 0.0f ? double(r[i]) * r[i] / inv_diag[i] : 0.0;
    }
};
struct CgUpdate {
    float alpha;
    const Float4* g;
    const float* q;
    const float* p;
    Float4* v;
    float* r;
    float* mu;
    PBF_HD void operator()(uint32_t i) const {
        Float4 a = v[i], b = g[i];
        v[i] = Float4{a.x + alpha * b.x, a.y + alpha * b.y, a.z + alpha * b.z, a.w};
        r[i] -= alpha * q[i];
        mu[i] += alpha * p[i];
    }
};
struct CgDirection {
    float beta;
    const float* r;
    const float* diag;
    float* p;
    PBF_HD void operator()(uint32_t i) const {
        float z = diag[i] > 0.0f ? r[i] / diag[i] : 0.0f;
        p[i] = z + beta * p[i];
    }
};

struct AddVelocity {
    const Float4* dv;
    Float4* vel;
    PBF_HD void operator()(uint32_t i) const {
        Float4 v = vel[i], d = dv[i];
        vel[i] = Float4{v.x + d.x, v.y + d.y, v.z + d.z, v.w};
    }
};

struct AddAcceleration {
    Float4* vel;
    Vec3 dv;
    PBF_HD void operator()(uint32_t i) const {
        Float4 v = vel[i];
        vel[i] = Float4{v.x + dv.x, v.y + dv.y, v.z + dv.z, v.w};
    }
};

// ---- the solver ---------------------------------------------------------------------------------
class Solver final : public ISolver {
public:
    explicit Solver(const Params& p) : p_(p) {
        radii_ = make_level_radii(p_.h0, p_.mass0);
        bool periodic[3] = {p_.periodic[0], p_.periodic[1], p_.periodic[2]};
        grid_ = make_grid_geometry(p_.domain, periodic, p_.h0);
        if (p_.adaptive) {
            // The parallel merge colours cells modulo 3; periodic axes need a multiple of 3 cells.
            for (int a = 0; a < 3; ++a) {
                if (!grid_.periodic[a]) continue;
                int n = (grid_.dims[a] / 3) * 3;
                grid_.dims[a] = n < 3 ? 3 : n;
                grid_.cell[a] = grid_.domain[a] / grid_.dims[a];
                grid_.inv_cell[a] = 1.0f / grid_.cell[a];
            }
        }
        cp_.rest_density = p_.rest_density;
        cp_.inv_rest_density = 1.0f / p_.rest_density;
        cp_.relaxation = p_.relaxation;
        cp_.h0 = p_.h0;
        cp_.unilateral = p_.unilateral;
        cp_.scorr_k_lambda = p_.scorr_k * p_.lambda_ref;
        cp_.scorr_n = p_.scorr_n;
        float wdq = poly6(p_.scorr_dq * p_.h0 * p_.scorr_dq * p_.h0, p_.h0);
        cp_.scorr_inv_wdq = wdq > 0.0f ? 1.0f / wdq : 0.0f;
        cp_.scorr_dq = p_.scorr_dq;

        atm_.ground_temperature = p_.ground_temperature;
        atm_.lapse_rate = p_.lapse_rate;
        atm_.buoyancy = p_.buoyancy;
        atm_.cloud_gravity = p_.cloud_gravity;
        atm_.dry_lapse_rate = p_.dry_lapse_rate;
        atm_.latent_heat = p_.latent_heat;
        atm_.phase_rate = p_.phase_rate;
        atm_.sat_a = p_.saturation[0];
        atm_.sat_b = p_.saturation[1];
        atm_.sat_c = p_.saturation[2];
        atm_.heating_rate = p_.heating_rate;
        atm_.heating_depth = p_.heating_depth;
        atm_.noise_frequency = p_.noise_frequency;
        atm_.noise_amplitude = p_.noise_amplitude;
        atm_.noise_offset[0] = p_.noise_offset[0];
        atm_.noise_offset[1] = p_.noise_offset[1];
        atm_.patch_radius = p_.heating_patch_radius;
        atm_.patch_centre[0] = 0.5f * p_.domain[0];
        atm_.patch_centre[1] = 0.5f * p_.domain[2];
        atm_.dt = p_.dt;
        atm_.diurnal = 1.0f;
        atm_.relax_decay = p_.relaxation_time > 0.0f ? float(std::exp(-double(p_.dt) / p_.relaxation_time)) : 1.0f;
        atm_.auto_decay = p_.autoconversion_rate > 0.0f ? float(std::exp(-double(p_.autoconversion_rate) * p_.dt))
                                                        : 1.0f;
        atm_.auto_threshold = p_.autoconversion_threshold;
        atm_.vapor_ratio = p_.initial_vapor_ratio;
        atm_.vapor_relative = p_.vapor_relative;

        ap_.k_p = p_.k_p;
        ap_.k_c = p_.k_c;
        ap_.split_threshold = p_.split_threshold;
        ap_.merge_threshold = p_.merge_threshold;
        ap_.max_level = p_.max_level < kMaxLevels - 1 ? p_.max_level : kMaxLevels - 2;
        ap_.min_distance = p_.min_distance;
        ap_.lookahead_height = p_.thermodynamics ? p_.lookahead_height : 0.0f;
        ap_.h0 = p_.h0;
        for (int l = 0; l < kMaxLevels; ++l) ap_.spacing[l] = p_.spacing * std::pow(2.0f, -l / 3.0f);
        // Two children of different parents are >= conflict - 2 * max offset apart: make that the threshold.
        ap_.conflict_radius = ap_.spacing[1] + p_.min_distance * radii_.h[1];
        if (ap_.conflict_radius > p_.h0) ap_.conflict_radius = p_.h0;

        smoothing_ = p_.thermodynamics && p_.kappa > 0.0f &&
                     (p_.smooth_fields[0] || p_.smooth_fields[1] || p_.smooth_fields[2]);
        cell_start_.resize(grid_.num_cells());
        cell_end_.resize(grid_.num_cells());
        if (p_.adaptive) {
            sub_start_.resize(std::size_t(grid_.num_cells()) * kSubCells);
            sub_end_.resize(std::size_t(grid_.num_cells()) * kSubCells);
            sub_radius_.resize(std::size_t(grid_.num_cells()) * kSubCells);
            cell_radius_.resize(grid_.num_cells());
        }
    }

    // -- set-up ------------------------------------------------------------------------------
    void set_fluid(std::size_t n, const float* pos3, const float* vel3, const float* temperature,
                   const float* vapor, const float* cloud, const float* mass, const uint32_t* id) override {
        std::size_t cap = std::max<std::size_t>(n, p_.adaptive ? p_.capacity : n);
        if (cap > 0xfffffff0u) throw std::length_error("particle capacity exceeds 2^32");
        capacity_ = cap;
        std::vector<Float4> hp(n), hv(n);
        uint32_t max_id = 0;
        for (std::size_t i = 0; i < n; ++i) {
            hp[i] = Float4{pos3[3 * i], pos3[3 * i + 1], pos3[3 * i + 2], mass[i]};
            hv[i] = Float4{vel3[3 * i], vel3[3 * i + 1], vel3[3 * i + 2], 0.0f};
            max_id = std::max(max_id, id[i]);
        }
        allocate(cap);
        n_ = n;
        thrust::copy(hp.begin(), hp.end(), pos_.begin());
        thrust::copy(hv.begin(), hv.end(), vel_.begin());
        thrust::copy(id, id + n, id_.begin());
        if (p_.thermodynamics) {
            thrust::copy(temperature, temperature + n, temperature_.begin());
            thrust::copy(vapor, vapor + n, vapor_.begin());
            thrust::copy(cloud, cloud + n, cloud_.begin());
        }
        next_id_ = n ? max_id + 1 : 0;
        parallel_for(n_, Commit{grid_, raw(pos_), raw(pos_)});  // wrap into the periodic box
    }

    void set_boundary(std::size_t n, const float* pos3, const float* temperature, const float* vapor) override {
        nb_ = n;
        if (n == 0) {
            bpos_.clear(); btemperature_.clear(); bvapor_.clear(); bstart_.clear(); bend_.clear();
            return;
        }
        std::vector<Float4> hp(n);
        for (std::size_t i = 0; i < n; ++i)
            hp[i] = Float4{pos3[3 * i], pos3[3 * i + 1], pos3[3 * i + 2], p_.mass0};
        // Sort boundary particles by cell once: they never move.
        std::vector<uint32_t> keys(n), order(n);
        for (std::size_t i = 0; i < n; ++i) { keys[i] = cell_key(grid_, xyz(hp[i])); order[i] = uint32_t(i); }
        std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return keys[a] < keys[b]; });
        std::vector<Float4> sp(n);
        std::vector<float> st(n, 0.0f), sv(n, 0.0f);
        std::vector<uint32_t> sk(n);
        for (std::size_t i = 0; i < n; ++i) {
            sp[i] = hp[order[i]];
            sk[i] = keys[order[i]];
            if (temperature) st[i] = temperature[order[i]];
            if (vapor) sv[i] = vapor[order[i]];
        }
        bpos_.assign(sp.begin(), sp.end());
        btemperature_.assign(st.begin(), st.end());
        bvapor_.assign(sv.begin(), sv.end());
        bcloud_.assign(n, 0.0f);
        dvec<uint32_t> dkeys(sk.begin(), sk.end());
        bstart_.assign(grid_.num_cells(), 0u);
        bend_.assign(grid_.num_cells(), 0u);
        parallel_for(n, MarkCellRanges{raw(dkeys), uint32_t(n), raw(bstart_), raw(bend_)});
    }

    void set_projection_impulse(std::size_t n, const float* mu) override {
        if (!p_.velocity_projection) return;
        if (n != n_) throw std::invalid_argument("projection_impulse: length differs from the particle count");
        thrust::copy(mu, mu + n, cg_mu_.begin());
    }

    void set_budget_totals(const double* totals) override {
        for (int k = 0; k < StepBudget::kTotals; ++k) last_stats_.budget.totals[k] = totals[k];
    }

    void set_clock(long long step, double time, uint32_t next_id) override {
        step_ = step;
        time_ = time;
        last_good_ = step;
        next_id_ = std::max(next_id_, next_id);
    }

    // -- stepping ----------------------------------------------------------------------------
    std::string step(int n) override {
        for (int s = 0; s < n; ++s) {
            if (p_.adaptive) do_step<AdaptivePolicy>(); else do_step<UniformPolicy>();
            clock_.collect(totals_);
#ifdef PBF_BACKEND_CUDA
            cudaError_t err = cudaGetLastError();
            if (err != cudaSuccess) return std::string("cuda|") + cudaGetErrorString(err);
#endif
            if (step_ % p_.check_every == 0) {
                std::string failure = check();
                if (!failure.empty()) return failure;
            }
        }
        return std::string();
    }

    void adapt_now() override {
        if (!p_.adaptive) throw std::invalid_argument("adapt_now: the scene is not adaptive");
        thrust::copy(thrust::device, pos_.begin(), pos_.begin() + n_, pred_.begin());
        build_neighbor_grid();
        adapt();
        clock_.collect(totals_);
    }

    std::size_t size() const override { return n_; }
    long long step_count() const override { return step_; }
    double time() const override { return time_; }
    uint32_t next_id() const override { return next_id_; }

    ArrayView view(const std::string& name) override {
        ArrayView v;
#ifdef PBF_BACKEND_CUDA
        v.on_device = true;
#endif
        auto f4 = [&](dvec<Float4>& a, std::size_t n) { v.data = raw(a); v.n = n; v.kind = ArrayKind::Float4; };
        auto f1 = [&](dvec<float>& a, std::size_t n) { v.data = raw(a); v.n = n; v.kind = ArrayKind::Float; };
        if (name == "position") f4(pos_, n_);
        else if (name == "velocity") f4(vel_, n_);
        else if (name == "id") { v.data = raw(id_); v.n = n_; v.kind = ArrayKind::UInt; }
        else if (name == "temperature" && p_.thermodynamics) f1(temperature_, n_);
        else if (name == "vapor" && p_.thermodynamics) f1(vapor_, n_);
        else if (name == "cloud" && p_.thermodynamics) f1(cloud_, n_);
        else if (name == "density") f1(density_, n_);
        else if (name == "projection_impulse" && p_.velocity_projection) f1(cg_mu_, n_);
        else if (name == "boundary_position") f4(bpos_, nb_);
        else if (name == "boundary_temperature") f1(btemperature_, nb_);
        else if (name == "boundary_vapor") f1(bvapor_, nb_);
        else throw std::invalid_argument("unknown or inactive array '" + name + "'");
        if (v.n == 0) v.data = nullptr;
        return v;
    }

    void copy_to_host(const std::string& name, void* dst) override {
        ArrayView v = view(name);
        if (v.n == 0) return;
        std::size_t bytes = v.n * (v.kind == ArrayKind::Float4 ? 16 : 4);
#ifdef PBF_BACKEND_CUDA
        cudaError_t err = cudaMemcpy(dst, v.data, bytes, cudaMemcpyDeviceToHost);
        if (err != cudaSuccess) throw std::runtime_error(std::string("cudaMemcpy: ") + cudaGetErrorString(err));
#else
        std::copy(static_cast<const char*>(v.data), static_cast<const char*>(v.data) + bytes, static_cast<char*>(dst));
#endif
    }

    PhaseTotals timings() const override { return totals_; }
    void reset_timings() override { totals_ = PhaseTotals{}; }

    StepStats stats() override {
        StepStats s = last_stats_;
        if (!s.budget.valid && n_ > 0) {
            // Before the first step: the state's totals, and no heat from any process yet.
            BudgetSums now = reduce_budget(pos_, true, false);
            StepBudget& b = s.budget;
            b.valid = true;
            double M = now.m > 0 ? now.m : 1.0;
            b.mass = now.m;
            b.mass_centre_height = now.my / M;
            b.kinetic_energy = now.ke;
            b.potential_energy = now.ape;
            b.mean_temperature = now.mT / M;
            b.total_water = now.mq;
        }
        s.step = step_;
        s.time = time_;
        s.n_particles = n_;
        if (n_ > 0) {
            Reduced r = reduce_checks();
            s.density_error_mean = r.err_sum / double(n_);
            s.density_error_max = r.err_max;
            s.density_excess_mean = r.excess_sum / double(n_);
            s.density_deficit_mean = r.deficit_sum / double(n_);
            s.max_speed = std::sqrt(double(r.speed2_max));
            for (int k = 0; k < 3; ++k) { s.min_position[k] = r.lo[k]; s.max_position[k] = r.hi[k]; }
        }
        s.level_counts.assign(std::size_t(std::max(p_.max_level, 0) + 1), 0);
        if (!p_.adaptive) {  // every particle is level 0: no host copy of the positions
            s.level_counts[0] = (long long)n_;
            return s;
        }
        std::vector<Float4> hp(n_);
        if (n_) thrust::copy(pos_.begin(), pos_.begin() + n_, hp.begin());
        for (auto& q : hp) {
            int l = radii_.level_of_mass(q.w);
            if (l >= int(s.level_counts.size())) s.level_counts.resize(l + 1, 0);
            s.level_counts[l] += 1;
        }
        return s;
    }

private:
    void allocate(std::size_t cap) {
        pos_.resize(cap); pred_.resize(cap); pos_tmp_.resize(cap);
        vel_.resize(cap); vel_tmp_.resize(cap);
        id_.resize(cap); uint_tmp_.resize(cap);
        lambda_.resize(cap); density_.resize(cap);
        keys_.resize(cap); perm_.resize(cap);
        float_tmp_.resize(cap);
        if (p_.vorticity > 0.0f) omega_.resize(cap);
        if (p_.velocity_projection) {
            cg_r_.resize(cap); cg_p_.resize(cap); cg_q_.resize(cap); cg_diag_.resize(cap);
            cg_mu_.assign(cap, 0.0f);
        }
        if (p_.thermodynamics) {
            temperature_.resize(cap); vapor_.resize(cap); cloud_.resize(cap);
        }
        if (smoothing_) {
            for (int k = 0; k < 3; ++k)
                if (p_.smooth_fields[k]) smooth_out_[k].resize(cap);
        }
        if (p_.adaptive) {
            flags_.resize(cap); energy_.resize(cap); split_count_.resize(cap); split_slot_.resize(cap);
            split_candidates_.resize(cap);
            merge_partner_.resize(cap);
        }
    }

    CellRanges fluid_ranges(const dvec<Float4>& positions) const {
        if (p_.adaptive)
            return CellRanges{raw(positions), raw(cell_start_), raw(cell_end_), raw(sub_start_), raw(sub_end_),
                              raw(sub_radius_), raw(cell_radius_), raw(keys_)};
        return CellRanges{raw(positions), raw(cell_start_), raw(cell_end_)};
    }
    CellRanges boundary_ranges() const {
        if (nb_ == 0) return CellRanges{nullptr, nullptr, nullptr};
        return CellRanges{raw(bpos_), raw(bstart_), raw(bend_)};
    }

    // Permute the first n_ entries of every particle array by perm_ (gather).
    template <class T>
    void permute(dvec<T>& a, dvec<T>& tmp) {
        thrust::gather(thrust::device, perm_.begin(), perm_.begin() + n_, a.begin(), tmp.begin());
        a.swap(tmp);
    }
    void permute_all(bool with_pred) {
        permute(pos_, pos_tmp_);
        if (with_pred) permute(pred_, pos_tmp_);
        else permute(density_, float_tmp_);  // compaction keeps each particle's last density
        permute(vel_, vel_tmp_);
        permute(id_, uint_tmp_);
        if (p_.velocity_projection) permute(cg_mu_, float_tmp_);
        if (p_.thermodynamics) {
            permute(temperature_, float_tmp_);
            permute(vapor_, float_tmp_);
            permute(cloud_, float_tmp_);
        }
    }

    void build_neighbor_grid() {
        const bool nested = p_.adaptive;
        parallel_for(n_, ComputeKeys{grid_, raw(pred_), raw(keys_), nested});
        thrust::sequence(thrust::device, perm_.begin(), perm_.begin() + n_);
        thrust::sort_by_key(thrust::device, keys_.begin(), keys_.begin() + n_, perm_.begin());
        permute_all(true);
        if (!nested) {
            thrust::fill(thrust::device, cell_start_.begin(), cell_start_.end(), 0u);
            thrust::fill(thrust::device, cell_end_.begin(), cell_end_.end(), 0u);
            parallel_for(n_, MarkCellRanges{raw(keys_), uint32_t(n_), raw(cell_start_), raw(cell_end_)});
            return;
        }
        // Adaptive: sub-cell ranges from the nested keys, then each cell's range and largest radius from them.
        thrust::fill(thrust::device, sub_start_.begin(), sub_start_.end(), 0u);
        thrust::fill(thrust::device, sub_end_.begin(), sub_end_.end(), 0u);
        parallel_for(n_, MarkCellRanges{raw(keys_), uint32_t(n_), raw(sub_start_), raw(sub_end_)});
        parallel_for(sub_start_.size(), SubCellRadius{radii_, raw(pred_), raw(sub_start_), raw(sub_end_),
                                                      raw(sub_radius_)});
        parallel_for(cell_start_.size(), CellFromSubCells{raw(sub_start_), raw(sub_end_), raw(sub_radius_),
                                                          raw(cell_start_), raw(cell_end_), raw(cell_radius_)});
    }

    BudgetSums reduce_budget(const dvec<Float4>& positions, bool with_vel, bool with_heating) const {
        const bool thermo = p_.thermodynamics;
        float stable = p_.dry_lapse_rate - p_.lapse_rate;
        BudgetTerms t{atm_, raw(positions), with_vel ? raw(vel_) : nullptr,
                      thermo ? raw(temperature_) : nullptr, thermo ? raw(vapor_) : nullptr,
                      thermo ? raw(cloud_) : nullptr, stable > 0.0f ? 0.5f / stable : 0.0f, with_heating};
        return thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                        thrust::counting_iterator<uint32_t>(uint32_t(n_)), t,
                                        BudgetSums{0, 0, 0, 0, 0, 0, 0, 0}, BudgetAdd{});
    }

    // Density constraint iterations on the predicted positions (eq. 1-4, 18).
    template <class Policy>
    void solve_density(const CellRanges& bnd) {
        for (int it = 0; it < p_.iterations; ++it) {
            CellRanges fl = fluid_ranges(pred_);
            parallel_for(n_, DensityLambda<Policy>{grid_, fl, bnd, radii_, cp_, raw(lambda_), raw(density_)});
            parallel_for(n_, PositionCorrection<Policy>{grid_, fl, bnd, radii_, cp_, raw(lambda_), raw(pos_tmp_)});
            pred_.swap(pos_tmp_);
        }
    }

    // Divergence-free velocity projection at the predicted positions (pbf_constraints.h): preconditioned
    // conjugate gradients on A mu = -J v, A = J M^-1 J^T, updating v += alpha M^-1 J^T p as it goes.
    // The kinetic energy of v falls with every iteration (CG minimises it along conjugate directions).
    // Warm start: the previous step's mu (the pressure impulse, which changes slowly) is applied first,
    // v += M^-1 J^T mu_prev, and CG solves for the correction, so a few iterations reach the projection.
    template <class Policy>
    void project_velocity(const CellRanges& bnd) {
        CellRanges fl = fluid_ranges(pred_);
        const std::size_t n = n_;
        float* r = raw(cg_r_);
        float* p = raw(cg_p_);
        float* q = raw(cg_q_);
        float* diag = raw(cg_diag_);
        Float4* g = raw(vel_tmp_);
        Float4* v = raw(vel_);
        float* mu = raw(cg_mu_);
        parallel_for(n, ApplyJT<Policy>{grid_, fl, bnd, radii_, cp_, mu, g});
        parallel_for(n, AddVelocity{g, v});
        // r = -J v, z = r / diag, p = z
        parallel_for(n, ApplyJ<Policy>{grid_, fl, bnd, radii_, cp_, v, r, diag});
        parallel_for(n, CgStart{r, diag, p});
        double rz = thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                             thrust::counting_iterator<uint32_t>(uint32_t(n)), CgDot{r, p}, 0.0,
                                             thrust::plus<double>());
        // Stop once the RMS divergence would change the density by less than divergence_tolerance per step:
        // projecting further only removes flow that the SPH divergence of a disordered particle set misreads.
        const double tol2 = double(p_.divergence_tolerance) * p_.divergence_tolerance / (double(p_.dt) * p_.dt) * n;
        auto converged = [&]() {
            if (!(tol2 > 0.0)) return false;
            double rr = thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                                 thrust::counting_iterator<uint32_t>(uint32_t(n)), CgDot{r, r}, 0.0,
                                                 thrust::plus<double>());
            return rr <= tol2;
        };
        for (int it = 0; it < p_.divergence_iterations && rz > 0.0 && !converged(); ++it) {
            parallel_for(n, ApplyJT<Policy>{grid_, fl, bnd, radii_, cp_, p, g});           // g = M^-1 J^T p
            parallel_for(n, ApplyJ<Policy>{grid_, fl, bnd, radii_, cp_, g, q, nullptr});   // q = A p
            double pq = thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                                 thrust::counting_iterator<uint32_t>(uint32_t(n)), CgDot{p, q}, 0.0,
                                                 thrust::plus<double>());
            // A direction whose Rayleigh quotient pq / p.D.p is tiny lies in the near-null space of A (modes the
            // SPH divergence barely sees); float32 matrix products cannot resolve it, and a step along it would
            // be huge and arbitrary. Stop there.
            double pdp = thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                                  thrust::counting_iterator<uint32_t>(uint32_t(n)),
                                                  CgPrecDot{p, nullptr, diag}, 0.0, thrust::plus<double>());
            if (!(pq > 1e-5 * pdp)) break;
            float alpha = float(rz / pq);
            // v += alpha g; r -= alpha q; the new z = r / diag is formed inside the next dot product
            parallel_for(n, CgUpdate{alpha, g, q, p, v, r, mu});
            if (it + 1 == p_.divergence_iterations) break;
            double rz_new = thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                                     thrust::counting_iterator<uint32_t>(uint32_t(n)),
                                                     CgPrecDot{r, diag, nullptr}, 0.0, thrust::plus<double>());
            float beta = float(rz_new / rz);
            rz = rz_new;
            parallel_for(n, CgDirection{beta, r, diag, p});                                   // p = z + beta p
        }
    }

    template <class Policy>
    void do_step() {
        const float dt = p_.dt;
        const bool vproj = p_.velocity_projection;
        const Vec3 gravity{p_.gravity[0], p_.gravity[1], p_.gravity[2]};
        atm_.diurnal = diurnal_factor(time_ + 0.5 * double(dt));   // C1 at the step's mid-time
        BudgetSums start = reduce_budget(pos_, false, false);
        // ---- PBF (Table 1 column "PBF") ----
        clock_.begin(kPhasePBF);
        clock_.begin(kPhaseNeighbors);
        parallel_for(n_, Predict{raw(vel_), raw(pos_), raw(pred_), vproj ? Vec3{0, 0, 0} : gravity, dt});
        build_neighbor_grid();
        clock_.end(kPhaseNeighbors);

        clock_.begin(kPhaseSolver);
        CellRanges bnd = boundary_ranges();
        solve_density<Policy>(bnd);
        if (!vproj) parallel_for(n_, UpdateVelocity{raw(pos_), raw(pred_), raw(vel_), 1.0f / dt});
        if (p_.xsph > 0.0f || p_.vorticity > 0.0f || p_.viscosity > 0.0f) {
            CellRanges fl = fluid_ranges(pred_);
            bool vort = p_.vorticity > 0.0f;
            parallel_for(n_, ViscosityVorticity<Policy>{grid_, fl, radii_, p_.h0, p_.xsph, p_.viscosity * dt,
                                                          cp_.inv_rest_density, vort, raw(vel_), raw(density_),
                                                          raw(vel_tmp_), vort ? raw(omega_) : nullptr});
            vel_.swap(vel_tmp_);
            if (vort)
                parallel_for(n_, VorticityConfinement<Policy>{grid_, fl, radii_, p_.h0, p_.vorticity, dt,
                                                                raw(density_), raw(omega_), raw(vel_)});
        }
        clock_.end(kPhaseSolver);
        clock_.end(kPhasePBF);

        // ---- temperature smoothing (section 4.1) ----
        double smoothing_heat = 0.0;
        if (smoothing_) {
            BudgetSums before = reduce_budget(pred_, false, false);
            clock_.begin(kPhaseSmoothing);
            dvec<float>* fields[3] = {&temperature_, &vapor_, &cloud_};
            SmoothingFields sf{};
            for (int k = 0; k < 3; ++k) {
                if (!p_.smooth_fields[k]) continue;
                sf.in[k] = raw(*fields[k]);
                sf.out[k] = raw(smooth_out_[k]);
            }
            parallel_for(n_, SmoothScalars<Policy>{grid_, fluid_ranges(pred_), radii_, p_.h0, cp_.inv_rest_density,
                                                     p_.smoothing_beta, p_.smoothing_epsilon, p_.lapse_rate, sf});
            for (int k = 0; k < 3; ++k)
                if (p_.smooth_fields[k]) fields[k]->swap(smooth_out_[k]);
            clock_.end(kPhaseSmoothing);
            smoothing_heat = reduce_budget(pred_, false, false).mT - before.mT;
        }

        // ---- cloud dynamics (eq. 5-11) ----
        ForcingSums forcing{0.0, 0.0, 0.0};
        if (p_.thermodynamics) {
            clock_.begin(kPhaseCloudDynamics);
            forcing = thrust::transform_reduce(
                thrust::device, thrust::counting_iterator<uint32_t>(0), thrust::counting_iterator<uint32_t>(uint32_t(n_)),
                CloudDynamics{atm_, raw(pos_), raw(pred_), raw(vel_), raw(temperature_), raw(vapor_), raw(cloud_)},
                forcing, ForcingAdd{});
            clock_.end(kPhaseCloudDynamics);
        }

        clock_.begin(kPhasePBF);
        if (vproj) {
            clock_.begin(kPhaseSolver);
            if (gravity.x != 0.0f || gravity.y != 0.0f || gravity.z != 0.0f)
                parallel_for(n_, AddAcceleration{raw(vel_), dt * gravity});
            project_velocity<Policy>(bnd);
            clock_.end(kPhaseSolver);
        }
        clock_.end(kPhasePBF);
        BudgetSums end = reduce_budget(pred_, true, p_.thermodynamics);
        clock_.begin(kPhasePBF);
        parallel_for(n_, Commit{grid_, raw(pred_), raw(pos_)});
        clock_.end(kPhasePBF);

        StepBudget& b = last_stats_.budget;
        b.valid = true;
        double M = end.m > 0 ? end.m : 1.0;
        b.mass = end.m;
        b.mass_centre_height = end.my / M;
        b.kinetic_energy = end.ke;
        b.potential_energy = end.ape;
        b.mean_temperature = end.mT / M;
        b.heat_source = end.heat / M;
        b.heat_smoothing = smoothing_heat / M;
        b.heat_adiabatic = -double(p_.dry_lapse_rate) * (end.my - start.my) / M;
        // Cloud water removed as rain (C3) released no heat: it is no part of the latent term.
        b.heat_latent = double(p_.latent_heat) * (end.mw - start.mw + forcing.rain) / M;
        b.heat_relaxation = forcing.heat_relax / M;
        b.water_relaxation = forcing.water_relax;
        b.water_rain = forcing.rain;
        b.total_water = end.mq;
        if (!p_.thermodynamics) b.heat_adiabatic = 0.0;
        b.totals[0] += b.heat_source;
        b.totals[1] += b.heat_latent;
        b.totals[2] += b.heat_adiabatic;
        b.totals[3] += b.heat_smoothing;
        b.totals[4] += b.heat_relaxation;
        b.totals[5] += b.water_relaxation;
        b.totals[6] += b.water_rain;

        step_ += 1;
        time_ += dt;
        if (p_.adaptive) adapt();
    }

    // Time-of-day factor f(t) = max(0, sin(2 pi t / P)) of the surface heating (docs/cycling.md C1).
    float diurnal_factor(double t) const {
        if (!(p_.diurnal_period > 0.0f)) return 1.0f;
        double s = std::sin(2.0 * 3.14159265358979323846 * t / double(p_.diurnal_period));
        return s > 0.0 ? float(s) : 0.0f;
    }

    // ---- splitting and merging (section 5.2) ----
    void adapt() {
        const bool thermo = p_.thermodynamics;
        // The grid built this step is still valid: positions only moved within their cells (wrapping).
        clock_.begin(kPhaseMerging);
        parallel_for(n_, MarkCandidates{ap_, atm_, radii_, raw(pos_), raw(temperature_), raw(vapor_), raw(cloud_),
                                        raw(energy_), raw(flags_)});
        CellRanges fl = fluid_ranges(pos_);
        parallel_for(n_, FindMergePartners{grid_, fl, radii_, raw(flags_), raw(merge_partner_)});
        clock_.begin(kPhaseMergePasses);
        uint32_t passes_with_work = thrust::transform_reduce(
            thrust::device, thrust::counting_iterator<uint32_t>(0), thrust::counting_iterator<uint32_t>(uint32_t(n_)),
            MergePassBit{grid_, raw(keys_), raw(merge_partner_)}, 0u, BitOr{});
        for (int oz = 0; oz < 3; ++oz)
            for (int oy = 0; oy < 3; ++oy)
                for (int ox = 0; ox < 3; ++ox) {
                    if (!(passes_with_work & (1u << (ox + 3 * oy + 9 * oz)))) continue;
                    int off[3] = {ox, oy, oz};
                    MergePass mp{grid_, fl, ap_, radii_, {ox, oy, oz}, {0, 0, 0}, raw(merge_partner_), raw(flags_),
                                 raw(pos_), raw(vel_),
                                 thermo ? raw(temperature_) : nullptr, thermo ? raw(vapor_) : nullptr,
                                 thermo ? raw(cloud_) : nullptr};
                    std::size_t threads = 1;
                    for (int a = 0; a < 3; ++a) {
                        int cnt = grid_.dims[a] > off[a] ? (grid_.dims[a] - off[a] + 2) / 3 : 0;
                        mp.per_axis[a] = cnt;
                        threads *= std::size_t(cnt);
                    }
                    parallel_for_teams(threads, mp);
                }
        clock_.end(kPhaseMergePasses);
        clock_.end(kPhaseMerging);

        clock_.begin(kPhaseSplitting);
        // Gather the split candidates (index order), decide with one team each, then give slots.
        auto cand_end = thrust::copy_if(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                        thrust::counting_iterator<uint32_t>(uint32_t(n_)), split_candidates_.begin(),
                                        HasFlag{raw(flags_), kSplitCandidate});
        std::size_t candidates = std::size_t(cand_end - split_candidates_.begin());
        std::size_t winners = 0;
        if (candidates) {
            parallel_for_teams(candidates, DecideSplits{grid_, fl, ap_, radii_, raw(split_candidates_), raw(energy_),
                                                        raw(id_), raw(flags_), raw(split_count_), uint32_t(step_)});
            // Inclusive scan: one read of its last element gives the number of winners.
            thrust::inclusive_scan(thrust::device, split_count_.begin(), split_count_.begin() + candidates,
                                   split_slot_.begin());
            winners = std::size_t(uint32_t(split_slot_[candidates - 1]));
        }
        std::size_t room = capacity_ - n_;
        std::size_t splits = std::min(winners, room);
        if (winners) {
            parallel_for(candidates, ApplySplits{grid_, ap_, radii_, uint32_t(n_), uint32_t(capacity_), next_id_,
                                                 uint32_t(step_), raw(split_candidates_), raw(split_slot_),
                                                 raw(flags_), raw(pos_), raw(vel_), raw(id_), raw(density_),
                                                 thermo ? raw(temperature_) : nullptr, thermo ? raw(vapor_) : nullptr,
                                                 thermo ? raw(cloud_) : nullptr});
        }
        next_id_ += uint32_t(splits);
        if (splits && p_.velocity_projection)   // new children start their warm start from zero
            thrust::fill(thrust::device, cg_mu_.begin() + n_, cg_mu_.begin() + n_ + splits, 0.0f);
        n_ += splits;
        clock_.end(kPhaseSplitting);

        // Compaction: drop particles consumed by merges (kept in order, deterministic).
        clock_.begin(kPhaseMerging);
        clock_.begin(kPhaseCompaction);
        auto end = thrust::copy_if(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                   thrust::counting_iterator<uint32_t>(uint32_t(n_)), perm_.begin(),
                                   IsAlive{raw(flags_)});
        std::size_t alive = std::size_t(end - perm_.begin());
        std::size_t merges = n_ - alive;
        if (merges) {
            n_ = alive;
            permute_all(false);
        }
        clock_.end(kPhaseCompaction);
        clock_.end(kPhaseMerging);

        last_stats_.split_last = (long long)splits;
        last_stats_.merge_last = (long long)merges;
        last_stats_.capacity_rejects_last = (long long)(winners - splits);
        last_stats_.splits += (long long)splits;
        last_stats_.merges += (long long)merges;
        last_stats_.split_capacity_rejects += (long long)(winners - splits);
    }

    // ---- stability checks ----
    ParticleCheck make_check() {
        float vmax = p_.max_velocity;
        const bool t = p_.thermodynamics;
        return ParticleCheck{raw(pos_), raw(vel_), raw(density_), t ? raw(temperature_) : nullptr,
                             t ? raw(vapor_) : nullptr, t ? raw(cloud_) : nullptr, cp_.inv_rest_density,
                             p_.unilateral, vmax * vmax};
    }

    Reduced reduce_checks() {
        Reduced init;
        init.err_sum = 0.0f; init.err_max = 0.0f; init.excess_sum = 0.0f; init.deficit_sum = 0.0f; init.why = 0; init.speed2_max = 0.0f; init.bad = 0;
        for (int k = 0; k < 3; ++k) { init.lo[k] = INFINITY; init.hi[k] = -INFINITY; }
        return thrust::transform_reduce(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                        thrust::counting_iterator<uint32_t>(uint32_t(n_)), make_check(), init,
                                        ReduceOp{});
    }

    std::string check() {
        if (n_ == 0) return std::string();
        Reduced r = reduce_checks();
        double mean_err = double(r.err_sum) / double(n_);
        std::string reason;
        if (r.bad > 0) {
            static const char* names[6] = {"NaN/Inf position", "NaN/Inf velocity", "speed above max_velocity",
                                           "NaN/Inf temperature", "NaN/Inf or negative vapor",
                                           "NaN/Inf or negative cloud"};
            std::string what;
            for (int k = 0; k < 6; ++k)
                if (r.why & (1u << k)) what += (what.empty() ? "" : ", ") + std::string(names[k]);
            reason = std::to_string(r.bad) + " particle(s) with " + what + " (max_velocity = " +
                     std::to_string(p_.max_velocity) + " m/s)";
        } else if (!(mean_err <= p_.max_density_error)) {
            reason = "mean density error " + std::to_string(mean_err) + " above max_density_error = " +
                     std::to_string(p_.max_density_error);
        }
        if (reason.empty()) {
            last_good_ = step_;
            return std::string();
        }
        std::vector<uint32_t> ids;
        if (r.bad > 0) {
            dvec<uint32_t> idx(n_);
            auto end = thrust::copy_if(thrust::device, thrust::counting_iterator<uint32_t>(0),
                                       thrust::counting_iterator<uint32_t>(uint32_t(n_)), idx.begin(),
                                       IsBad{make_check()});
            std::size_t nbad = std::min<std::size_t>(std::size_t(end - idx.begin()), 16);
            // Gather the ids on the device, then one copy to the host.
            dvec<uint32_t> bad_ids(nbad);
            thrust::gather(thrust::device, idx.begin(), idx.begin() + nbad, id_.begin(), bad_ids.begin());
            ids.resize(nbad);
            thrust::copy(bad_ids.begin(), bad_ids.end(), ids.begin());
        }
        // Plain string building (no iostreams: their locale machinery is not safe in every link setup).
        std::string msg = "unstable|" + std::to_string(step_) + "|" + std::to_string(last_good_) + "|" + reason + "|";
        for (std::size_t k = 0; k < ids.size(); ++k) msg += (k ? "," : "") + std::to_string(ids[k]);
        return msg;
    }

    Params p_;
    GridGeometry grid_{};
    LevelRadii radii_{};
    ConstraintParams cp_{};
    AtmosphereParams atm_{};
    AdaptParams ap_{};
    bool smoothing_ = false;
    std::size_t n_ = 0, nb_ = 0, capacity_ = 0;
    long long step_ = 0, last_good_ = 0;
    double time_ = 0.0;
    uint32_t next_id_ = 0;

    dvec<Float4> pos_, pred_, pos_tmp_, vel_, vel_tmp_, omega_;
    dvec<uint32_t> id_, uint_tmp_, keys_, perm_, cell_start_, cell_end_;
    dvec<uint32_t> sub_start_, sub_end_;   // adaptive runs: nested sub-cell ranges (grid.h)
    dvec<float> sub_radius_, cell_radius_; // adaptive runs: largest kernel radius per sub-cell and per cell
    dvec<float> lambda_, density_, float_tmp_, temperature_, vapor_, cloud_, smooth_out_[3];
    dvec<float> cg_r_, cg_p_, cg_q_, cg_diag_;   // velocity projection (conjugate gradients)
    dvec<float> cg_mu_;                         // its solution, kept per particle for the next step's warm start
    dvec<uint8_t> flags_;
    dvec<float> energy_;
    dvec<uint32_t> split_count_, split_slot_, split_candidates_, merge_partner_;
    dvec<Float4> bpos_;
    dvec<float> btemperature_, bvapor_, bcloud_;
    dvec<uint32_t> bstart_, bend_;

    PhaseClock clock_;
    PhaseTotals totals_;
    StepStats last_stats_;
};

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
