// Adaptive particles (section 5.2): shape energy (eq. 20), splitting 1 -> 2 and merging 2 -> 1
// with exact mass bookkeeping (m_l = m0 2^-l, h_l = h0 2^(-l/3)).
//
// Splitting. A particle with E > alpha and l < max_level is a candidate. Its two children sit at
// x +- (d_{l+1} / 2) n, with n a unit direction drawn from (id, step) and d_{l+1} the lattice spacing
// of level l+1. It splits only if (a) no other candidate of higher priority (larger E; ties go to a
// hash of id and step) lies within the conflict radius, so children of two parents splitting in the
// same step never come closer than the threshold, and (b) no existing particle other than the parent
// lies within min_distance * h_{l+1} of either child (only particles within |offset| + r_min of the
// parent can). The candidates are first gathered into a list (index order); one team per candidate
// decides. Winners get slots from a prefix sum over the list; the parent's slot holds child 1, slot
// n + (winners before it) holds child 2. With the capacity full, the winners that fit split and the
// rest are counted as rejected.
//
// Merging. Candidates have E < beta and l > 0. Each finds its partner first (closest same-level
// candidate within h_l, a read-only parallel pass). Teams of threads then run over grid cells, not
// particles (Figure 4): cells are processed in 27 passes, a pass taking every cell whose coordinates
// are congruent to the pass offset modulo 3 (periodic axes have a cell count divisible by 3 when
// adaptive, so the pattern holds across the wrap); cells that hold no pair are passed over. The team
// working on cell A reads and writes only particles in A and its 26 neighbours (A +- 1): the partner
// search radius h_l <= h0 <= cell side, and the too-close check around the midpoint
// m = (x_i + x_j)/2 covers |x - m| < min_distance h_{l-1} <= 0.5 h0 with |m - x_i| <= h_l/2, so every
// particle it touches lies within h0 of x_i, i.e. in A +- 1. Two cells of one pass are at least 3 cells
// apart on some axis, so their A +- 1 blocks are disjoint: no particle is read by one team while another
// writes it, and none is consumed twice (eq. 21 with d = ceil(h / L) = 1, stride 2d + 1). Particles
// merged earlier in the step sit at their midpoints, up to h_1 / 2 outside the cell they were sorted
// into, so the too-close searches (here and for splits) prune cells with that slack; such a particle
// is seen whenever its cell lies in the block (min_distance <= 0.5 is enforced by the scene). Inside a team
// the cell's particles are taken one at a time in index order, so the outcome does not depend on the
// team size. The merged particle replaces i at the midpoint (mass-weighted averages: equal masses);
// j is marked dead and removed by the compaction that follows. A team's block meets only the blocks of the cells
// within 2 of A, so A's team needs only those of earlier passes to have finished: on the GPU the 27 passes are one
// launch in which each team waits for just those (cell_walk.h: for_each_cell_by_colour), with the passes' results.
#pragma once
#include "common.h"
#include "grid.h"
#include "kernels.h"
#include "thermodynamics.h"

