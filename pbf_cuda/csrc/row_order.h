// The order of the neighbour-list passes' threads (parallel_for_in_order in parallel_for.h):
//   order_tiles_by_length(n, length, min_saving, order)  that order: each block's tile longest item first (GPU)
#pragma once
#ifndef PBF_BACKEND_NS
#error "row_order.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <cstddef>
#include <cstdint>

#include "kernel_launch.h"

namespace pbf {
namespace PBF_BACKEND_NS {

#ifdef PBF_BACKEND_CUDA
// The order of the neighbour-list passes' threads (parallel_for_in_order): a warp runs as long as its longest row
// (the rounds of its longest particle's candidate loop), and in the sort's order a warp's 32 particles mix long and
// short rows where fine and coarse particles meet (cycling_adaptive at step 601: rows of 8 to 89 candidates, and the
// warps' longest rows sum to 1.16 times their mean rows; docs/benchmarks.md, "Rows of equal length", and
// benchmarks/row_balance.py). So each tile of kRowTile consecutive particles (one block of parallel_for_in_order,
// whose four warps share their lines in the SM's L1) is ordered by its particles' row length, longest first, in
// buckets of four candidates (kListBatch's rounds): order[base + rank] = i, where that shortens the tile's four
// warps by at least min_saving candidates in all. Elsewhere order[i] = i,
// and the warps read their rows' slots in whole lines: a permuted warp reads each slot of its rows from four lines
// instead of one, which cost the 1M-particle `growing` more than its rows' lengths saved with every tile permuted.
// Particles of a bucket take their ranks in the order their threads reach the shared counter: that decides which
// thread computes which particle, and every particle's result is the same to the bit.
constexpr uint32_t kRowTile = 128;
constexpr uint32_t kRowBuckets = 64;   // lengths 0-3, 4-7, .., 248 and more; the last bucket: items past n
__global__ void __launch_bounds__(kRowTile) order_tiles_kernel(uint32_t n, const uint32_t* length, uint32_t min_saving,
                                                              uint32_t* order) {
    __shared__ uint32_t first[kRowBuckets];   // items per bucket, then the bucket's first rank
    __shared__ uint32_t warp_longest[kRowTile / 32], sorted_longest[kRowTile / 32];
    wait_for_prior_grids();
    const uint32_t base = blockIdx.x * kRowTile, t = threadIdx.x, i = base + t;
    const uint32_t len = i < n ? length[i] : 0u;
    const uint32_t bucket = i < n ? kRowBuckets - 2u - min(len / 4u, kRowBuckets - 2u) : kRowBuckets - 1u;
    if (t < kRowBuckets) first[t] = 0u;
    if (t < kRowTile / 32) sorted_longest[t] = 0u;
    uint32_t longest = len;
    for (int o = 16; o > 0; o >>= 1) longest = max(longest, __shfl_xor_sync(0xffffffffu, longest, o));
    if (t % 32u == 0) warp_longest[t / 32u] = longest;
    __syncthreads();
    const uint32_t within = atomicAdd(&first[bucket], 1u);
    __syncthreads();
    if (t < 32) {   // exclusive scan of the buckets' counts: lane l holds buckets 2 l and 2 l + 1
        static_assert(kRowBuckets == 64, "one warp scans two buckets per lane");
        const uint32_t a = first[2 * t], b = first[2 * t + 1];
        uint32_t incl = a + b;
        for (uint32_t o = 1; o < 32u; o <<= 1) {
            const uint32_t v = __shfl_up_sync(0xffffffffu, incl, o);
            if (t >= o) incl += v;
        }
        first[2 * t] = incl - a - b;
        first[2 * t + 1] = incl - b;
    }
    __syncthreads();
    const uint32_t rank = first[bucket] + within;
    if (i < n) atomicMax(&sorted_longest[rank / 32u], len);
    __syncthreads();
    if (i >= n) return;
    uint32_t before = 0, after = 0;
    for (uint32_t w = 0; w < kRowTile / 32; ++w) {
        before += warp_longest[w];
        after += sorted_longest[w];
    }
    order[before >= after + min_saving ? base + rank : i] = i;
}
inline void order_tiles_by_length(std::size_t n, const uint32_t* length, uint32_t min_saving, uint32_t* order) {
    if (n == 0) return;
    launch("order_tiles", order_tiles_kernel, unsigned((n + kRowTile - 1) / kRowTile), kRowTile, uint32_t(n), length,
           min_saving, order);
}
#else
inline void order_tiles_by_length(std::size_t, const uint32_t*, uint32_t, uint32_t*) {}
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
