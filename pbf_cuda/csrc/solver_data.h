// The solver's data, apart from its algorithm (SPlisHSPlasH's SimulationData beside its TimeStep): the
// parameters and what is derived from them once, the particle arrays (structure of arrays, sorted by cell
// every step), the clock and the statistics. The phases (*_launch.h) read and write it; the step that runs
// them in the paper's order is Solver::do_step (solver_impl.inl).
#pragma once
#include "launch.h"

#include "adaptivity.h"
#include "diagnostics.h"
#include "grid.h"
#include "kernels.h"
#include "neighbor_list.h"
#include "params.h"
#include "pbf_constraints.h"
#include "solver_api.h"
#include "thermodynamics.h"

namespace pbf {
namespace PBF_BACKEND_NS {

struct SolverData {
    Params p;
    GridGeometry grid{};
    LevelRadii radii{};
    ConstraintParams cp{};      // pbf_constraints_launch.h: make_constraint_params
    AtmosphereParams atm{};     // thermodynamics_launch.h: make_atmosphere_params
    AdaptParams ap{};           // adaptivity_launch.h: make_adapt_params
    bool smoothing = false;     // smoothing_launch.h: smoothing_active
    std::size_t n = 0, nb = 0, capacity = 0;   // fluid particles, boundary particles, fluid slots
    long long step = 0, last_good = 0;
    double time = 0.0;
    uint32_t next_id = 0;
    bool end_budget_is_next_start = false;   // the last step's end sums are this state's (diagnostics_launch.h)

    // Fluid particles, n of capacity slots in use. pos (w = mass), pred the predicted x* of the step.
    dvec<Float4> pos, pred, pos_tmp, vel, vel_tmp, omega;
    dvec<uint32_t> id, uint_tmp, keys, perm, cell_start, cell_end;
    dvec<uint32_t> sub_start, sub_end;    // adaptive runs: nested sub-cell ranges (grid.h)
    dvec<float> sub_radius, cell_radius;  // adaptive runs: largest kernel radius per sub-cell and per cell
    dvec<uint32_t> nbr_count, nbr_index;  // this step's neighbour lists (neighbor_list.h), with pbf.neighbor_list
    uint32_t nbr_width = 32;              // the lists' row width (grows to the longest row seen, grid_launch.h)
    uint32_t nbr_row = 0, nbr_slot = 0;   // their layout: candidate k of particle i at i nbr_row + k nbr_slot
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
        keys.resize(cap); perm.resize(cap);
        float_tmp.resize(cap);
        step_sums.resize(1);
        if (p.neighbor_list) nbr_count.resize(cap);
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
    // predicted positions) and the compaction after merges (with each particle's last density).
    template <class T>
    void permute(dvec<T>& a, dvec<T>& tmp) {
        thrust::gather(exec(), perm.begin(), perm.begin() + n, a.begin(), tmp.begin());
        a.swap(tmp);
    }
    void permute_all(bool with_pred) {
        permute(pos, pos_tmp);
        if (with_pred) permute(pred, pos_tmp);
        else permute(density, float_tmp);  // compaction keeps each particle's last density
        permute(vel, vel_tmp);
        permute(id, uint_tmp);
        if (p.velocity_projection) permute(cg_mu, float_tmp);
        if (p.thermodynamics) {
            permute(temperature, float_tmp);
            permute(vapor, float_tmp);
            permute(cloud, float_tmp);
        }
    }
};

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