namespace pbf {

enum AdaptFlag : uint8_t { kMergeCandidate = 1, kSplitCandidate = 2, kDead = 4, kMergedNow = 8, kSplitNow = 16 };

// The counts of one splitting and merging, written in device memory as the step goes and read by the host with the
// step's other sums (StepSums, diagnostics.h; adaptivity_launch.h: adapt, finish_adapt): the kernels read them where
// they are, so the host does not wait for any of them.
struct AdaptCounts {
    uint32_t candidates;     // split candidates (the first entries of SolverData::split_candidates)
    uint32_t winners;        // candidates that won their conflicts
    uint32_t after_splits;   // particles after the splits: n + min(winners, capacity - n)
    uint32_t alive;          // particles the compaction keeps
};

struct AdaptParams {
    float k_p, k_c, split_threshold, merge_threshold;
    int max_level;
    float min_distance;
    float h0;
    float spacing[kMaxLevels];  // lattice spacing of each level, m
    float conflict_radius;      // m
    float lookahead_height;     // m; 0: the paper's criterion
    bool refine_warm_air;       // the 'thermal' and 'heated' criteria
    float heating_time;         // s; > 0: the 'heated' criterion's tau
    float wall_band;            // m; particles closer than this to a wall stay at level 0 (0: off)
};

// Shape energy (eq. 20) and candidate marks. The refinement criterion decides what water E measures:
//   paper      E = k_p (1 - exp(-k_c w))                                   (eq. 20)
//   lookahead  E = k_p (1 - exp(-k_c w*)),  w* = max(w, v + w - q_s(T - Gamma_d dz))
//   thermal    E = k_p (1 - exp(-k_c w*)),  w* = max(w, (T - T0(y)) / Q)
//   heated     E = k_p (1 - exp(-k_c w*)),  w* = max(w, (T - T0(y)) / Q, S_e(x, z) tau / Q)
// Look-ahead: w* is the cloud water of the particle lifted dz dry-adiabatically (eq. 7) and brought to
// saturation (eq. 10, latent heat left out, which only lowers w*): air within dz of its condensation level is
// refined before it condenses. Thermal: w* is the particle's heat excess over the environment profile
// T0(y) = T_g - Gamma y (eq. 6), written as the cloud water whose condensation would release it (eq. 11,
// Q = L / c_p), so heated, buoyant air is refined from the ground up, before it reaches its condensation
// level, on the same scale k_c as the cloud: with the defaults it splits at 0.45 K of excess, merges below 0.06 K.
// Heated: the thermal criterion, and every particle above heated ground, from the ground to the lid, with S_e(x, z)
// tau / Q the cloud water whose condensation would release the heat the ground under it gives in tau = heating_time
// (eq. 5's pattern, without the diurnal factor): the columns where thermals will rise are fine before they rise,
// and the thermal rises through fine air from the top of the walls' band up.
// Either way the thermals that build a cloud run at the fine resolution, not only the cloud.
// Merging uses the same E with beta < alpha, so a particle the criterion wants fine is never merged back.
// Walls (coarse_near_walls): E = 0 within h0 of a wall, whatever the criterion.
struct MarkCandidates {
    GridGeometry grid;          // the domain and which axes have walls
    AdaptParams ap;
    AtmosphereParams atm;
    LevelRadii radii;
    const Float4* pos;
    const float* temperature;
    const float* vapor;
    const float* cloud;
    float* energy;
    uint8_t* flags;
    PBF_HD void operator()(uint32_t i) const {
        float w = cloud[i];
        if (ap.lookahead_height > 0.0f) {
            float lifted = temperature[i] - atm.dry_lapse_rate * ap.lookahead_height;
            w = fmaxf(w, vapor[i] + cloud[i] - atm.saturation(lifted));
        }
        if (ap.refine_warm_air) {
            float excess = temperature[i] - atm.environment_temperature(pos[i].y);
            w = fmaxf(w, excess / atm.latent_heat);
        }
        if (ap.heating_time > 0.0f) {  // the heat the ground below gives in tau (eq. 5), as cloud water
            float column = atm.heating_rate * atm.heating_pattern(pos[i].x, pos[i].z) * ap.heating_time;
            w = fmaxf(w, column / atm.latent_heat);
        }
        float e = ap.k_p * (-expm1f(-ap.k_c * w));  // E = k_p (1 - exp(-k_c w)), eq. 20
        // Next to a wall the boundary particles sit on the level-0 lattice: a finer kernel sees them as lumps and
        // lets a fine particle slip against the wall, so within h0 of a wall E = 0 (never split, finer ones merge).
        for (int a = 0; a < 3; ++a) {
            if (grid.periodic[a]) continue;
            float x = component(xyz(pos[i]), a);
            if (x < ap.wall_band || x > grid.domain[a] - ap.wall_band) e = 0.0f;
        }
        energy[i] = e;
        int l = radii.level_of_mass(pos[i].w);
        uint8_t f = 0;
        if (e > ap.split_threshold && l < ap.max_level) f |= kSplitCandidate;
        if (e < ap.merge_threshold && l > 0) f |= kMergeCandidate;
        flags[i] = f;
    }
};

PBF_INLINE Vec3 split_direction(uint32_t id, uint32_t step) {
    uint32_t s = hash_u32(id * 0x9E3779B9u ^ hash_u32(step));
    float u = 2.0f * hash_unit(s) - 1.0f;              // cos(theta)
    float phi = 2.0f * kPi * hash_unit(s ^ 0x68bc21ebu);
    float r = sqrtf(fmaxf(0.0f, 1.0f - u * u));
    return Vec3{r * cosf(phi), u, r * sinf(phi)};
}

// Decide which split candidates split this step: one team per candidate (a warp on the GPU), its lanes
// sharing the two neighbour searches and voting. candidates[t] is the t-th candidate in index order;
// writes count[t] (0 or 1) and kSplitNow.
struct DecideSplits {
    GridGeometry grid;
    CellRanges fluid;
    AdaptParams ap;
    LevelRadii radii;
    const uint32_t* candidates;
    const float* energy;
    const uint32_t* id;
    uint8_t* flags;
    uint32_t* count;
    uint32_t step;
    template <class Team>
    PBF_HD void operator()(uint32_t t, const Team& team) const {
        uint32_t i = candidates[t];
        if (team.rank() == 0) count[t] = 0;
        uint8_t fi = flags[i];
        if (fi & (kDead | kMergedNow)) return;
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        int l = radii.level_of_mass(pi.w);
        float ei = energy[i];
        uint32_t idi = id[i];
        // Priority: larger E first; ties (e.g. a uniform cloud) broken by a hash of (id, step), so that
        // about one in every conflict neighbourhood wins each step wherever the particles are numbered.
        uint32_t hi_rank = hash_u32(idi ^ hash_u32(step + 0x51ed27u));
        const int ci[3] = {cell_coord(grid, xi.x, 0), cell_coord(grid, xi.y, 1), cell_coord(grid, xi.z, 2)};
        const BlockSearch<Team> block(team, grid, fluid, ci);   // both searches below look around the parent
        // Split candidates have not moved since the sort (merges move merge candidates only): no slack.
        const bool lost = block.any(team, xi, ap.conflict_radius, 0.0f, [&](uint32_t j, Vec3, float) {
            if (j == i || !(flags[j] & kSplitCandidate) || (flags[j] & (kDead | kMergedNow))) return false;
            float ej = energy[j];
            uint32_t hj = hash_u32(id[j] ^ hash_u32(step + 0x51ed27u));
            return ej > ei || (ej == ei && (hj > hi_rank || (hj == hi_rank && id[j] < idi)));
        });
        if (lost) return;
        Vec3 off = (0.5f * ap.spacing[l + 1]) * split_direction(idi, step);
        Vec3 c1 = xi + off, c2 = xi - off;
        float r_min = ap.min_distance * radii.h[l + 1];
        float r2_min = r_min * r_min;
        // Children must stay inside the walls.
        for (int a = 0; a < 3; ++a) {
            if (grid.periodic[a]) continue;
            float lo = fminf(component(c1, a), component(c2, a)), hi = fmaxf(component(c1, a), component(c2, a));
            if (lo < 0.0f || hi > grid.domain[a]) return;
        }
        // Only particles within |offset| + r_min of the parent can come within r_min of a child. Merged
        // particles of this step sit at their midpoints, possibly outside their cell's box: slack.
        float reach = 0.5f * ap.spacing[l + 1] + r_min;
        const bool blocked = block.any(team, xi, reach, radii.moved_slack(), [&](uint32_t j, Vec3, float) {
            if (j == i || (flags[j] & kDead)) return false;
            Vec3 xj = xyz(fluid.pos[j]);
            Vec3 d1 = min_image(grid, c1 - xj), d2 = min_image(grid, c2 - xj);
            return dot(d1, d1) < r2_min || dot(d2, d2) < r2_min;
        });
        if (blocked) return;
        if (team.rank() == 0) {
            count[t] = 1;
            flags[i] = fi | kSplitNow;
        }
    }
};

// Write the children of the winners that fit in the capacity, one thread per candidate.
// slot[t] = inclusive scan of count, so a winner (count 1) has slot[t] - 1 winners before it.
struct ApplySplits {
    GridGeometry grid;
    AdaptParams ap;
    LevelRadii radii;
    uint32_t n;            // particles before the split
    uint32_t capacity;
    uint32_t next_id;
    uint32_t step;
    const uint32_t* candidates;
    const uint32_t* slot;
    uint8_t* flags;
    float* mu;             // the velocity projection's warm start (nullptr: none): a child starts from zero
    Float4* pos;
    Float4* vel;
    uint32_t* id;
    float* density;        // children start with the parent's density (diagnostics only)
    float* temperature;    // nullptr when no thermodynamics
    float* vapor;
    float* cloud;
    PBF_HD void operator()(uint32_t t) const {
        uint32_t i = candidates[t];
        if (!(flags[i] & kSplitNow)) return;
        uint32_t before = slot[t] - 1u;
        uint32_t k = n + before;
        if (k >= capacity) {  // no room: this winner does not split
            flags[i] &= uint8_t(~kSplitNow);
            return;
        }
        Float4 p = pos[i];
        int l = radii.level_of_mass(p.w);
        Vec3 n3 = split_direction(id[i], step);
        Vec3 off = (0.5f * ap.spacing[l + 1]) * n3;
        float m_child = 0.5f * p.w;  // exact: a power-of-two division
        pos[i] = make_float4(wrap_position(grid, xyz(p) + off), m_child);
        pos[k] = make_float4(wrap_position(grid, xyz(p) - off), m_child);
        vel[k] = vel[i];
        id[k] = next_id + before;
        density[k] = density[i];
        if (temperature) {
            temperature[k] = temperature[i];
            vapor[k] = vapor[i];
            cloud[k] = cloud[i];
        }
        if (mu) mu[k] = 0.0f;
        flags[k] = 0;
    }
};

// The splits' totals from the decisions' inclusive scan (one thread): winners = slot[candidates - 1], and the
// particles after the splits, those that fit in the capacity (ApplySplits gives the rest no slot).
struct SplitTotals {
    uint32_t n, capacity;
    const uint32_t* slot;
    AdaptCounts* counts;
    PBF_HD void operator()() const {
        const uint32_t winners = counts->candidates ? slot[counts->candidates - 1] : 0u;
        counts->winners = winners;
        counts->after_splits = n + (winners < capacity - n ? winners : capacity - n);
    }
};

// Particles the compaction keeps: those below the count after the splits that no merge consumed.
struct KeptAfterMerges {
    const uint8_t* flags;
    const AdaptCounts* counts;
    PBF_HD bool operator()(uint32_t i) const { return i < counts->after_splits && !(flags[i] & kDead); }
};

// Each merge candidate's partner: the closest same-level candidate within h_l (ties: lower index).
// Read-only and fully parallel; the merge walk only consumes the pairs. (Reading the step's lists, narrowed to the
// pairs within support at x*, instead of the 27 cells changed the partners where a pair had closed in by more than
// the lists' skin during the step or straddled the periodic wrap: the states left the cell search's after 350-450 of
// Table 1's 500 steps of `growing`, so the partners keep the cell search.)
struct FindMergePartners {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    const uint8_t* flags;
    uint32_t* partner;  // 0xffffffff: none
    PBF_HD void operator()(uint32_t i) const {
        uint32_t best = 0xffffffffu;
        if (flags[i] & kMergeCandidate) {
            Float4 pi = fluid.pos[i];
            float hl = radii.h[radii.level_of_mass(pi.w)];
            float best_r2 = hl * hl;
            for_each_neighbor(grid, fluid, xyz(pi), hl, [&](uint32_t j, Vec3, float r2) {
                if (j == i || !(flags[j] & kMergeCandidate) || fluid.pos[j].w != pi.w) return;
                if (r2 < best_r2 || (r2 == best_r2 && j < best)) { best = j; best_r2 = r2; }
            });
        }
        partner[i] = best;
    }
};

// The race-free parallel merge, one cell's team (a warp on the GPU, one thread on the CPU), called for the cells in
// 27 colours (cell_walk.h: for_each_cell_by_colour). The team walks the cell's particles in index order, exactly as one
// thread would; its lanes share only each midpoint's too-close search and vote on it, and the candidate's lane writes.
// The result is therefore the same for any team size.
struct MergeCell {
    GridGeometry grid;
    CellRanges fluid;
    AdaptParams ap;
    LevelRadii radii;
    const uint32_t* partner;
    uint8_t* flags;
    Float4* pos;           // == fluid.pos (written in place)
    Float4* vel;
    float* temperature;
    float* vapor;
    float* cloud;
    // A cell's team before its turn: what no other team changes while the cells merge (the cells' ranges, the merge
    // candidates' marks and partners), read before the team waits for its turn (cell_walk.h: for_each_cell_by_colour).
    template <class Team>
    struct Turn {
        uint32_t start, end;
        BlockSearch<Team> block;   // every too-close search of this cell's pairs
        uint32_t first_partner;    // the partner of this lane's particle of the cell's first chunk (kNone: none)
        bool busy;                 // the cell holds a merge candidate with a partner
    };
    static constexpr uint32_t kNone = 0xffffffffu;
    template <class Team>
    PBF_HD Turn<Team> prepare(const int c[3], const Team& team) const {
        const uint32_t cell = cell_index(grid, c[0], c[1], c[2]);
        const uint32_t start = fluid.start[cell], end = fluid.end[cell];
        const uint32_t mine = start + team.rank();
        const uint32_t first_partner = mine < end ? partner[mine] : kNone;
        // Only the candidate mark is read of the flags, which no team changes (others set the other bits meanwhile).
        bool busy = team.any(first_partner != kNone && (flags[mine] & kMergeCandidate));
        for (uint32_t chunk = start + Team::kSize; chunk < end && !busy; chunk += Team::kSize) {
            const uint32_t i = chunk + team.rank();
            busy = team.any(i < end && partner[i] != kNone && (flags[i] & kMergeCandidate));
        }
        return Turn<Team>{start, end, BlockSearch<Team>(team, grid, fluid, c), first_partner, busy};
    }
    template <class Team>
    PBF_HD void operator()(const Turn<Team>& turn, const Team& team) const {
        const uint32_t end = turn.end;
        const BlockSearch<Team>& block = turn.block;
        // The cell's particles in chunks of the team's size: one vote finds the chunk's merge candidates with a
        // partner (neither the candidate mark nor the partner changes while the cells merge), then those are taken
        // one at a time in index order, exactly as a walk over every particle would. Only this team touches the
        // block while it runs, so each lane reads its own candidate's flags, position and its partner's beforehand,
        // and the flags a candidate's turn sees are those with this chunk's earlier merges added (lane l's candidate
        // merged with merged_with: chunk + l took kMergedNow, merged_with kDead); a particle moves only by merging,
        // which its flags then show. Its velocity and scalars, read beforehand as well, are current wherever it
        // merges (neither particle of a pair that merges was touched earlier in the chunk), so the candidate's own
        // lane writes the merged particle.
        for (uint32_t chunk = turn.start; chunk < end; chunk += Team::kSize) {
            const uint32_t mine = chunk + team.rank();
            const uint32_t my_flags = mine < end ? flags[mine] : 0u;
            const uint32_t candidate_partner = chunk == turn.start ? turn.first_partner : (mine < end ? partner[mine] : kNone);
            const bool has_pair = (my_flags & kMergeCandidate) && candidate_partner != kNone;
            uint32_t my_partner = 0, my_partner_flags = 0, merged_with = kNone;
            Float4 my_pos{}, my_partner_pos{}, my_vel{}, my_partner_vel{};
            float my_scalars[3] = {}, partner_scalars[3] = {};   // temperature, vapor, cloud
            if (has_pair) {
                my_partner = candidate_partner;
                my_partner_flags = flags[my_partner];
                my_pos = pos[mine];
                my_partner_pos = pos[my_partner];
                my_vel = vel[mine];
                my_partner_vel = vel[my_partner];
                if (temperature) {
                    my_scalars[0] = temperature[mine], partner_scalars[0] = temperature[my_partner];
                    my_scalars[1] = vapor[mine], partner_scalars[1] = vapor[my_partner];
                    my_scalars[2] = cloud[mine], partner_scalars[2] = cloud[my_partner];
                }
            }
            for (uint32_t pending = team.ballot(has_pair); pending; pending &= pending - 1u) {
                const uint32_t lane = lowest_set_bit(pending);
                const uint32_t i = chunk + lane;
                const uint32_t best = team.broadcast(my_partner, lane);
                const uint32_t fi = team.broadcast(my_flags, lane), fj = team.broadcast(my_partner_flags, lane);
                const bool taken_in_chunk = team.any(merged_with != kNone && (merged_with == i || merged_with == best ||
                                                                               chunk + team.rank() == best));
                if (taken_in_chunk || ((fi | fj) & (kDead | kMergedNow))) continue;
                const Float4 pi = team.broadcast(my_pos, lane);
                const Float4 pj = team.broadcast(my_partner_pos, lane);
                Vec3 xi = xyz(pi);
                int l = radii.level_of_mass(pi.w);
                Vec3 best_r = min_image(grid, xi - xyz(pj));
                Vec3 mid = xi - 0.5f * best_r;  // x_i - (x_i - x_j)/2, minimum image
                float r_min = ap.min_distance * radii.h[l - 1];
                if (block.any(team, mid, r_min, radii.moved_slack(), [&](uint32_t k, Vec3, float) {
                        return !(k == i || k == best || (flags[k] & kDead));
                    }))
                    continue;
                if (team.rank() == lane) {   // the candidate's lane, which holds both particles' fields
                    const uint32_t j = best;
                    const Float4 vi = my_vel, vj = my_partner_vel;
                    pos[i] = make_float4(wrap_position(grid, mid), pi.w + pj.w);  // exact: 2 m_l = m_{l-1}
                    vel[i] = Float4{0.5f * (vi.x + vj.x), 0.5f * (vi.y + vj.y), 0.5f * (vi.z + vj.z), 0.0f};
                    if (temperature) {
                        temperature[i] = 0.5f * (my_scalars[0] + partner_scalars[0]);
                        vapor[i] = 0.5f * (my_scalars[1] + partner_scalars[1]);
                        cloud[i] = 0.5f * (my_scalars[2] + partner_scalars[2]);
                    }
                    flags[i] = uint8_t(fi | kMergedNow);
                    flags[j] = uint8_t(fj | kDead);
                    merged_with = j;
                }
                team.sync();
            }
        }
    }
};

}  // namespace pbf
