// The boundary between the Python bindings (g++) and the two backends (nvcc / g++ + OpenMP).
// Only plain types and raw pointers cross it; each backend keeps its Thrust containers inside.
#pragma once
#include <utility>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "params.h"

namespace pbf {

// Table 1 phases and finer timers. The pbf phase contains neighbors and solver; merging contains
// merge_passes (the coloured cell passes of Figure 4) and compaction.
enum Phase : int { kPhasePBF = 0, kPhaseNeighbors, kPhaseSolver, kPhaseSmoothing, kPhaseCloudDynamics,
                   kPhaseSplitting, kPhaseMerging, kPhaseMergePasses, kPhaseCompaction, kNumPhases };
inline const char* phase_name(int p) {
    static const char* names[kNumPhases] = {"pbf", "neighbors", "solver", "smoothing", "cloud_dynamics",
                                            "splitting", "merging", "merge_passes", "compaction"};
    return names[p];
}

struct PhaseTotals {
    double total_ms[kNumPhases] = {};
    long long count[kNumPhases] = {};
};

// Energy and heat budget of the last step (fluid particles; mass-weighted, SI). Heat terms are the
// mass-weighted mean temperature change of the step in K from each process, so that
//   mean_temperature(step) - mean_temperature(step - 1) = heat_source + heat_latent + heat_adiabatic + heat_smoothing
// up to rounding (split/merge conserve mass-weighted heat by construction).
struct StepBudget {
    bool valid = false;
    double mass = 0.0;                 // kg
    double mass_centre_height = 0.0;   // m
    double kinetic_energy = 0.0;       // J (sum 1/2 m |u|^2)
    double potential_energy = 0.0;     // J, available potential energy of a stable stratification:
                                       //   sum m (k_b / T0(y)) (T - T0(y))^2 / (2 (Gamma_d - Gamma_env))
    double mean_temperature = 0.0;     // K, mass-weighted
    double heat_source = 0.0;          // K, ground heating (eq. 5)
    double heat_latent = 0.0;          // K, latent heat (eq. 11)
    double heat_adiabatic = 0.0;       // K, adiabatic term (eq. 7)
    double heat_smoothing = 0.0;       // K, temperature smoothing (eq. 12-17): 0 up to rounding
    double total_water = 0.0;          // kg (sum m (v + w))
    double heat_relaxation = 0.0;      // K, relaxation toward T0(y) (docs/cycling.md C2)
    double water_relaxation = 0.0;     // kg, vapor added by the relaxation toward v0(y) (C2; < 0: removed)
    double water_rain = 0.0;           // kg, cloud water removed as rain by autoconversion (C3)
    double heat_subsidence = 0.0;      // K, large-scale subsidence -w_s dtheta0/dy (thermodynamics.h L1)
    double heat_radiation = 0.0;       // K, radiative cooling R(y) (L2)
    double water_subsidence = 0.0;     // kg, vapor added by the subsidence -w_s dv0/dy (L1; < 0: removed)
    double water_tendency = 0.0;       // kg, vapor added by the large-scale moisture tendency M(y) (L3)
    // The terms summed over every step since step 0 (checkpoints carry them): K for the heat terms, kg
    // for the water terms.  Water closes: total_water(t) = total_water(0)
    //   + totals[5] - totals[6] + totals[9] + totals[10] (docs/cycling.md C4).
    static constexpr int kTotals = 11;
    double totals[kTotals] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};  // source, latent, adiabatic, smoothing,
        // relaxation, water_relaxation, rain, subsidence, radiation, water_subsidence, water_tendency
};

struct StepStats {
    long long step = 0;
    double time = 0.0;
    std::size_t n_particles = 0;
    bool neighbor_lists = false;        // pbf.neighbor_list in use (false once given up: grid_launch.h)
    unsigned long long neighbor_candidates = 0;  // entries of the last step's lists (0 without lists)
    unsigned neighbor_row_width = 0;    // the lists' row width W (slots per particle; 0 without lists)
    unsigned long long wall_candidates = 0;   // entries of the walls' table (grid.h, WallNeighbourhoods)
    double density_error_mean = 0.0;
    double density_error_max = 0.0;
    double density_excess_mean = 0.0;   // mean max(rho/rho0 - 1, 0): compression
    double density_deficit_mean = 0.0;  // mean max(1 - rho/rho0, 0): rarefaction
    double max_speed = 0.0;
    double dt = 0.0;                    // the step in use, s (time_step.h)
    double cfl = 0.0;                   // max_i |v_i| dt / h_i of the state
    double min_position[3] = {0, 0, 0};
    double max_position[3] = {0, 0, 0};
    std::vector<long long> level_counts;
    long long splits = 0;                  // cumulative
    long long merges = 0;                  // cumulative
    long long split_capacity_rejects = 0;  // cumulative: splits refused because capacity was full
    long long split_last = 0, merge_last = 0, capacity_rejects_last = 0;  // in the last step
    StepBudget budget;
};


enum class ArrayKind { Float, Float4, UInt };

struct ArrayView {
    void* data = nullptr;
    std::size_t n = 0;       // elements (Float4 counts as one)
    ArrayKind kind = ArrayKind::Float;
    bool on_device = false;  // CUDA memory
};

class ISolver {
public:
    virtual ~ISolver() = default;
    virtual void set_fluid(std::size_t n, const float* pos3, const float* vel3, const float* temperature,
                           const float* vapor, const float* cloud, const float* mass, const uint32_t* id) = 0;
    virtual void set_boundary(std::size_t n, const float* pos3, const float* temperature, const float* vapor) = 0;
    virtual void set_clock(long long step, double time, uint32_t next_id) = 0;
    virtual double time_step() const = 0;           // the step in use, s
    virtual void set_time_step(double dt) = 0;      // a checkpoint's step (CFL-controlled runs)
    // A checkpoint's neighbour-list row width (it only grows during a run; restored, a resumed run's lists and
    // statistics are those of the uninterrupted run)
    virtual void set_neighbor_row_width(unsigned width) = 0;
    // Advances up to n steps; stops at the first step that fails its check and returns
    // "unstable|<step>|<last good step>|<reason>|<id,id,...>" (empty string: all n steps passed).
    // Errors travel as values, never as exceptions, across the backend boundary.
    virtual std::string step(int n) = 0;
    // Runs only the split/merge phase on the current state (for tests and studies of section 5.2).
    virtual void adapt_now() = 0;
    virtual std::size_t size() const = 0;
    virtual long long step_count() const = 0;
    virtual double time() const = 0;
    virtual uint32_t next_id() const = 0;
    // Copies an array to host memory (dst holds size() elements of the array's kind).
    virtual ArrayView view(const std::string& name) = 0;
    virtual void copy_to_host(const std::string& name, void* dst) = 0;
    // Warm start of the velocity projection (the last step's pressure impulse per particle), for checkpoints.
    virtual void set_projection_impulse(std::size_t n, const float* mu) = 0;
    // Restore the budget's running totals (StepBudget::totals) from a checkpoint.
    virtual void set_budget_totals(const double* totals) = 0;
    virtual PhaseTotals timings() const = 0;
    virtual void reset_timings() = 0;
    virtual StepStats stats() = 0;
};

std::unique_ptr<ISolver> make_cpu_solver(const Params& p);
#ifdef PBF_WITH_CUDA
std::unique_ptr<ISolver> make_cuda_solver(const Params& p);
int cuda_device_count();
std::string cuda_device_name();
std::pair<std::size_t, std::size_t> cuda_memory_info();
double cuda_copy_bandwidth(std::size_t nbytes, int repeats);   // bytes/s, read + written
#endif

}  // namespace pbf
