// The solver's data, apart from its algorithm (SPlisHSPlasH's SimulationData beside its TimeStep): the
// parameters and what is derived from them once, the particle arrays (structure of arrays, sorted by cell
// every step), the clock and the statistics. The phases (*_launch.h) read and write it; the step that runs
// them in the paper's order is Solver::do_step (solver_impl.inl).
#pragma once
#include <cmath>
#include <utility>

#include "counted_launch.h"
#include "device_memory.h"
#include "parallel_for.h"
#include "phase_clock.h"

#include "adaptivity.h"
#include "diagnostics.h"
#include "grid.h"
#include "kernels.h"
#include "neighbor_list.h"
#include "params.h"
#include "pbf_constraints.h"
#include "solver_api.h"
#include "thermodynamics.h"
#include "time_step.h"

namespace pbf {
namespace PBF_BACKEND_NS {

// dst[k][i] = src[k][perm[i]] for up to kFloat4 float4 arrays, kFloat float arrays and one uint array (u_src
// nullptr: none): one pass of SolverData::permute_all. The loops run to compile-time bounds (constant indices).
struct GatherParticles {
    static constexpr int kFloat4 = 3, kFloat = 6;
    const uint32_t* perm;
    const Float4* f4_src[kFloat4] = {};
    Float4* f4_dst[kFloat4] = {};
    const float* f1_src[kFloat] = {};
    float* f1_dst[kFloat] = {};
    const uint32_t* u_src = nullptr;
    uint32_t* u_dst = nullptr;
    int f4 = 0, f1 = 0;
    PBF_HD void operator()(uint32_t i) const {
        const uint32_t j = perm[i];
#pragma unroll
        for (int k = 0; k < kFloat4; ++k)
            if (k < f4) f4_dst[k][i] = f4_src[k][j];
#pragma unroll
        for (int k = 0; k < kFloat; ++k)
            if (k < f1) f1_dst[k][i] = f1_src[k][j];
        if (u_src) u_dst[i] = u_src[j];
    }
};

// A list of at most N items held in place: permute_all's array lists, built at every sort without heap allocations.
template <class T, std::size_t N>
struct Few {
    T item[N];
    std::size_t size = 0;
    void push_back(const T& t) { item[size++] = t; }
    const T& operator[](std::size_t k) const { return item[k]; }
};

struct SolverData {
    Params p;
    GridGeometry grid{};
    LevelRadii radii{};
    ConstraintParams cp{};      // pbf_constraints_launch.h: make_constraint_params
    AtmosphereParams atm{};     // thermodynamics_launch.h: make_atmosphere_params
    AdaptParams ap{};           // adaptivity_launch.h: make_adapt_params
    StepRates rates{};          // time_step.h: the per-step coefficients at p.dt (the step in use)
    bool smoothing = false;     // smoothing_launch.h: smoothing_active
    std::size_t n = 0, nb = 0, capacity = 0;   // fluid particles, boundary particles, fluid slots
    long long step = 0, last_good = 0;
    double time = 0.0;
    double energy_reference = std::nan("");  // the mechanical energy the check holds an unforced fluid to, J (set_fluid)
    bool energy_settling = false;            // the reference still takes the first checked step's energy
    uint32_t next_id = 0;
    bool end_budget_is_next_start = false;   // the last step's end sums are this state's (diagnostics_launch.h)

