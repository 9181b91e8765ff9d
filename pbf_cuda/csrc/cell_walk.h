// The 27-colour walk over the cells of a grid (the merge passes of adaptivity.h):
//   for_each_cell_by_colour(dims, periodic, done, epoch, f)  a team for each cell of a grid in 27 colours (c modulo
//                               3), colour after colour as far as the cells' neighbourhoods overlap (one launch on
//                               the GPU)
#pragma once
#ifndef PBF_BACKEND_NS
#error "cell_walk.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "common.h"
#include "kernel_launch.h"
#include "parallel_for.h"

#ifdef PBF_BACKEND_CUDA
#include <cuda/atomic>
#include <cuda_runtime.h>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

// ---- the cells of a grid in 27 colours --------------------------------------------------------------------------
// for_each_cell_by_colour(dims, periodic, done, epoch, f): one team per cell c = (x, y, z) of a grid of dims cells,
// colour by colour, colour (x % 3) + 3 (y % 3) + 9 (z % 3) in increasing order and, within a colour, its cells x
// fastest. turn = f.prepare(c, team) reads what no team changes (it may run before the earlier colours' teams have
// finished) and says whether the cell has work (turn.busy); f(turn, team) does it, touching only particles of the
// cells within 1 of c: two teams of one colour (3 cells apart) share none, and each team sees its cells as every
// earlier colour left them (the race-free merge of adaptivity.h).
// CPU: the colours one after the other, a parallel loop over each colour's cells.
// GPU: one launch instead of one per colour. The warps take the cells in that order, and a busy cell's team waits
// only for the teams of earlier colours within 2 cells, whose cells overlap its own: each team, busy or not, marks
// its cell done (done[cell] = epoch, a release store) once it has finished, and a waiting team reads the marks with
// acquire loads. Every team thus starts from the state the colour-by-colour walk gives it and writes what that walk
// writes. No team waits for a later one, and the grid holds no more warps than the GPU runs at once (each takes its
// cells in increasing order), so the walk always moves on. done: one entry per cell, never equal to a new epoch
// before the call. (Listing the busy cells first, so that the warps skip the others, made the walk slower: the
// listing's launches cost more than the idle cells' marks.)
struct CellColours {
    int dims[3];
    bool periodic[3];
    uint32_t first[28];   // the first item of each colour; first[27]: all cells
    static PBF_HD int count(int dim, int offset) { return dim > offset ? (dim - offset + 2) / 3 : 0; }
    CellColours(const int d[3], const bool p[3]) {
        for (int a = 0; a < 3; ++a) dims[a] = d[a], periodic[a] = p[a];
        first[0] = 0;
        for (int k = 0; k < 27; ++k)
            first[k + 1] = first[k] + uint32_t(count(dims[0], k % 3)) * uint32_t(count(dims[1], k / 3 % 3)) *
                                          uint32_t(count(dims[2], k / 9));
    }
    static PBF_HD int colour(const int c[3]) { return c[0] % 3 + 3 * (c[1] % 3) + 9 * (c[2] % 3); }
    // Item t (colour-major) as its colour and cell coordinates (x fastest within the colour).
    PBF_HD int cell(uint32_t t, int c[3]) const {
        int k = 0;
        while (t >= first[k + 1]) ++k;
        const uint32_t local = t - first[k];
        const uint32_t nx = uint32_t(count(dims[0], k % 3)), ny = uint32_t(count(dims[1], k / 3 % 3));
        c[0] = k % 3 + 3 * int(local % nx);
        c[1] = k / 3 % 3 + 3 * int(local / nx % ny);
        c[2] = k / 9 + 3 * int(local / (nx * ny));
        return k;
    }
    PBF_HD uint32_t index(const int c[3]) const {
        return uint32_t(c[0]) + uint32_t(dims[0]) * (uint32_t(c[1]) + uint32_t(dims[1]) * uint32_t(c[2]));
    }
};

#ifdef PBF_BACKEND_CUDA
template <class F>
__global__ void __launch_bounds__(128) colour_walk_kernel(CellColours w, uint32_t* done, uint32_t epoch, F f) {
    wait_for_prior_grids();
    const uint32_t lane = threadIdx.x % WarpTeam::kSize, warps = gridDim.x * (blockDim.x / WarpTeam::kSize);
    const WarpTeam team{lane};
    for (uint32_t t = (blockIdx.x * blockDim.x + threadIdx.x) / WarpTeam::kSize; t < w.first[27]; t += warps) {
        int c[3];
        const int k = w.cell(t, c);
        const auto turn = f.prepare(c, team);
        if (turn.busy) {
            // The cells within 2 of c (lane l: offsets l, l + 32, .. of the 5 x 5 x 5) of an earlier colour.
            for (uint32_t o = lane; o < 125u; o += 32u) {
                int n[3] = {c[0] + int(o % 5u) - 2, c[1] + int(o / 5u % 5u) - 2, c[2] + int(o / 25u) - 2};
                bool inside = true;
                for (int a = 0; a < 3; ++a) {
                    if (w.periodic[a]) n[a] = (n[a] + 2 * w.dims[a]) % w.dims[a];
                    else inside = inside && n[a] >= 0 && n[a] < w.dims[a];
                }
                if (!inside || CellColours::colour(n) >= k) continue;
                cuda::atomic_ref<uint32_t, cuda::thread_scope_device> mark(done[w.index(n)]);
                while (mark.load(cuda::memory_order_acquire) != epoch) __nanosleep(32);
            }
            __syncwarp();
            f(turn, team);
        }
        __syncwarp();
        __threadfence();   // each lane's writes before the mark
        __syncwarp();
        if (lane == 0)
            cuda::atomic_ref<uint32_t, cuda::thread_scope_device>(done[w.index(c)]).store(epoch, cuda::memory_order_release);
    }
}

template <class F>
void for_each_cell_by_colour(const int dims[3], const bool periodic[3], uint32_t* done, uint32_t epoch, const F& f) {
    const CellColours w(dims, periodic);
    const uint32_t cells = w.first[27];
    if (cells == 0) return;
    // No more blocks than run at once (the walk's progress rests on it; see above).
    int device = 0, sms = 0, per_sm = 0;
    cudaGetDevice(&device);
    cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device);
    cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, colour_walk_kernel<F>, 128, 0);
    const std::size_t resident = std::size_t(std::max(1, sms * per_sm));
    const std::size_t wanted = (std::size_t(cells) * WarpTeam::kSize + 127) / 128;
    launch("colour walk", colour_walk_kernel<F>, unsigned(std::min(wanted, resident)), 128u, w, done, epoch, f);
}
#else
template <class F>
struct ColourTeams {
    CellColours w;
    uint32_t first;
    F f;
    void operator()(uint32_t t) const {
        int c[3];
        w.cell(first + t, c);
        const auto turn = f.prepare(c, SerialTeam{});
        if (turn.busy) f(turn, SerialTeam{});
    }
};
template <class F>
void for_each_cell_by_colour(const int dims[3], const bool periodic[3], uint32_t*, uint32_t, const F& f) {
    const CellColours w(dims, periodic);
    for (int k = 0; k < 27; ++k) parallel_for(w.first[k + 1] - w.first[k], ColourTeams<F>{w, w.first[k], f});
}
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
