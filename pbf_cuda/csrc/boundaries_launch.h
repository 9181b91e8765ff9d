// Launch code of the boundaries (section 5.1; grid.h): the walls' boundary particles, sorted by cell once
// (they never move; the constraint kernels read each cell's boundary candidates from the table gathered here,
// SolverData::wall_neighbourhoods, and clamp fluid particles to the walls), and the commit x = x* that wraps
// positions into the box on periodic axes.
#pragma once
#include <algorithm>
#include <cmath>
#include <vector>

#include "device_memory.h"
#include "grid.h"
#include "parallel_for.h"
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

// The walls' table (grid.h, WallNeighbourhoods) from the boundary particles sorted by cell key: for each cell, the
// boundary particles of its 27 cells (wrapped on periodic axes, as for_each_in_block visits them: z, then y, then
// x offsets, each cell's particles in index order) that lie within `reach` of the cell's box. The reach is h0
// widened by a thousandth, so that a fluid particle rounded into the cell beside its own still finds every
// boundary particle within h0 (the kernels test |r| < h0 themselves).
inline void gather_wall_neighbourhoods(const GridGeometry& g, float h0, const std::vector<Float4>& pos,
                                       const std::vector<uint32_t>& keys, std::vector<uint32_t>& offset,
                                       std::vector<Float4>& table) {
    const uint32_t cells = g.num_cells();
    const std::size_t n = pos.size();
    std::vector<uint32_t> start(cells, 0u), end(cells, 0u);
    for (std::size_t i = 0; i < n; ++i) {
        if (i == 0 || keys[i - 1] != keys[i]) start[keys[i]] = uint32_t(i);
        if (i + 1 == n || keys[i + 1] != keys[i]) end[keys[i]] = uint32_t(i + 1);
    }
    // f(b) for each of the 27 cells around `cell` (wrapped on periodic axes, none past a wall), in the order
    // for_each_in_block visits them: z, then y, then x offsets.
    auto for_each_block_cell = [&](uint32_t cell, auto&& f) {
        uint32_t c[3];
        cell_coords(g, cell, c);
        auto step = [&](int a, int d) {
            int v;
            return neighbor_coord(g, a, int(c[a]), d, v) ? v : -1;
        };
        for (int dz = -1; dz <= 1; ++dz) {
            int z = step(2, dz);
            if (z < 0) continue;
            for (int dy = -1; dy <= 1; ++dy) {
                int y = step(1, dy);
                if (y < 0) continue;
                for (int dx = -1; dx <= 1; ++dx) {
                    int x = step(0, dx);
                    if (x >= 0) f(cell_index(g, x, y, z));
                }
            }
        }
    };
    std::vector<uint8_t> near(cells, 0u);   // cells with a boundary particle among their 27 (a symmetric relation)
    for (uint32_t b = 0; b < cells; ++b)
        if (start[b] != end[b]) for_each_block_cell(b, [&](uint32_t c) { near[c] = 1u; });
    const double reach = double(h0) * 1.001;
    offset.assign(std::size_t(cells) + 1, 0u);
    table.clear();
    for (uint32_t cell = 0; cell < cells; ++cell) {
        offset[cell] = uint32_t(table.size());
        if (!near[cell]) continue;
        uint32_t c[3];
        cell_coords(g, cell, c);
        // Squared distance (m^2) from p to this cell's box (minimum image on periodic axes).
        auto box_distance2 = [&](const Float4& p) {
            const double x[3] = {p.x, p.y, p.z};
            double d2 = 0.0;
            for (int a = 0; a < 3; ++a) {
                double half = 0.5 * double(g.cell[a]);
                double d = x[a] - (double(g.origin[a]) + (double(c[a]) + 0.5) * double(g.cell[a]));
                if (g.periodic[a]) d -= double(g.domain[a]) * std::nearbyint(d / double(g.domain[a]));
                double e = std::fabs(d) - half;
                if (e > 0.0) d2 += e * e;
            }
            return d2;
        };
        for_each_block_cell(cell, [&](uint32_t b) {
            for (uint32_t j = start[b]; j < end[b]; ++j)
                if (box_distance2(pos[j]) < reach * reach) table.push_back(pos[j]);
        });
    }
    offset[cells] = uint32_t(table.size());
}

// n boundary particles (level-0 mass) at pos3, with their temperature and vapor (nullptr: 0), sorted by cell,
// and the walls' table gathered from them.
inline void set_boundary_particles(SolverData& d, std::size_t n, const float* pos3, const float* temperature,
                                   const float* vapor) {
    d.nb = n;
    if (n == 0) {
        d.bpos.clear(); d.btemperature.clear(); d.bvapor.clear(); d.wall_offset.clear(); d.wall_pos.clear();
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
    std::vector<uint32_t> offset;
    std::vector<Float4> table;
    gather_wall_neighbourhoods(d.grid, d.p.h0, sp, sk, offset, table);
    d.wall_offset.assign(offset.begin(), offset.end());
    d.wall_pos.assign(table.begin(), table.end());
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
