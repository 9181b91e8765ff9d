// Per-step neighbour lists (Verlet lists with a skin; Verlet 1967, as SPH codes such as SPlisHSPlasH keep them):
// right after the particles are sorted by cell, each particle's candidates within (support + skin) are found once
// with the policy's cell search (kernel_policy.h: for_each_candidate) and stored in the order the search visits
// them. The step's ~20 neighbour passes (density iterations, XSPH and vorticity, smoothing, the velocity
// projection's conjugate gradients) then read each particle's ~45 candidates instead of scanning the ~200
// particles of 27 cells (or the nested sub-cells of adaptive runs) every time.
//
// Layout: rows of a fixed width W (ELLPACK, as GPU sparse-matrix formats keep them), so one pass finds, counts
// and stores the candidates (FillNeighbors) without a counting pass and a scan before it. On the GPU the rows
// are stored slot-major (candidate k of particle i at k n + i): the 32 lanes of a warp, 32 consecutive
// particles, read and write slot k of their rows in one coalesced transaction. On the CPU they are row-major
// (i W + k): one thread walks one particle's row through the cache. W is the longest row a build found (plus an
// eighth, rounded up to 8). A row longer than W is cut at W, and that particle's passes search the cells for the
// rest of the step (CellRanges::listed); the rows are widened for the next step (grid_launch.h). So the step never
// waits for the lists' size: it is read with the step's other sums after the step.
// Measured against the compressed rows with a counting pass that they replace: docs/benchmarks.md.
//
// The passes keep the search's own test (|r| below the pair's support) on the positions they see, so the lists
// only change which particles are looked at. Within a step positions move only by the density constraint's
// corrections, so a pass finds the pairs the cell search would find, in the same order, unless two particles
// closed in on each other by more than the skin during the step's density iterations: then a pair that enters
// the support's outermost shell is left out, where the kernels and their gradients are nearly zero (the cell
// search, which reads the cells as sorted, leaves out pairs in the same way when a particle crosses into a cell
// outside its neighbour's 27). Measured: bitwise equal to the cell search over 25 steps of four scenes on the CPU
// (tests/test_solver_core.py); from a start jittered by 0.3 spacings, where the first step's iterations move
// particles 0.2 kernel radii, within 1.4e-3 of a spacing after one step and 1e-2 after ten, with the same mean
// density error to 4 digits (the dam break, CPU).
// Making them exact cost more than they save: checking the displacement before every density iteration and
// building the lists again found some particle past half the skin in most steps of the 831k-particle `growing`
// once convection is under way (a skin of 0.1 h0; in 65k-particle runs a few particles per step move more than
// 0.05 h0, none more than 0.1 h0), which made its steps 14.8 ms against 13.5 ms for the cell search and 14.3 ms
// before the lists (H100, eae6434); a skin of 0.2 h0 made every pass dearer (831k particles: 10.1 ms against
// 7.9). pbf.neighbor_list = false keeps the cell search, for sizes whose lists would not fit in memory
// (pbf_cuda/memory.py counts them).
#pragma once
#include "common.h"
#include "grid.h"
#include "kernel_policy.h"

