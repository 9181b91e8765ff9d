// Launch code of the boundaries (section 5.1; grid.h): the walls' boundary particles, sorted by cell once
// (they never move; the constraint kernels read them through SolverData::boundary_ranges and clamp fluid
// particles to the walls), and the commit x = x* that wraps positions into the box on periodic axes.
#pragma once
#include <algorithm>
#include <vector>

#include "grid.h"
#include "grid_launch.h"
#include "solver_data.h"

namespace pbf {
namespace PBF_BACKEND_NS {

struct Commit {
    GridGeometry g;
    const Float4* pred;
    Float4* pos;
    PBF_HD void operator()(uint32_t i) const {
        Float4 p = pred[i];
        pos[i] = make_float4(wrap_position(g, xyz(p)), p.w);
    }
};

// x = x*, wrapped into [0, L) on periodic axes (from == to: wrap in place).
inline void commit_positions(SolverData& d, const dvec<Float4>& from, dvec<Float4>& to) {
    parallel_for(d.n, Commit{d.grid, raw(from), raw(to)});
}

// n boundary particles (level-0 mass) at pos3, with their temperature and vapor (nullptr: 0), sorted by cell.
inline void set_boundary_particles(SolverData& d, std::size_t n, const float* pos3, const float* temperature,
                                   const float* vapor) {
    d.nb = n;
    if (n == 0) {
        d.bpos.clear(); d.btemperature.clear(); d.bvapor.clear(); d.bstart.clear(); d.bend.clear();
        return;
    }
    std::vector<Float4> hp(n);
    for (std::size_t i = 0; i < n; ++i)
        hp[i] = Float4{pos3[3 * i], pos3[3 * i + 1], pos3[3 * i + 2], d.p.mass0};
    std::vector<uint32_t> keys(n), order(n);
    for (std::size_t i = 0; i < n; ++i) { keys[i] = cell_key(d.grid, xyz(hp[i])); order[i] = uint32_t(i); }
    std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return keys[a] < keys[b]; });
    std::vector<Float4> sp(n);
    std::vector<float> st(n, 0.0f), sv(n, 0.0f);
    std::vector<uint32_t> sk(n);
    for (std::size_t i = 0; i < n; ++i) {
        sp[i] = hp[order[i]];
        sk[i] = keys[order[i]];
        if (temperature) st[i] = temperature[order[i]];
        if (vapor) sv[i] = vapor[order[i]];
    }
    d.bpos.assign(sp.begin(), sp.end());
    d.btemperature.assign(st.begin(), st.end());
    d.bvapor.assign(sv.begin(), sv.end());
    d.bcloud.assign(n, 0.0f);
    dvec<uint32_t> dkeys(sk.begin(), sk.end());
    d.bstart.assign(d.grid.num_cells(), 0u);
    d.bend.assign(d.grid.num_cells(), 0u);
    parallel_for(n, MarkCellRanges{raw(dkeys), uint32_t(n), raw(d.bstart), raw(d.bend)});
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
