// Uniform-grid neighbour search (index sort, Ihmsen et al. 2011): particles are sorted by cell
// key every step; a cell's particles are the range [cell_start, cell_end) of the sorted arrays.
// Cell side >= the largest kernel radius, so neighbours lie in the 27 surrounding cells.
// Periodic axes use wrapped cell lookup and minimum-image distances (section 5.1 without the
// image particles' memory); wall axes extend the grid by one kernel radius beyond each wall
// for the boundary particles.
#pragma once
#include <cstddef>
#include "common.h"

namespace pbf {

struct GridGeometry {
    int dims[3];
    float origin[3];
    float cell[3];
    float inv_cell[3];
    float domain[3];
    float inv_domain[3];
    bool periodic[3];
    PBF_HD uint32_t num_cells() const { return uint32_t(dims[0]) * dims[1] * dims[2]; }
};

inline GridGeometry make_grid_geometry(const float domain[3], const bool periodic[3], float h_max) {
    GridGeometry g{};
    for (int a = 0; a < 3; ++a) {
        g.domain[a] = domain[a];
        g.inv_domain[a] = 1.0f / domain[a];
        g.periodic[a] = periodic[a];
        if (periodic[a]) {
            int n = int(std::floor(domain[a] / h_max));
            g.dims[a] = n < 3 ? 3 : n;
            g.origin[a] = 0.0f;
            g.cell[a] = domain[a] / g.dims[a];
        } else {
            float extent = domain[a] + 2.0f * h_max;
            int n = int(std::ceil(extent / h_max - 1e-4f));
            g.dims[a] = n < 1 ? 1 : n;
            g.origin[a] = -h_max;
            g.cell[a] = extent / g.dims[a];
            if (g.cell[a] < h_max) { g.dims[a] -= 1; g.cell[a] = extent / g.dims[a]; }
        }
        g.inv_cell[a] = 1.0f / g.cell[a];
    }
    return g;
}

PBF_INLINE int cell_coord(const GridGeometry& g, float x, int a) {
    float t = (x - g.origin[a]) * g.inv_cell[a];
    if (!(t > -1e9f && t < 1e9f)) t = 0.0f;  // NaN / Inf: any valid cell (the step's check reports it)
    int c = int(floorf(t));
    if (g.periodic[a]) {
        c %= g.dims[a];
        if (c < 0) c += g.dims[a];
    } else {
        c = c < 0 ? 0 : (c >= g.dims[a] ? g.dims[a] - 1 : c);
    }
    return c;
}

PBF_INLINE uint32_t cell_index(const GridGeometry& g, int cx, int cy, int cz) {
    return (uint32_t(cz) * g.dims[1] + uint32_t(cy)) * g.dims[0] + uint32_t(cx);
}

// The inverse of cell_index: cell coordinates (cx, cy, cz) of a cell index.
PBF_INLINE void cell_coords(const GridGeometry& g, uint32_t cell, uint32_t c[3]) {
    c[0] = cell % uint32_t(g.dims[0]);
    c[1] = (cell / uint32_t(g.dims[0])) % uint32_t(g.dims[1]);
    c[2] = cell / (uint32_t(g.dims[0]) * uint32_t(g.dims[1]));
}

PBF_INLINE uint32_t cell_key(const GridGeometry& g, Vec3 p) {
    return cell_index(g, cell_coord(g, p.x, 0), cell_coord(g, p.y, 1), cell_coord(g, p.z, 2));
}

// x_i - x_j with the minimum-image convention on periodic axes.
PBF_INLINE Vec3 min_image(const GridGeometry& g, Vec3 d) {
    if (g.periodic[0]) d.x -= g.domain[0] * rintf(d.x * g.inv_domain[0]);
    if (g.periodic[1]) d.y -= g.domain[1] * rintf(d.y * g.inv_domain[1]);
    if (g.periodic[2]) d.z -= g.domain[2] * rintf(d.z * g.inv_domain[2]);
    return d;
}

// True when x lies within distance r of a wall (boundary particles can only be neighbours then).
PBF_INLINE bool near_wall(const GridGeometry& g, Vec3 x, float r) {
    for (int a = 0; a < 3; ++a) {
        if (g.periodic[a]) continue;
        float v = component(x, a);
        if (v < r || v > g.domain[a] - r) return true;
    }
    return false;
}

// Wrap a position into [0, L) on periodic axes.
PBF_INLINE Vec3 wrap_position(const GridGeometry& g, Vec3 p) {
    for (int a = 0; a < 3; ++a) {
        if (!g.periodic[a]) continue;
        float L = g.domain[a];
        float v = component(p, a);
        v -= L * floorf(v / L);
        if (v >= L) v -= L;  // rounding at the top edge
        set_component(p, a, v);
    }
    return p;
}

// A sorted particle set with its cell ranges, as seen from kernels (raw pointers only).
// Adaptive runs also carry nested sub-cells (below): every cell split 2 x 2 x 2, with per-cell and
// per-sub-cell largest kernel radius; uniform runs leave those pointers null.
struct CellRanges {
    const Float4* pos;        // sorted positions (w = mass)
    const uint32_t* start;    // per cell: first index
    const uint32_t* end;      // per cell: one past the last index (start == end: empty)
    const uint32_t* sub_start = nullptr;  // per sub-cell (cell * 8 + sub): first index
    const uint32_t* sub_end = nullptr;    // per sub-cell: one past the last index
    const float* sub_radius = nullptr;    // per sub-cell: largest kernel radius of its particles (m), 0 if empty
    const float* cell_radius = nullptr;   // per cell: largest kernel radius of its particles (m), 0 if empty
    const uint32_t* key = nullptr;        // per particle: its nested key as sorted
    // This step's neighbour lists (neighbor_list.h), when the solver keeps them: particle i has nbr_count[i]
    // candidates, the k-th at nbr_index[i * nbr_row + k * nbr_slot], in the order the cell search visits them.
    // A count above nbr_width is a row cut at the width: that particle's passes search the cells (listed).
    const uint32_t* nbr_count = nullptr;
    const uint32_t* nbr_index = nullptr;
    uint32_t nbr_row = 0, nbr_slot = 0, nbr_width = 0;
    // Whether particle i's passes read its list: the lists are kept and its row holds all its candidates.
    PBF_HD bool listed(uint32_t i) const { return nbr_count && nbr_count[i] <= nbr_width; }
    // Particle i's candidate k (64-bit arithmetic: the lists may hold more than 2^32 entries).
    PBF_HD uint32_t candidate(uint32_t i, uint32_t k) const {
        return nbr_index[std::size_t(i) * nbr_row + std::size_t(k) * nbr_slot];
    }
};

// ---- the walls' neighbourhoods, one table per run -------------------------------------------------------
// Boundary particles never move, and every fluid particle of a cell sees the boundary particles of the same 27
// cells. So each cell's boundary candidates are gathered once, when the walls are set (boundaries_launch.h):
// the positions (w = mass) of the boundary particles within h0 of the cell's box, in the order the 27-cell
// search visits them, one contiguous segment per cell. A fluid particle next to a wall then reads one segment
// instead of searching 27 cell ranges: on the GPU each of those ranges cost a dependent load, and the warps
// holding a wall's particles set the length of every constraint pass (a 104k-particle `growing` step took 1.7x
// as long with the walls' search as without it; docs/benchmarks.md).
struct WallNeighbourhoods {
    const uint32_t* offset = nullptr;   // per cell c: its segment is [offset[c], offset[c + 1]); nullptr: no walls
    const Float4* pos = nullptr;        // the segments' boundary positions (w = mass)
};

// Calls f(r, r2, m_b) for every boundary particle b with |r| < r_max, r = x_i - x_b (minimum image), in the
// 27-cell search's order. r_max <= h0, the reach the table was gathered for. Positions are read kListBatch at a
// time (kernel_policy.h), so that a thread has several loads in flight. For a predicted position more than a
// cell beyond a wall (clamped into the outer cells by cell_coord) the table, like the 27-cell search, can miss
// boundary particles that lie beyond the grid as well (the dam break's walls reach 1.25 h0 deep).
template <uint32_t kBatch, class F>
PBF_HD inline void for_each_wall_neighbor(const GridGeometry& g, const WallNeighbourhoods& walls, Vec3 xi,
                                          float r_max, F&& f) {
    const uint32_t c = cell_key(g, xi);
    const uint32_t e = walls.offset[c + 1];
    const float r2max = r_max * r_max;
    auto visit = [&](const Float4& pb) {
        Vec3 r = min_image(g, Vec3{xi.x - pb.x, xi.y - pb.y, xi.z - pb.z});
        float r2 = dot(r, r);
        if (r2 < r2max) f(r, r2, pb.w);
    };
    uint32_t k = walls.offset[c];
    for (; k + kBatch <= e; k += kBatch) {
        Float4 pb[kBatch];
        for (uint32_t b = 0; b < kBatch; ++b) pb[b] = walls.pos[k + b];
        for (uint32_t b = 0; b < kBatch; ++b) visit(pb[b]);
    }
    for (; k < e; ++k) visit(walls.pos[k]);
}

// Calls f(j, r, r2) for the particles j = b, b + stride, ... below e of a cell's (or sub-cell's) range with
// r2 = |x_i - x_j|^2 < r2max (minimum image), in index order. One position at a time, one cell at a time: reading
// four positions at a time, as the lists' passes do (kernel_policy.h: kListBatch), and visiting a row's consecutive
// cells in one loop both made the lists' build no faster and every list pass slower (ApplyJT +9% and +8% in ncu,
// H100; docs/performance.md, Speed of the step, change 9): this search is compiled into each list pass as its fallback.
template <class F>
PBF_HD inline void for_each_in_range(const GridGeometry& g, const Float4* pos, uint32_t b, uint32_t e,
                                     uint32_t stride, Vec3 q, float r2max, F&& f) {
    for (uint32_t j = b; j < e; j += stride) {
        const Float4 pj = pos[j];
        Vec3 r = min_image(g, Vec3{q.x - pj.x, q.y - pj.y, q.z - pj.z});
        float r2 = dot(r, r);
        if (r2 < r2max) f(j, r, r2);
    }
}

// ---- the block of cells c +- 1: the searches' pruning ----------------------------------------
// q's offset from the lower corner of cell c along axis a, in cells (minimum image on periodic axes).
PBF_HD inline float offset_in_cells(const GridGeometry& g, Vec3 q, const int c[3], int a) {
    float t = (component(q, a) - g.origin[a]) * g.inv_cell[a] - float(c[a]);
    if (g.periodic[a]) t -= float(g.dims[a]) * rintf(t / float(g.dims[a]));
    return t;
}

// Squared distance (m^2) along axis a from a point at offset rel (offset_in_cells) to the slab of cells at offset d.
PBF_HD inline float slab_gap2(const GridGeometry& g, int a, float rel, int d) {
    float lo = float(d) - rel, hi = rel - float(d + 1);
    float m = lo > hi ? lo : hi;   // max(0, lo, hi) without fmaxf, a library call on the CPU (NaN-aware)
    float e = (m > 0.0f ? m : 0.0f) * g.cell[a];
    return e * e;
}

// Coordinate c + d of the neighbouring cell along axis a, wrapped on periodic axes; false beyond a wall.
PBF_HD inline bool neighbor_coord(const GridGeometry& g, int a, int c, int d, int& out) {
    int x = c + d;
    if (g.periodic[a]) x = x < 0 ? x + g.dims[a] : (x >= g.dims[a] ? x - g.dims[a] : x);
    else if (x < 0 || x >= g.dims[a]) return false;
    out = x;
    return true;
}

// ---- nested sub-cells for particles of several radii (adaptive runs) --------------------------
// A cell of side >= h0 (the level-0 radius) is split into 2 x 2 x 2 sub-cells of side >= h0 / 2, the finest
// radius of three levels (h_3 = h0 / 2). Particles are sorted by the nested key cell * 8 + sub, so each
// cell's particles stay one contiguous range (everything that works per cell, such as merging, is unchanged)
// and each sub-cell's particles are a range inside it. A pair (i, j) interacts where |x_ij| < max(h_i, h_j)
// (the support of the symmetric kernel of eq. 19), so particle i needs only the sub-cells closer to its own
// than the larger of the two sub-cells' largest radii: a fine particle amid fine ones scans the 3 x 3 x 3
// sub-cells its own support needs (as a uniform run at that spacing does), not the level-0 volume, 8x larger.
constexpr uint32_t kSubCells = 8;

PBF_INLINE uint32_t sub_cell_of(const GridGeometry& g, Vec3 p) {
    uint32_t sub = 0;
    for (int a = 0; a < 3; ++a) {
        float t = (component(p, a) - g.origin[a]) * g.inv_cell[a];
        if (!(t > -1e9f && t < 1e9f)) t = 0.0f;
        float frac = t - floorf(t);
        uint32_t s = frac >= 0.5f ? 1u : 0u;
        // Clamped positions beyond a wall belong to the nearest sub-cell of the edge cell.
        if (!g.periodic[a]) {
            if (t < 0.0f) s = 0u;
            else if (t >= float(g.dims[a])) s = 1u;
        }
        sub |= s << a;
    }
    return sub;
}

PBF_INLINE uint32_t nested_key(const GridGeometry& g, Vec3 p) { return cell_key(g, p) * kSubCells + sub_cell_of(g, p); }

// Calls f(j, r, r2) for particles j of `set` (with nested ranges) near particle i, r = x_i - x_j (minimum image),
// a superset of the pairs with |r| < max(h_i, h_j). Two modes, chosen per pair of cells:
//   sub-cell mode, when both cells are fine (largest radius <= the sub-cell side): a sub-cell S_j is visited
//     when it lies closer to i's sub-cell S_i than R = max(largest radius in S_i, in S_j), and f is called for
//     r2 < R^2. A fine particle amid fine ones scans the 3 x 3 x 3 sub-cells its support needs, as a uniform
//     run at its spacing does, not the level-0 volume, 8 times larger.
//   cell mode, otherwise: the cell's whole range, f called for r2 < R^2 with R = max(largest radius in i's cell,
//     in j's cell): one contiguous loop, as the uniform search does.
// Every test reads the sub-cells and cells as sorted (i's own from its sort key), never positions that moved since,
// and is symmetric in i and j: j is visited from i exactly when i is from j, so pair forces stay equal and opposite.
// skin (m) widens every radius test by that much (the neighbour lists' candidates; 0 for the sums themselves).
template <class F>
PBF_HD inline void for_each_neighbor_nested(const GridGeometry& g, const CellRanges& set, uint32_t i, Vec3 q,
                                            F&& f, float skin = 0.0f) {
    const uint32_t key = set.key[i];
    const uint32_t cell_i = key / kSubCells;
    uint32_t c[3];
    cell_coords(g, cell_i, c);
    const uint32_t si = key % kSubCells;
    const int sub_i[3] = {int(si & 1u), int((si >> 1) & 1u), int(si >> 2)};
    const float sub_side = 0.5f * fminf(g.cell[0], fminf(g.cell[1], g.cell[2]));
    const float hs_i = set.sub_radius[key];
    const float hc_i = set.cell_radius[cell_i];
    const bool fine_i = hc_i <= sub_side;
    // Squared gap (m^2) along axis a between i's sub-cell and sub-cell s (0, 1) of the cell at offset d:
    // |o| - 1 whole sub-cells lie between them, o = 2 d + s - s_i.
    auto gap2 = [&](int a, int d, int s) {
        int o = 2 * d + s - sub_i[a];
        o = o < 0 ? -o : o;
        float e = o > 1 ? float(o - 1) * 0.5f * g.cell[a] : 0.0f;
        return e * e;
    };
    for (int dz = -1; dz <= 1; ++dz) {
        int cz;
        if (!neighbor_coord(g, 2, int(c[2]), dz, cz)) continue;
        for (int dy = -1; dy <= 1; ++dy) {
            int cy;
            if (!neighbor_coord(g, 1, int(c[1]), dy, cy)) continue;
            for (int dx = -1; dx <= 1; ++dx) {
                int cx;
                if (!neighbor_coord(g, 0, int(c[0]), dx, cx)) continue;
                uint32_t cell = cell_index(g, cx, cy, cz);
                uint32_t b = set.start[cell], en = set.end[cell];
                if (b == en) continue;
                float hc = set.cell_radius[cell];
                if (!(fine_i && hc <= sub_side)) {   // cell mode
                    float rc = fmaxf(hc_i, hc) + skin;
                    for_each_in_range(g, set.pos, b, en, 1u, q, rc * rc, f);
                    continue;
                }
                for (uint32_t s = 0; s < kSubCells; ++s) {   // sub-cell mode
                    uint32_t sc = cell * kSubCells + s;
                    uint32_t sb = set.sub_start[sc], se = set.sub_end[sc];
                    if (sb == se) continue;
                    float hs = fmaxf(hs_i, set.sub_radius[sc]) + skin;
                    float rs2 = hs * hs;
                    float es = gap2(0, dx, int(s & 1u)) + gap2(1, dy, int((s >> 1) & 1u)) + gap2(2, dz, int(s >> 2));
                    if (es >= rs2) continue;
                    for_each_in_range(g, set.pos, sb, se, 1u, q, rs2, f);
                }
            }
        }
    }
}

// Calls f(j, r, r2) for the particles j = start + first, start + first + stride, ... of each cell of the block
// c +- 1 whose box lies within r_max + slack of q (z, then y, then x offsets), where r2 = |q - x_j|^2 < r_max^2.
// slack lets particles that moved up to that far out of the cell they were sorted into be found.
template <class F>
PBF_HD inline void for_each_in_block_strided(const GridGeometry& g, const CellRanges& set, const int c[3], Vec3 q,
                                             float r_max, float slack, uint32_t first, uint32_t stride, F&& f) {
    const float r2max = r_max * r_max;
    const float r2prune = (r_max + slack) * (r_max + slack);
    const float rel[3] = {offset_in_cells(g, q, c, 0), offset_in_cells(g, q, c, 1), offset_in_cells(g, q, c, 2)};
    for (int dz = -1; dz <= 1; ++dz) {
        int cz;
        if (!neighbor_coord(g, 2, c[2], dz, cz)) continue;
        float ez = slab_gap2(g, 2, rel[2], dz);
        if (ez >= r2prune) continue;
        for (int dy = -1; dy <= 1; ++dy) {
            int cy;
            if (!neighbor_coord(g, 1, c[1], dy, cy)) continue;
            float ey = ez + slab_gap2(g, 1, rel[1], dy);
            if (ey >= r2prune) continue;
            for (int dx = -1; dx <= 1; ++dx) {
                int cx;
                if (!neighbor_coord(g, 0, c[0], dx, cx)) continue;
                if (ey + slab_gap2(g, 0, rel[0], dx) >= r2prune) continue;
                uint32_t cell = cell_index(g, cx, cy, cz);
                for_each_in_range(g, set.pos, set.start[cell] + first, set.end[cell], stride, q, r2max, f);
            }
        }
    }
}

template <class F>
PBF_HD inline void for_each_in_block(const GridGeometry& g, const CellRanges& set, const int c[3], Vec3 q,
                                     float r_max, F&& f) {
    for_each_in_block_strided(g, set, c, q, r_max, 0.0f, 0u, 1u, f);
}

// A team's searches of the block c +- 1, for the too-close tests of splitting and merging: any(team, q, r_max, slack,
// pred) votes whether pred(j, r, r2) holds for some particle j that for_each_in_block_strided(g, set, c, q, r_max,
// slack, ...) visits (the same cells, pruned the same way, and |r| < r_max). Splitting and merging ask only whether
// such a particle exists, so the order of the visits does not matter, and a search may stop at the first one.
// A team holds one block for several searches (a split decision's two, a merge pass's candidates in one cell).
// The generic team walks the cells at each search, its lanes striding over each cell's range.
template <class Team>
struct BlockSearch {
    const GridGeometry& g;
    const CellRanges& set;
    int c[3];
    PBF_HD BlockSearch(const Team&, const GridGeometry& grid, const CellRanges& ranges, const int cell[3])
        : g(grid), set(ranges), c{cell[0], cell[1], cell[2]} {}
    template <class Pred>
    PBF_HD bool any(const Team& team, Vec3 q, float r_max, float slack, Pred&& pred) const {
        bool hit = false;
        for_each_in_block_strided(g, set, c, q, r_max, slack, team.rank(), Team::kSize, [&](uint32_t j, Vec3 r, float r2) {
            if (pred(j, r, r2)) hit = true;
        });
        return team.any(hit);
    }
};

#if defined(__CUDACC__)
// A warp flattens the block: lane l < 27 holds the range of cell c + (l % 3, l / 3 % 3, l / 9) - 1, read once for
// all the team's searches. A search prunes each lane's cell against q, numbers the remaining particles by a scan
// over the lanes, and the lanes test 2 x 32 of them at a time (two positions in flight per lane), voting after
// each round, so that a search ends at the round that finds a particle.
template <>
struct BlockSearch<WarpTeam> : BlockSearch<SerialTeam> {
    uint32_t start = 0, count = 0;   // this lane's cell range (count 0: beyond a wall, or lane >= 27)
    PBF_HD BlockSearch(const WarpTeam& team, const GridGeometry& grid, const CellRanges& ranges, const int cell[3])
        : BlockSearch<SerialTeam>(SerialTeam{}, grid, ranges, cell) {
        const uint32_t lane = team.rank();
        if (lane >= 27) return;
        int cc[3];
        for (int a = 0; a < 3; ++a)
            if (!neighbor_coord(g, a, c[a], lane_offset(lane, a), cc[a])) return;
        const uint32_t k = cell_index(g, cc[0], cc[1], cc[2]);
        start = set.start[k];
        count = set.end[k] - start;
    }
    static PBF_HD int lane_offset(uint32_t lane, int a) {
        return int(a == 0 ? lane % 3u : (a == 1 ? lane / 3u % 3u : lane / 9u)) - 1;
    }
    template <class Pred>
    PBF_HD bool any(const WarpTeam& team, Vec3 q, float r_max, float slack, Pred&& pred) const {
#if defined(__CUDA_ARCH__)
        constexpr uint32_t kAll = 0xffffffffu;
        constexpr uint32_t kRound = 2;   // positions in flight per lane
        const uint32_t lane = team.rank();
        const float r2max = r_max * r_max;
        const float r2prune = (r_max + slack) * (r_max + slack);
        uint32_t cnt = 0;
        if (lane < 27) {
            float e = 0.0f;   // the squared gap to the cell, summed z, y, x as for_each_in_block_strided prunes
            for (int a = 2; a >= 0; --a) e = e + slab_gap2(g, a, offset_in_cells(g, q, c, a), lane_offset(lane, a));
            if (e < r2prune) cnt = count;
        }
        uint32_t incl = cnt;   // inclusive scan of the counts over the lanes
        for (uint32_t o = 1; o < 32u; o <<= 1) {
            const uint32_t t = __shfl_up_sync(kAll, incl, o);
            if (lane >= o) incl += t;
        }
        const uint32_t excl = incl - cnt;
        const uint32_t total = __shfl_sync(kAll, incl, 31);
        for (uint32_t base = 0; base < total; base += kRound * 32u) {
            uint32_t j[kRound];
            Float4 pj[kRound];
            for (uint32_t u = 0; u < kRound; ++u) {
                const uint32_t k = base + u * 32u + lane;
                uint32_t s = 0;   // the lane whose cell holds particle k: the first with incl > k
                for (uint32_t step = 16; step > 0; step >>= 1) {
                    const uint32_t v = __shfl_sync(kAll, incl, int(s + step - 1u));
                    if (v <= k) s += step;
                }
                j[u] = __shfl_sync(kAll, start, int(s)) + (k - __shfl_sync(kAll, excl, int(s)));
                if (k < total) pj[u] = set.pos[j[u]];
            }
            bool hit = false;
            for (uint32_t u = 0; u < kRound; ++u) {
                if (base + u * 32u + lane >= total) continue;
                Vec3 r = min_image(g, Vec3{q.x - pj[u].x, q.y - pj[u].y, q.z - pj[u].z});
                float r2 = dot(r, r);
                if (r2 < r2max && pred(j[u], r, r2)) hit = true;
            }
            if (team.any(hit)) return true;
        }
        return false;
#else
        return BlockSearch<SerialTeam>::any(SerialTeam{}, q, r_max, slack, pred);   // host pass of nvcc: never runs
#endif
    }
};
#endif

// Calls f(j, r_ij, r2) for every particle j of `set` with |r_ij| < r_max (r_ij = x_i - x_j,
// minimum image), including i itself when it belongs to the set (r2 = 0). r_max <= cell side.
template <class F>
PBF_HD inline void for_each_neighbor(const GridGeometry& g, const CellRanges& set, Vec3 xi, float r_max, F&& f) {
    int c[3] = {cell_coord(g, xi.x, 0), cell_coord(g, xi.y, 1), cell_coord(g, xi.z, 2)};
    for_each_in_block(g, set, c, xi, r_max, f);
}

}  // namespace pbf
