// Launch code of the neighbour search (Ihmsen et al. 2011; grid.h): the solver's grid, and every step the
// sort of the particles by the cell of their predicted position x* with the cell ranges (uniform runs) or the
// nested sub-cell ranges and largest radii (adaptive runs, section 5.2).
#pragma once
#include <algorithm>

#include "device_memory.h"
#include "grid.h"
#include "kernel_launch.h"
#include "parallel_for.h"
#include "reduce.h"
#include "row_order.h"
#include "solver_data.h"
#include "sort.h"

namespace pbf {
namespace PBF_BACKEND_NS {

// Sort key of particle i: its cell (uniform runs) or its nested sub-cell cell * 8 + sub (adaptive runs, grid.h),
// with perm[i] = i (the sort's values); on the way, the ranges' start and end cleared (for item i < ranges): one pass
// over max(n, ranges) items.
struct ComputeKeys {
    GridGeometry g;
    const Float4* pos;
    uint32_t* keys;
    uint32_t* perm;
    bool nested;
    uint32_t n;
    uint32_t* range_start;
    uint32_t* range_end;
    uint32_t ranges;
    PBF_HD void operator()(uint32_t i) const {
        if (i < n) {
            Vec3 x = xyz(pos[i]);
            keys[i] = nested ? nested_key(g, x) : cell_key(g, x);
            perm[i] = i;
        }
        if (i < ranges) {
            range_start[i] = 0u;
            range_end[i] = 0u;
        }
    }
};

// Bits a sort key of the grid needs: keys run below num_cells (uniform) or num_cells x 8 (nested).
inline int sort_key_bits(const GridGeometry& g, bool nested) {
    const unsigned long long keys = (unsigned long long)g.num_cells() * (nested ? kSubCells : 1u);
    int bits = 1;
    while (bits < 32 && (1ull << bits) < keys) ++bits;
    return bits;
}

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
    // The radius falls with the level and the level with the mass, so the largest radius is the heaviest particle's:
    // one radius lookup per sub-cell (a lookup per particle kept the levels' radii in local memory).
    PBF_HD void operator()(uint32_t s) const {
        const uint32_t b = start[s], e = end[s];
        if (b == e) {
            radius[s] = 0.0f;
            return;
        }
        float m = 0.0f;
        for (uint32_t j = b; j < e; ++j) m = fmaxf(m, pos[j].w);
        radius[s] = radii.radius_of_mass(m);
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

// The solver's neighbour grid: cells of at least h0; adaptive runs need a multiple of 3 cells on periodic
// axes (the parallel merge colours cells modulo 3, adaptivity.h).
inline GridGeometry make_solver_grid(const Params& p) {
    bool periodic[3] = {p.periodic[0], p.periodic[1], p.periodic[2]};
    GridGeometry grid = make_grid_geometry(p.domain, periodic, p.h0);
    if (p.adaptive) {
        for (int a = 0; a < 3; ++a) {
            if (!grid.periodic[a]) continue;
            int n = (grid.dims[a] / 3) * 3;
            grid.dims[a] = n < 3 ? 3 : n;
            grid.cell[a] = grid.domain[a] / grid.dims[a];
            grid.inv_cell[a] = 1.0f / grid.cell[a];
        }
    }
    return grid;
}

// Cell (and sub-cell) range arrays of the grid.
inline void allocate_grid(SolverData& d) {
    d.cell_start.resize(d.grid.num_cells());
    d.cell_end.resize(d.grid.num_cells());
    if (d.p.adaptive) {
        d.sub_start.resize(std::size_t(d.grid.num_cells()) * kSubCells);
        d.sub_end.resize(std::size_t(d.grid.num_cells()) * kSubCells);
        d.sub_radius.resize(std::size_t(d.grid.num_cells()) * kSubCells);
        d.cell_radius.resize(d.grid.num_cells());
        d.colour_done.assign(d.grid.num_cells(), 0u);   // below every epoch of the merge walk (from 1 on)
        d.colour_epoch = 0;
    }
}

// Sort every particle array by the cell of pred (the nested key in adaptive runs) and mark the ranges.
inline void build_neighbor_grid(SolverData& d) {
    const bool nested = d.p.adaptive;
    dvec<uint32_t>& start = nested ? d.sub_start : d.cell_start;   // the ranges MarkCellRanges fills
    dvec<uint32_t>& end = nested ? d.sub_end : d.cell_end;
    const std::size_t ranges = start.size();
    parallel_for(std::max(d.n, ranges), ComputeKeys{d.grid, raw(d.pred), raw(d.keys), raw(d.perm), nested,
                                                    uint32_t(d.n), raw(start), raw(end), uint32_t(ranges)});
    sort_pairs(d.keys, d.perm, d.uint_tmp, d.perm_alt, d.n, sort_key_bits(d.grid, nested));
    d.permute_all(true);
    parallel_for(d.n, MarkCellRanges{raw(d.keys), uint32_t(d.n), raw(start), raw(end)});
    if (!nested) return;
    // Adaptive: each cell's range and largest radius from its sub-cells' ranges.
    parallel_for(d.sub_start.size(), SubCellRadius{d.radii, raw(d.pred), raw(d.sub_start), raw(d.sub_end),
                                                   raw(d.sub_radius)});
    parallel_for(d.cell_start.size(), CellFromSubCells{raw(d.sub_start), raw(d.sub_end), raw(d.sub_radius),
                                                       raw(d.cell_start), raw(d.cell_end), raw(d.cell_radius)});
}

#ifdef PBF_BACKEND_CUDA
constexpr bool kSlotMajorLists = true;    // a warp's 32 particles read slot k of their rows together
#else
constexpr bool kSlotMajorLists = false;   // a thread walks its particle's row
#endif

// The lists' size: their total (the statistics), and the rows widened to the longest plus an eighth, rounded up to 8,
// where one was longer than the width; a width that grew stays.
inline void record_list_size(SolverData& d, const ListSize& size) {
    d.list_entries = size.total;
    if (size.longest > d.nbr_width) d.nbr_width = (size.longest + size.longest / 8 + 7u) / 8u * 8u;
}

// After the step: the lists' size from the step's sums, where this step built lists.
inline void take_list_size(SolverData& d, const ListSize& size) {
    if (!d.list_size_pending) return;
    d.list_size_pending = false;
    record_list_size(d, size);
}

// Rows of the current width filled for this step's sorted particles (FillNeighbors, with pair_sum taken along);
// false where the lists had to be given up.
template <class Policy, class PairSum>
bool fill_neighbor_rows(SolverData& d, const PairSum& pair_sum) {
    const uint32_t n = uint32_t(d.n);
    const unsigned long long entries = (unsigned long long)(n) * d.nbr_width;
    if (entries > 0xffffffffull) {
        d.give_up_lists();
        return false;
    }
    if (entries > d.nbr_index.size()) {
        // Rows for every particle slot where they fit the index range: an adaptive run's particle count grows with
        // its splits between steps, and rows sized to this step's count were freed and allocated again (a device
        // synchronisation and a fill of the whole array) at every new largest count. Rows for this step's count
        // where the slots' do not fit in memory.
        const unsigned long long slots = (unsigned long long)std::max<std::size_t>(d.capacity, n) * d.nbr_width;
        const unsigned long long wants[2] = {slots <= 0xffffffffull ? slots : entries, entries};
        const int tries = wants[0] == entries ? 1 : 2;   // uniform runs: the slots are the particles
        bool done = false;
        for (int t = 0; t < tries && !done; ++t) {
            try {
                d.nbr_index.clear();
                d.nbr_index.shrink_to_fit();
                d.nbr_index.resize(std::size_t(wants[t]));
                done = true;
            } catch (const std::bad_alloc&) {
#ifdef PBF_BACKEND_CUDA
                cudaGetLastError();   // the failed allocation is not the step's error
#endif
            }
        }
        if (!done) {
            d.give_up_lists();
            return false;
        }
    }
    d.nbr_row = kSlotMajorLists ? 1u : d.nbr_width;
    d.nbr_slot = kSlotMajorLists ? n : 1u;
    const float skin = kNeighborSkin * d.p.h0;
    parallel_for(n, FillNeighbors<Policy, PairSum>{d.grid, d.fluid_ranges(d.pred), d.radii, d.p.h0, skin, d.nbr_width,
                                                   d.nbr_row, d.nbr_slot, raw(d.nbr_count), raw(d.nbr_index), pair_sum});
    return true;
}

// The list passes' thread order (launch.h: order_tiles_by_length) from the rows' lengths as built: a tile is
// permuted where that shortens its four warps by at least kRowOrderMinSaving candidates (measured on an H100 against
// 8 and 24: as fast on the adaptive scenes, and 8 slowed the 1M-particle `growing`; docs/performance.md, "Speed of the step",
// change 15). The rows narrowed after the density iterations keep this order (ordered again by their narrowed
// lengths, the passes after were no faster). CLOUDPBF_ROW_ORDER=0 in the environment keeps the index order (for
// comparisons); the CPU backend's threads walk chunks of particles and keep it always.
constexpr uint32_t kRowOrderMinSaving = 16;
inline void order_list_passes(SolverData& d) {
    d.pass_order_ready = false;
#ifdef PBF_BACKEND_CUDA
    static const bool enabled = !switched_off_in_environment("CLOUDPBF_ROW_ORDER");
    if (enabled && d.n > 0) {
        order_tiles_by_length(d.n, raw(d.nbr_count), kRowOrderMinSaving, raw(d.pass_order));
        d.pass_order_ready = true;
    }
#endif
}

// This step's neighbour lists (neighbor_list.h) from the sorted particles: one pass finds, counts and stores each
// particle's candidates in rows of the current width, and one reduction sums their total and the longest row into
// the step's sums, which the host reads after the step (take_list_size): the step does not wait for it. A row longer
// than the width is cut at the width, and that particle's passes search the cells for the rest of the step
// (CellRanges::listed: the same pairs in the same order); the rows are widened for the next step (to the longest
// plus an eighth, rounded up to 8: record_list_size). The run's first build does wait for the size and
// fills the rows again where one was cut, so that from the first step every particle reads its list (on the GPU the
// list and the cell search may round a pair's terms differently, and pair forces are exactly opposite only where
// both particles take the same path). Rows of n x width entries that would exceed 2^32 - 1 entries (about 75M
// particles at a width of 56) or cannot be allocated give the lists up for the rest of the run: the passes search
// the cells instead (the same neighbours, slower; d.lists_given_up, in the statistics).
// pair_sum: a sum the build takes along (FillNeighbors; NoPairSum: none). Returns whether it was taken: the lists
// were built.
template <class Policy, class PairSum>
bool build_neighbor_lists(SolverData& d, const PairSum& pair_sum) {
    d.lists_ready = false;
    if (!d.p.neighbor_list || d.lists_given_up || d.n == 0) return false;
    if (!fill_neighbor_rows<Policy>(d, pair_sum)) return false;
    const ListSizeOf count{raw(d.nbr_count)};
    if (!d.list_width_settled) {   // the run's first build: every row whole from the first step
        d.list_width_settled = true;
        const uint32_t width = d.nbr_width;
        record_list_size(d, reduce_over(d.n, count, ListSize{0ull, 0u}, ListSizeAdd{}));
        if (d.nbr_width != width && !fill_neighbor_rows<Policy>(d, pair_sum)) return false;
    }
    reduce_into(d.n, count, ListSize{0ull, 0u}, ListSizeAdd{}, &raw(d.step_sums)->list_size);
    order_list_passes(d);
    d.lists_ready = true;
    d.list_size_pending = true;
    return true;
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
