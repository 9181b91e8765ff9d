// Launch code of the adaptive particles (section 5.2; adaptivity.h): after the step, mark candidates by
// their shape energy (eq. 20), merge pairs in 27 coloured passes over the cells (Figure 4), split the
// winners of the candidates' conflicts into the free slots, and compact the particles merges consumed.
#pragma once
#include <algorithm>
#include <cmath>

#include "adaptivity.h"
#include "grid.h"
#include "solver_data.h"

namespace pbf {
namespace PBF_BACKEND_NS {


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

// The race-free parallel merge: 27 passes, each over the cells of one colour (cell coordinates modulo 3),
// skipping the passes whose cells hold no pair.
inline void merge_pairs(SolverData& d, const CellRanges& fl) {
    const bool thermo = d.p.thermodynamics;
    const GridGeometry& grid = d.grid;
    uint32_t passes_with_work = reduce_over(d.n, MergePassBit{grid, raw(d.keys), raw(d.merge_partner)}, 0u, BitOr{});
    for (int oz = 0; oz < 3; ++oz)
        for (int oy = 0; oy < 3; ++oy)
            for (int ox = 0; ox < 3; ++ox) {
                if (!(passes_with_work & (1u << (ox + 3 * oy + 9 * oz)))) continue;
                int off[3] = {ox, oy, oz};
                MergePass mp{grid, fl, d.ap, d.radii, {ox, oy, oz}, {0, 0, 0}, raw(d.merge_partner), raw(d.flags),
                             raw(d.pos), raw(d.vel),
                             thermo ? raw(d.temperature) : nullptr, thermo ? raw(d.vapor) : nullptr,
                             thermo ? raw(d.cloud) : nullptr};
                std::size_t threads = 1;
                for (int a = 0; a < 3; ++a) {
                    int cnt = grid.dims[a] > off[a] ? (grid.dims[a] - off[a] + 2) / 3 : 0;
                    mp.per_axis[a] = cnt;
                    threads *= std::size_t(cnt);
                }
                parallel_for_teams(threads, mp);
            }
}

// Gather the split candidates (index order), decide with one team each, then give the winners slots while
// the capacity lasts. Returns (winners, splits): winners - splits were turned away for want of room.
inline std::pair<std::size_t, std::size_t> split_particles(SolverData& d, const CellRanges& fl) {
    const bool thermo = d.p.thermodynamics;
    auto cand_end = thrust::copy_if(exec(), thrust::counting_iterator<uint32_t>(0),
                                    thrust::counting_iterator<uint32_t>(uint32_t(d.n)), d.split_candidates.begin(),
                                    HasFlag{raw(d.flags), kSplitCandidate});
    std::size_t candidates = std::size_t(cand_end - d.split_candidates.begin());
    std::size_t winners = 0;
    if (candidates) {
        parallel_for_teams(candidates, DecideSplits{d.grid, fl, d.ap, d.radii, raw(d.split_candidates), raw(d.energy),
                                                    raw(d.id), raw(d.flags), raw(d.split_count), uint32_t(d.step)});
        // Inclusive scan: one read of its last element gives the number of winners.
        thrust::inclusive_scan(exec(), d.split_count.begin(), d.split_count.begin() + candidates,
                               d.split_slot.begin());
        winners = std::size_t(uint32_t(d.split_slot[candidates - 1]));
    }
    std::size_t room = d.capacity - d.n;
    std::size_t splits = std::min(winners, room);
    if (winners) {
        parallel_for(candidates, ApplySplits{d.grid, d.ap, d.radii, uint32_t(d.n), uint32_t(d.capacity), d.next_id,
                                             uint32_t(d.step), raw(d.split_candidates), raw(d.split_slot),
                                             raw(d.flags), raw(d.pos), raw(d.vel), raw(d.id), raw(d.density),
                                             thermo ? raw(d.temperature) : nullptr, thermo ? raw(d.vapor) : nullptr,
                                             thermo ? raw(d.cloud) : nullptr});
    }
    d.next_id += uint32_t(splits);
    if (splits && d.p.velocity_projection)   // new children start their warm start from zero
        thrust::fill(exec(), d.cg_mu.begin() + d.n, d.cg_mu.begin() + d.n + splits, 0.0f);
    d.n += splits;
    return {winners, splits};
}

// Drop the particles consumed by merges (kept in order, deterministic); returns how many.
inline std::size_t compact(SolverData& d) {
    auto end = thrust::copy_if(exec(), thrust::counting_iterator<uint32_t>(0),
                               thrust::counting_iterator<uint32_t>(uint32_t(d.n)), d.perm.begin(), IsAlive{raw(d.flags)});
    std::size_t alive = std::size_t(end - d.perm.begin());
    std::size_t merges = d.n - alive;
    if (merges) {
        d.n = alive;
        d.permute_all(false);
    }
    return merges;
}

// Splitting and merging (section 5.2) on the committed positions. The grid built this step is still valid:
// positions only moved within their cells (wrapping).
inline void adapt(SolverData& d) {
    d.clock.begin(kPhaseMerging);
    CellRanges fl = d.fluid_ranges(d.pos);
    mark_candidates(d, fl);
    d.clock.begin(kPhaseMergePasses);
    merge_pairs(d, fl);
    d.clock.end(kPhaseMergePasses);
    d.clock.end(kPhaseMerging);

    d.clock.begin(kPhaseSplitting);
    std::pair<std::size_t, std::size_t> split = split_particles(d, fl);
    std::size_t winners = split.first, splits = split.second;
    d.clock.end(kPhaseSplitting);

    d.clock.begin(kPhaseMerging);
    d.clock.begin(kPhaseCompaction);
    std::size_t merges = compact(d);
    d.clock.end(kPhaseCompaction);
    d.clock.end(kPhaseMerging);

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
