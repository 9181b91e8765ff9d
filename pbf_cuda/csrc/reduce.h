// The reductions of the dispatch layer:
//   reduce_over(n, f, init, op) op-reduction of f(i) over [0, n) (Thrust transform_reduce), read by the host
//   reduce_into(n, f, init, op, out[, then])  the same into *out in device memory: the host does not wait (one
//                               launch); then() runs once after the value is written
#pragma once
#ifndef PBF_BACKEND_NS
#error "reduce.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <thrust/iterator/counting_iterator.h>
#include <thrust/transform_reduce.h>

#include <cstddef>
#include <cstdint>
#include <cstring>

#include "common.h"
#include "device_memory.h"
#include "kernel_launch.h"

namespace pbf {
namespace PBF_BACKEND_NS {

// op-reduction of f(i) over i in [0, n), starting from init (the host waits for the value).
template <class T, class F, class Op>
T reduce_over(std::size_t n, const F& f, T init, Op op) {
    return thrust::transform_reduce(exec(), thrust::counting_iterator<uint32_t>(0),
                                    thrust::counting_iterator<uint32_t>(uint32_t(n)), f, init, op);
}

// The same reduction written to *out (device memory) without the host waiting for it. On the GPU one launch
// (reduce_kernel below) instead of CUB's DeviceReduce, which takes two at these sizes: a step makes ~15 reductions
// (the conjugate gradients' dots, the budget, the check), and the second launch of each cost more than its work.
// init must be op's identity (every sum here starts from 0, the check from its empty record). On the CPU the value
// itself.
#ifdef PBF_BACKEND_CUDA
// One-launch reduction in a fixed order, so the same value on every run (no floating-point atomics): each of at
// most kReduceBlocks blocks reduces its items (item i in block (i / 256) mod blocks, thread i mod 256, in index
// order), then its threads in a fixed tree (each warp's 32 by shuffles, then the block's 8 warps), writes its
// partial, and the block that finishes last (a counter in device memory, reset by that block) reduces the partials
// in the same tree. The number of blocks depends on n only.
constexpr unsigned kReduceThreads = 256;
constexpr unsigned kReduceBlocks = 1024;
// Items per thread the number of blocks aims at (up to kReduceBlocks): one item per thread (blocks = n / 256) made
// every block's tree and every block's turn at the counter cost more than its items; sixteen left too few threads
// to keep the loads in flight. Measured on an H100 (docs/performance.md, "Speed of the step", change 15): 4 against 1, the same
// states, 0.02 ms less per step at 483k particles and 0.01 ms at 1M; 16 was slower than 1.
constexpr unsigned kReduceItemsPerThread = 4;
__device__ unsigned int reduce_blocks_done = 0;

// A T read past the L1 cache (the partials other blocks wrote; their writes are fenced before the counter).
template <class T>
__device__ inline T load_from_l2(const T* p) {
    static_assert(sizeof(T) % 4 == 0, "reduce_into: the reduced type's size must be a multiple of 4 bytes");
    T v;
    const unsigned* src = reinterpret_cast<const unsigned*>(p);
    unsigned* dst = reinterpret_cast<unsigned*>(&v);
    for (unsigned k = 0; k < sizeof(T) / 4; ++k) dst[k] = __ldcg(src + k);
    return v;
}

// op over the 32 lanes of a warp in a fixed tree (lane l takes lane l + o, o = 16, 8, .., 1); the result in lane 0.
template <class T, class Op>
__device__ inline T reduce_warp(T v, Op op) {
    static_assert(sizeof(T) % 4 == 0, "reduce_into: the reduced type's size must be a multiple of 4 bytes");
    for (unsigned o = 16; o > 0; o >>= 1) {
        unsigned word[sizeof(T) / 4];
        memcpy(word, &v, sizeof(T));
        for (unsigned k = 0; k < sizeof(T) / 4; ++k) word[k] = __shfl_down_sync(0xffffffffu, word[k], o);
        T other;
        memcpy(&other, word, sizeof(T));
        v = op(v, other);
    }
    return v;
}

// op over the kReduceThreads values v of a block (every thread calls it); the result in thread 0. s: shared memory
// for one value per warp.
template <class T, class Op>
__device__ inline T reduce_block(T v, T init, Op op, T* s) {
    const unsigned lane = threadIdx.x % 32u, warp = threadIdx.x / 32u;
    v = reduce_warp(v, op);
    if (lane == 0) s[warp] = v;
    __syncthreads();
    if (warp == 0) v = reduce_warp(lane < kReduceThreads / 32u ? s[lane] : init, op);
    return v;
}

template <class F, class T, class Op, class Then>
__global__ void __launch_bounds__(kReduceThreads) reduce_kernel(uint32_t n, F f, T init, Op op, T* partial, T* out,
                                                                Then then) {
    __shared__ alignas(T) unsigned char storage[sizeof(T) * (kReduceThreads / 32u)];
    __shared__ bool last;
    T* s = reinterpret_cast<T*>(storage);
    wait_for_prior_grids();
    const unsigned t = threadIdx.x;
    T acc = init;
#pragma unroll 4
    for (std::size_t i = std::size_t(blockIdx.x) * kReduceThreads + t; i < n; i += std::size_t(gridDim.x) * kReduceThreads)
        acc = op(acc, f(uint32_t(i)));
    acc = reduce_block(acc, init, op, s);
    if (t == 0) {
        partial[blockIdx.x] = acc;
        __threadfence();
        last = atomicAdd(&reduce_blocks_done, 1u) == gridDim.x - 1;
    }
    __syncthreads();
    if (!last) return;
    __threadfence();
    // The partials in the order of a loop over b = t, t + 256, ...; for small T (the sums and dot products of the
    // step) all loads are issued before the first op, so the last block waits for L2 once, not once per row.
    static_assert(kReduceBlocks % kReduceThreads == 0, "reduce_kernel: whole rows of partials");
    constexpr unsigned kRows = kReduceBlocks / kReduceThreads;
    acc = init;
    if constexpr (sizeof(T) <= 16) {
        T row[kRows];
#pragma unroll
        for (unsigned k = 0; k < kRows; ++k)
            if (t + k * kReduceThreads < gridDim.x) row[k] = load_from_l2(partial + t + k * kReduceThreads);
#pragma unroll
        for (unsigned k = 0; k < kRows; ++k)
            if (t + k * kReduceThreads < gridDim.x) acc = op(acc, row[k]);
    } else {
        for (unsigned b = t; b < gridDim.x; b += kReduceThreads) acc = op(acc, load_from_l2(partial + b));
    }
    acc = reduce_block(acc, init, op, s);
    if (t == 0) {
        *out = acc;
        reduce_blocks_done = 0;
        then();
    }
}
#endif

// Nothing to do after a reduction (reduce_into's then).
struct NoFinish {
    PBF_HD void operator()() const {}
};

// then(): run once after *out is written, by the thread that wrote it (scalar work on the sum, such as a solver's
// step size), in place of a run_once launch after the reduction.
template <class T, class F, class Op, class Then = NoFinish>
void reduce_into(std::size_t n, const F& f, T init, Op op, T* out, const Then& then = Then{}) {
#ifdef PBF_BACKEND_CUDA
    const std::size_t per_block = std::size_t(kReduceThreads) * kReduceItemsPerThread;
    const std::size_t wanted = (n + per_block - 1) / per_block;
    const unsigned blocks = unsigned(wanted < 1 ? 1 : (wanted > kReduceBlocks ? kReduceBlocks : wanted));
    const std::size_t bytes = sizeof(T) * blocks;
    char* tmp = temp_allocator().allocate(std::ptrdiff_t(bytes));
    launch("reduce_into", reduce_kernel<F, T, Op, Then>, blocks, kReduceThreads, uint32_t(n), f, init, op,
           reinterpret_cast<T*>(tmp), out, then);
    temp_allocator().deallocate(tmp, bytes);
#else
    *out = reduce_over(n, f, init, op);
    then();
#endif
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