    // Fluid particles, n of capacity slots in use. pos (w = mass), pred the predicted x* of the step.
    dvec<Float4> pos, pred, pos_tmp, vel, vel_tmp, omega;
    dvec<uint32_t> id, uint_tmp, keys, perm, cell_start, cell_end;
    dvec<uint32_t> perm_alt;              // the sort's second value buffer (its second key buffer is uint_tmp)
    dvec<uint32_t> sub_start, sub_end;    // adaptive runs: nested sub-cell ranges (grid.h)
    dvec<float> sub_radius, cell_radius;  // adaptive runs: largest kernel radius per sub-cell and per cell
    dvec<uint32_t> nbr_count, nbr_index;  // this step's neighbour lists (neighbor_list.h), with pbf.neighbor_list
    uint32_t nbr_width = 32;              // the lists' row width (grows to the longest row seen, grid_launch.h)
    uint32_t nbr_row = 0, nbr_slot = 0;   // their layout: candidate k of particle i at i nbr_row + k nbr_slot
    dvec<uint32_t> pass_order;            // GPU: the list passes' thread order, tiles by row length (row_order.h)
    bool pass_order_ready = false;
    bool lists_ready = false;             // the lists belong to this step's sorted particles
    bool list_size_pending = false;       // their size is in this step's sums (grid_launch.h: take_list_size)
    bool list_width_settled = false;      // the run's first build has set the width (grid_launch.h)
    bool lists_given_up = false;          // more than 2^32 - 1 entries, or no memory (grid_launch.h)
    unsigned long long list_entries = 0;  // candidates in the last lists built
    void give_up_lists() {
        lists_given_up = true;
        lists_ready = false;
        nbr_index.clear();
        nbr_index.shrink_to_fit();
    }
    dvec<float> lambda, density, float_tmp, temperature, vapor, cloud, smooth_out[3];
    dvec<float> cg_r, cg_p, cg_q, cg_diag;   // velocity projection (conjugate gradients)
    dvec<float> cg_mu;                       // its solution, kept per particle for the next step's warm start
    dvec<CgState> cg_state;                  // its scalars (one), in device memory
    dvec<float> shift_y;                     // the density constraint's vertical shift of each particle this step, m
    dvec<float> grad_correction;             // L_i (symmetric 3x3, 6 floats per particle) of the projection's Jacobian
    dvec<uint8_t> flags;                     // adaptive runs: AdaptFlag bits
    dvec<float> energy;                      // adaptive runs: shape energy E (eq. 20)
    dvec<uint32_t> split_count, split_slot, split_candidates, merge_partner;
    // The step adapted, and its particle count waits for the counts in the step's sums (adaptivity_launch.h:
    // finish_adapt): adapt_from particles before, and until then n is the compaction's bound.
    bool adapt_waiting = false;
    std::size_t adapt_from = 0;
    dvec<uint32_t> colour_done;              // adaptive runs: per cell, the merge walk's mark (cell_walk.h: for_each_cell_by_colour)
    uint32_t colour_epoch = 0;               // the last merge walk's mark
    // Boundary particles (walls), sorted by cell once: they never move. Each cell's boundary candidates, gathered
    // once (grid.h, WallNeighbourhoods; boundaries_launch.h).
    dvec<Float4> bpos;
    dvec<float> btemperature, bvapor, bcloud;
    dvec<uint32_t> wall_offset;
    dvec<Float4> wall_pos;

    dvec<StepSums> step_sums;                // this step's sums for the host (one record, diagnostics.h)

    PhaseClock clock;
    PhaseTotals totals;
    StepStats last_stats;

    // The fluid particles at `positions` (pos or pred) with this step's cell ranges, as kernels see them, and the
    // step's neighbour lists where they are kept and still belong to the sorted particles (the kernels' sums read
    // them; merging and splitting, which renumber particles, get none).
    CellRanges fluid_ranges(const dvec<Float4>& positions) const {
        CellRanges r = p.adaptive ? CellRanges{raw(positions), raw(cell_start), raw(cell_end), raw(sub_start),
                                               raw(sub_end), raw(sub_radius), raw(cell_radius), raw(keys)}
                                  : CellRanges{raw(positions), raw(cell_start), raw(cell_end)};
        if (lists_ready) {
            r.nbr_count = raw(nbr_count);
            r.nbr_index = raw(nbr_index);
            r.nbr_row = nbr_row;
            r.nbr_slot = nbr_slot;
            r.nbr_width = nbr_width;
        }
        return r;
    }
    // The order in which the list passes' threads take the particles (nullptr: index order).
    const uint32_t* list_pass_order() const { return lists_ready && pass_order_ready ? raw(pass_order) : nullptr; }
    // The walls' neighbourhoods (offset == nullptr: no walls).
    WallNeighbourhoods wall_neighbourhoods() const {
        if (nb == 0) return WallNeighbourhoods{};
        return WallNeighbourhoods{raw(wall_offset), raw(wall_pos)};
    }

