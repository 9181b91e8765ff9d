// Per-step neighbour lists (Verlet lists with a skin; Verlet 1967, as SPH codes such as SPlisHSPlasH keep them):
// right after the particles are sorted by cell, each particle's candidates within (support + skin) are found once
// with the policy's cell search (kernel_policy.h: for_each_candidate) and stored in the order the search visits
// them, in compressed rows (nbr_offset, nbr_index). The step's ~20 neighbour passes (density iterations, XSPH and
// vorticity, smoothing, the velocity projection's conjugate gradients) then read each particle's ~45 candidates
// instead of scanning the ~200 particles of 27 cells (or the nested sub-cells of adaptive runs) every time.
//
// The passes keep the search's own test (|r| below the pair's support) on the positions they see, so the lists
// only change which particles are looked at. Within a step positions move only by the density constraint's
// corrections (a small fraction of a spacing), less than half the skin, so a pass finds the pairs the cell search
// would find, in the same order: results agree with the cell search to rounding (tests/test_solver_core.py).
// Before each density iteration after the first, and after the last, the step checks that no particle moved half
// a skin or more since the lists were built. The first time one did in a step, the lists are built again from the
// moved positions, as Verlet lists are kept; a second time, the step's remaining passes use the cell search itself
// (building again at every check made the 831k-particle `growing` 47% slower in its convective phase, H100).
// Either way the passes see exactly the pairs the cell search sees. pbf.neighbor_list = false keeps the cell search, for sizes whose lists
// would not fit in memory (pbf_cuda/memory.py counts them).
#pragma once
#include "common.h"
#include "grid.h"
#include "kernel_policy.h"

namespace pbf {

// Skin of the lists as a fraction of the level-0 kernel radius h0. In `growing` (65k particles, 300 steps of
// convection, CPU) the density iterations moved a few particles per step by more than half of it (0.05 h0), none
// by 0.1 h0. A wider skin costs every pass: with 0.2 h0 the 831k-particle `growing` step took 10.1 ms on an H100
// against 7.9 ms.
constexpr float kNeighborSkin = 0.1f;

// count[i] = candidates of particle i.
template <class Policy>
struct CountNeighbors {
    GridGeometry grid;
    CellRanges fluid;
    float h0, skin;
    uint32_t* count;
    PBF_HD void operator()(uint32_t i) const {
        uint32_t c = 0;
        Policy::for_each_candidate(grid, fluid, i, xyz(fluid.pos[i]), h0, skin, [&](uint32_t, Vec3, float) { ++c; });
        count[i] = c;
    }
};

// index[offset[i] ..] = the candidates of particle i, in search order.
template <class Policy>
struct FillNeighbors {
    GridGeometry grid;
    CellRanges fluid;
    float h0, skin;
    const uint32_t* offset;
    uint32_t* index;
    PBF_HD void operator()(uint32_t i) const {
        uint32_t k = offset[i];
        Policy::for_each_candidate(grid, fluid, i, xyz(fluid.pos[i]), h0, skin,
                                   [&](uint32_t j, Vec3, float) { index[k++] = j; });
    }
};

// Squared distance (m^2) particle i moved since the lists were built at `built`.
struct MovedSince {
    const Float4* pos;
    const Float4* built;
    PBF_HD float operator()(uint32_t i) const {
        Vec3 d = xyz(pos[i]) - xyz(built[i]);
        return dot(d, d);
    }
};

struct MaxFloat {
    PBF_HD float operator()(float a, float b) const { return a > b ? a : b; }
};

}  // namespace pbf