namespace pbf {

// Skin of the lists as a fraction of the level-0 kernel radius h0.
constexpr float kNeighborSkin = 0.1f;

// f(j, r, r2, m_j, h_j) for the candidates of particle i (kernel radius hi): the policy's search widened by the skin,
// and in adaptive runs only the pairs within their own support max(h_i, h_j) plus the skin. The nested search's cell
// mode tests a whole cell's pairs against the cell's largest radius, so without this a level-3 particle in a cell
// that holds one level-0 particle would list every particle within h0 (8 times the volume its pairs need) and every
// pass would read them. The test is symmetric in i and j, so j is in i's list exactly when i is in j's.
template <class Policy, class F>
PBF_HD inline void for_each_list_candidate(const GridGeometry& grid, const CellRanges& fluid, const LevelRadii& radii,
                                           float h0, float skin, uint32_t i, Vec3 xi, float hi, F&& f) {
    Policy::for_each_candidate(grid, fluid, i, xi, h0, skin, [&](uint32_t j, Vec3 r, float r2) {
        const float mj = fluid.pos[j].w;
        const float hj = Policy::radius(radii, h0, mj);
        if (Policy::within_support(r2, hi, hj, skin)) f(j, r, r2, mj, hj);
    });
}

// The sum (widened so that it cannot wrap) and the largest of the particles' candidate counts: the lists' size,
// summed after their build into the step's sums (grid_launch.h: build_neighbor_lists).
struct ListSize {
    unsigned long long total;
    uint32_t longest;
};
struct ListSizeOf {
    const uint32_t* count;
    PBF_HD ListSize operator()(uint32_t i) const { return ListSize{count[i], count[i]}; }
};
struct ListSizeAdd {
    PBF_HD ListSize operator()(const ListSize& a, const ListSize& b) const {
        return ListSize{a.total + b.total, a.longest > b.longest ? a.longest : b.longest};
    }
};

// A sum over the pairs that the lists' build takes along (FillNeighbors): Sums, add(sums, i, j, r, r2, h_i, m_j, h_j)
// for each candidate within its pair's support (i itself included, r2 = 0), in the order the row stores them, which
// is the order in which a list pass would visit them (kernel_policy.h: for_each_fluid_neighbor), then
// finish(sums, i, x_i, m_i, h_i). NoPairSum: none (the plain build).
struct NoPairSum {
    struct Sums {};
    PBF_HD void add(Sums&, uint32_t, uint32_t, Vec3, float, float, float, float) const {}
    PBF_HD void finish(Sums&, uint32_t, Vec3, float, float) const {}
};

// count[i] = the candidates of particle i; the first `width` of them stored in its row, in search order; the pair sum
// taken along, where there is one.
template <class Policy, class PairSum = NoPairSum>
struct FillNeighbors {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    float h0, skin;
    uint32_t width, row, slot;   // row i starts at index + i row; slot k is k slot further
    uint32_t* count;
    uint32_t* index;
    PairSum pair_sum;
    PBF_HD void operator()(uint32_t i) const {
        uint32_t c = 0;
        uint32_t* out = index + std::size_t(i) * row;
        const Float4 pi = fluid.pos[i];
        const float hi = Policy::radius(radii, h0, pi.w);
        typename PairSum::Sums sums{};
        for_each_list_candidate<Policy>(grid, fluid, radii, h0, skin, i, xyz(pi), hi,
                                        [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (c < width) out[std::size_t(c) * slot] = j;
            ++c;
            if (within_radius(r2, Policy::support(hi, hj), 0.0f)) pair_sum.add(sums, i, j, r, r2, hi, mj, hj);
        });
        pair_sum.finish(sums, i, xyz(pi), pi.w, hi);
        count[i] = c;
    }
};

// Particle i's row narrowed, in place and in order, to the candidates within their pair's support at the positions
// the kernel sees (the step's final x*, after the density iterations): every later pass of the step (vorticity
// confinement, smoothing, the projection's conjugate gradients) then reads only the pairs it sums, in the order it
// summed them before, so its results are bitwise the same. A lattice neighbourhood has (1 + skin)^3 - 1 = 33%
// more candidates than pairs. A pass over the pairs at x* takes the narrowing along (the XSPH pass,
// ViscosityVorticity in pbf_constraints.h): for_each_fluid_neighbor calls it for exactly the pairs kept, i itself
// included, and row slot `kept` is never ahead of the slots the pass has read.
struct RowNarrowing {
    uint32_t* count = nullptr;   // nullptr: the pass does not narrow
    uint32_t* index = nullptr;
    uint32_t row = 0, slot = 0;  // the lists' layout (CellRanges::candidate)
    struct Cursor {
        uint32_t* row;
        uint32_t kept;
    };
    PBF_HD Cursor begin(uint32_t i) const { return Cursor{index + std::size_t(i) * row, 0}; }
    PBF_HD void keep(Cursor& c, uint32_t j) const { c.row[std::size_t(c.kept++) * slot] = j; }
    PBF_HD void finish(uint32_t i, const Cursor& c) const { count[i] = c.kept; }
};

// The narrowing as a pass of its own, where no XSPH pass runs to take it along.
template <class Policy>
struct NarrowNeighbors {
    GridGeometry grid;
    CellRanges fluid;   // with the lists
    LevelRadii radii;
    float h0;
    RowNarrowing narrowing;
    PBF_HD void operator()(uint32_t i) const {
        if (!fluid.listed(i)) return;   // a row cut at the width stays as it is: its passes search the cells
        RowNarrowing::Cursor c = narrowing.begin(i);
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xyz(fluid.pos[i]),
                                        [&](uint32_t j, Vec3, float, float, float) { narrowing.keep(c, j); });
        narrowing.finish(i, c);
    }
};

}  // namespace pbf