    // Per-particle arrays of cap slots; the optional ones only where their phase runs.
    void allocate(std::size_t cap) {
        pos.resize(cap); pred.resize(cap); pos_tmp.resize(cap);
        vel.resize(cap); vel_tmp.resize(cap);
        id.resize(cap); uint_tmp.resize(cap);
        lambda.resize(cap); density.resize(cap);
        keys.resize(cap); perm.resize(cap); perm_alt.resize(cap);
        float_tmp.resize(cap);
        step_sums.resize(1);
        if (p.neighbor_list) nbr_count.resize(cap);
#ifdef PBF_BACKEND_CUDA
        if (p.neighbor_list) pass_order.resize(cap);
#endif
        if (p.vorticity > 0.0f) omega.resize(cap);
        if (p.velocity_projection) {
            cg_r.resize(cap); cg_p.resize(cap); cg_q.resize(cap); cg_diag.resize(cap);
            cg_mu.assign(cap, 0.0f);
            cg_state.resize(1);
            if (p.gradient_correction) grad_correction.resize(6 * cap);
            if (p.shift_keeps_anomaly && p.thermodynamics) shift_y.resize(cap);
        }
        if (p.thermodynamics) {
            temperature.resize(cap); vapor.resize(cap); cloud.resize(cap);
        }
        if (smoothing) {
            for (int k = 0; k < 3; ++k)
                if (p.smooth_fields[k]) smooth_out[k].resize(cap);
        }
        if (p.adaptive) {
            flags.resize(cap); energy.resize(cap); split_count.resize(cap); split_slot.resize(cap);
            split_candidates.resize(cap);
            merge_partner.resize(cap);
        }
    }

    // Permute the first n entries of every particle array by perm (gather): the neighbour sort (with the
    // predicted positions) and the compaction after merges (with each particle's last density). One pass gathers
    // as many arrays as there are free buffers of their type to gather into (GatherParticles): the scratch arrays
    // and those the step rewrites before it reads them (omega, lambda, the conjugate gradients' r, p, q, diag);
    // each gathered array is swapped with its buffer, which is then free again. Most scenes take one pass.
    // count (device memory, nullptr: n): the number of entries to permute, at most n.
    void permute_all(bool with_pred, const uint32_t* count = nullptr) {
        Few<dvec<Float4>*, 3> f4;
        f4.push_back(&pos);
        f4.push_back(&vel);
        if (with_pred) f4.push_back(&pred);
        Few<dvec<float>*, 5> f1;
        if (!with_pred) f1.push_back(&density);   // compaction keeps each particle's last density
        if (p.velocity_projection) f1.push_back(&cg_mu);
        if (p.thermodynamics) {
            f1.push_back(&temperature);
            f1.push_back(&vapor);
            f1.push_back(&cloud);
        }
        Few<dvec<Float4>*, 3> free4;
        free4.push_back(&pos_tmp);
        free4.push_back(&vel_tmp);
        if (p.vorticity > 0.0f) free4.push_back(&omega);
        Few<dvec<float>*, 6> free1;
        free1.push_back(&float_tmp);
        free1.push_back(&lambda);
        if (p.velocity_projection) {
            free1.push_back(&cg_r);
            free1.push_back(&cg_p);
            free1.push_back(&cg_q);
            free1.push_back(&cg_diag);
        }
        std::size_t next4 = 0, next1 = 0;
        bool id_done = false;
        while (next4 < f4.size || next1 < f1.size || !id_done) {
            GatherParticles g{raw(perm)};
            Few<std::pair<dvec<Float4>*, dvec<Float4>*>, GatherParticles::kFloat4> swaps4;
            Few<std::pair<dvec<float>*, dvec<float>*>, GatherParticles::kFloat> swaps1;
            for (std::size_t k = 0; k < free4.size && k < GatherParticles::kFloat4 && next4 < f4.size; ++k, ++next4) {
                g.f4_src[g.f4] = raw(*f4[next4]);
                g.f4_dst[g.f4++] = raw(*free4[k]);
                swaps4.push_back({f4[next4], free4[k]});
            }
            for (std::size_t k = 0; k < free1.size && k < GatherParticles::kFloat && next1 < f1.size; ++k, ++next1) {
                g.f1_src[g.f1] = raw(*f1[next1]);
                g.f1_dst[g.f1++] = raw(*free1[k]);
                swaps1.push_back({f1[next1], free1[k]});
            }
            if (!id_done) {
                g.u_src = raw(id);
                g.u_dst = raw(uint_tmp);
            }
            if (count) parallel_for_upto(n, count, g);
            else parallel_for(n, g);
            for (std::size_t k = 0; k < swaps4.size; ++k) swaps4[k].first->swap(*swaps4[k].second);
            for (std::size_t k = 0; k < swaps1.size; ++k) swaps1[k].first->swap(*swaps1[k].second);
            if (!id_done) id.swap(uint_tmp);
            id_done = true;
        }
    }
};

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
