// Launch code of the adaptive particles (section 5.2; adaptivity.h): after the step, mark candidates by
// their shape energy (eq. 20), merge pairs in 27 coloured passes over the cells (Figure 4), split the
// winners of the candidates' conflicts into the free slots, and compact the particles merges consumed.
#pragma once
#include <thrust/scan.h>

#include <algorithm>
#include <cmath>

#include "adaptivity.h"
#include "cell_walk.h"
#include "counted_launch.h"
#include "device_memory.h"
#include "grid.h"
#include "parallel_for.h"
#include "solver_data.h"

namespace pbf {
namespace PBF_BACKEND_NS {


struct HasFlag {
    const uint8_t* flags;
    uint8_t flag;
    PBF_HD bool operator()(uint32_t i) const { return (flags[i] & flag) != 0; }
};

inline AdaptParams make_adapt_params(const Params& p, const LevelRadii& radii) {
    AdaptParams ap{};
    ap.k_p = p.k_p;
    ap.k_c = p.k_c;
    ap.split_threshold = p.split_threshold;
    ap.merge_threshold = p.merge_threshold;
    ap.max_level = p.max_level < kMaxLevels - 1 ? p.max_level : kMaxLevels - 2;
    ap.min_distance = p.min_distance;
    ap.lookahead_height = p.thermodynamics ? p.lookahead_height : 0.0f;
    ap.refine_warm_air = p.thermodynamics && p.refine_warm_air;
    ap.heating_time = p.thermodynamics ? p.heating_time : 0.0f;
    ap.h0 = p.h0;
    ap.wall_band = p.coarse_near_walls ? p.h0 : 0.0f;
    for (int l = 0; l < kMaxLevels; ++l) ap.spacing[l] = p.spacing * std::pow(2.0f, -l / 3.0f);
    // Two children of different parents are >= conflict - 2 * max offset apart: make that the threshold.
    ap.conflict_radius = ap.spacing[1] + p.min_distance * radii.h[1];
    if (ap.conflict_radius > p.h0) ap.conflict_radius = p.h0;
    return ap;
}

// Shape energy and split / merge candidates, then each merge candidate's partner (read-only passes).
inline void mark_candidates(SolverData& d, const CellRanges& fl) {
    parallel_for(d.n, MarkCandidates{d.grid, d.ap, d.atm, d.radii, raw(d.pos), raw(d.temperature), raw(d.vapor), raw(d.cloud),
                                     raw(d.energy), raw(d.flags)});
    parallel_for(d.n, FindMergePartners{d.grid, fl, d.radii, raw(d.flags), raw(d.merge_partner)});
}

// The race-free parallel merge (MergeCell): the cells in 27 colours, colour after colour where their neighbourhoods
// overlap (for_each_cell_by_colour; on the GPU one launch, each cell's team waiting only for the earlier colours'
// teams within 2 cells), the cells without a pair passed over.
inline void merge_pairs(SolverData& d, const CellRanges& fl) {
    const bool thermo = d.p.thermodynamics;
    d.colour_epoch += 1;
    const MergeCell merge{d.grid, fl, d.ap, d.radii, raw(d.merge_partner), raw(d.flags), raw(d.pos), raw(d.vel),
                          thermo ? raw(d.temperature) : nullptr, thermo ? raw(d.vapor) : nullptr,
                          thermo ? raw(d.cloud) : nullptr};
    for_each_cell_by_colour(d.grid.dims, d.grid.periodic, raw(d.colour_done), d.colour_epoch, merge);
}

// Gather the split candidates (index order), decide with one team each, then give the winners slots while the
// capacity lasts (new children start their warm start from zero). The counts stay in device memory: the
// candidates' number sizes the decisions' and the slots' walks there (parallel_for_*_upto), and the scan runs over
// n entries, of which the first `candidates` matter (each entry is 0 or 1, so no sum wraps).
inline void split_particles(SolverData& d, const CellRanges& fl) {
    const bool thermo = d.p.thermodynamics;
    AdaptCounts* counts = &raw(d.step_sums)->adapt;
    const std::size_t n = d.n;
    select_into(n, HasFlag{raw(d.flags), kSplitCandidate}, raw(d.split_candidates), &counts->candidates);
    parallel_for_teams_upto(n, &counts->candidates,
                            DecideSplits{d.grid, fl, d.ap, d.radii, raw(d.split_candidates), raw(d.energy), raw(d.id),
                                         raw(d.flags), raw(d.split_count), uint32_t(d.step)});
    if (n > 0)   // inclusive scan: slot[t] - 1 winners come before candidate t
        thrust::inclusive_scan(exec(), d.split_count.begin(), d.split_count.begin() + n, d.split_slot.begin());
    parallel_for_upto(n, &counts->candidates,
                      ApplySplits{d.grid, d.ap, d.radii, uint32_t(n), uint32_t(d.capacity), d.next_id, uint32_t(d.step),
                                  raw(d.split_candidates), raw(d.split_slot), raw(d.flags),
                                  d.p.velocity_projection ? raw(d.cg_mu) : nullptr, raw(d.pos), raw(d.vel), raw(d.id),
                                  raw(d.density), thermo ? raw(d.temperature) : nullptr,
                                  thermo ? raw(d.vapor) : nullptr, thermo ? raw(d.cloud) : nullptr});
    run_once(SplitTotals{uint32_t(n), uint32_t(d.capacity), raw(d.split_slot), counts});
}

// Splitting and merging (section 5.2) on the committed positions. The grid built this step is still valid:
// positions only moved within their cells (wrapping). The host waits for none of its counts: the compaction selects
// the particles that stay (in order, deterministic: the splits' children included, the merges' consumed ones left
// out) among the first min(2 n, capacity) slots (each particle splits at most once), and permutes that many slots'
// threads, those past the count returning at once. The counts come to the host with the step's sums, and
// finish_adapt then sets the particle count; until then d.n is that bound.
inline void adapt(SolverData& d) {
    AdaptCounts* counts = &raw(d.step_sums)->adapt;
    d.clock.begin(kPhaseMerging);
    CellRanges fl = d.fluid_ranges(d.pos);
    mark_candidates(d, fl);
    d.clock.begin(kPhaseMergePasses);
    merge_pairs(d, fl);
    d.clock.end(kPhaseMergePasses);
    d.clock.end(kPhaseMerging);

    d.clock.begin(kPhaseSplitting);
    split_particles(d, fl);
    d.clock.end(kPhaseSplitting);

    d.clock.begin(kPhaseMerging);
    d.clock.begin(kPhaseCompaction);
    d.adapt_waiting = true;
    d.adapt_from = d.n;
    d.n = std::min(2 * d.n, d.capacity);
    select_into(d.n, KeptAfterMerges{raw(d.flags), counts}, raw(d.perm), &counts->alive);
    d.permute_all(false, &counts->alive);
    d.clock.end(kPhaseCompaction);
    d.clock.end(kPhaseMerging);
}

// The particle count and the statistics of the step's splitting and merging, from its counts as the host read them
// (with the step's sums); nothing where the step did not adapt.
inline void finish_adapt(SolverData& d, const AdaptCounts& counts) {
    if (!d.adapt_waiting) return;
    const std::size_t before = d.adapt_from, winners = counts.winners, splits = counts.after_splits - before,
                      merges = counts.after_splits - counts.alive;
    d.adapt_waiting = false;
    d.n = counts.alive;
    d.next_id += uint32_t(splits);
    StepStats& s = d.last_stats;
    s.split_last = (long long)splits;
    s.merge_last = (long long)merges;
    s.capacity_rejects_last = (long long)(winners - splits);
    s.splits += (long long)splits;
    s.merges += (long long)merges;
    s.split_capacity_rejects += (long long)(winners - splits);
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
