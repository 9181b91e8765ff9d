// The plain launches of the dispatch layer: how a kernel functor runs over n items.
//   parallel_for(n, f)          f(i) for i in [0, n): one CUDA thread per item, or an OpenMP loop
//   parallel_for_teams(n, f)    f(t, team) with one team per item: a warp on the GPU, a thread on the CPU
//   parallel_for_in_order(n, order, f)  f(order[t]) on thread t (GPU; the CPU keeps the index order;
//                               the order: row_order.h)
//   run_once(f)                 f() once: a one-thread kernel on the GPU (scalar work on device memory)
#pragma once
#ifndef PBF_BACKEND_NS
#error "parallel_for.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <cstddef>
#include <cstdint>

#include "common.h"
#include "kernel_launch.h"

namespace pbf {
namespace PBF_BACKEND_NS {

#ifdef PBF_BACKEND_CUDA
template <class F>
__global__ void PBF_LAUNCH_BOUNDS for_each_kernel(uint32_t n, F f) {
    wait_for_prior_grids();
    uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i < n) f(i);
}

// One thread per item in blocks of 128. Thrust's for_each gives each thread two items in blocks of 256: at
// 100k particles that is ~200 blocks for 132 SMs (17% of the warps an SM can hold, measured with Nsight
// Compute on an H100), and each thread walks two neighbourhoods one after the other. The neighbour loops are
// latency-bound, so a small scene ran at a third of the per-particle speed of a large one.
template <class F>
void parallel_for(std::size_t n, const F& f) {
    if (n == 0) return;
    const unsigned block = 128;
    launch("parallel_for", for_each_kernel<F>, unsigned((n + block - 1) / block), block, uint32_t(n), f);
}

template <class F>
__global__ void PBF_LAUNCH_BOUNDS for_each_in_order_kernel(uint32_t n, const uint32_t* order, F f) {
    wait_for_prior_grids();
    uint32_t t = blockIdx.x * blockDim.x + threadIdx.x;
    if (t < n) f(order[t]);
}

// f(order[t]) for t in [0, n), order a permutation of [0, n) (nullptr: parallel_for): which thread takes which item,
// nothing else; every item is still computed by one thread from the same inputs, so the results are those of
// parallel_for to the bit.
template <class F>
void parallel_for_in_order(std::size_t n, const uint32_t* order, const F& f) {
    if (!order) return parallel_for(n, f);
    if (n == 0) return;
    const unsigned block = 128;
    launch("parallel_for_in_order", for_each_in_order_kernel<F>, unsigned((n + block - 1) / block), block, uint32_t(n),
           order, f);
}
#else
// Chunks of 512 items handed out as threads come free (OpenMP's dynamic schedule). Thrust's for_each splits the
// range into one equal part per thread; a particle's cost follows its neighbourhood (a full one in the bulk, half
// of one at a free surface or a wall), so with 2 threads one waited for the other at the end of every pass.
constexpr long long kCpuChunk = 512;
template <class F>
void parallel_for(std::size_t n, const F& f) {
    if (n == 0) return;
    const long long m = (long long)n;
#pragma omp parallel for schedule(dynamic, kCpuChunk)
    for (long long i = 0; i < m; ++i) f(uint32_t(i));
}
// A thread walks its chunk's items one after the other: the order of items within a team does not matter here.
template <class F>
void parallel_for_in_order(std::size_t n, const uint32_t*, const F& f) { parallel_for(n, f); }
#endif

// f(t, team) for t in [0, n): one team per item (common.h), a warp on the GPU, a thread on the CPU.
#ifdef PBF_BACKEND_CUDA
template <class F>
__global__ void team_kernel(uint32_t n, F f) {
    wait_for_prior_grids();
    uint32_t t = (blockIdx.x * blockDim.x + threadIdx.x) / WarpTeam::kSize;
    if (t >= n) return;  // whole warps leave together: blockDim is a multiple of the warp size
    f(t, WarpTeam{threadIdx.x % WarpTeam::kSize});
}

template <class F>
void parallel_for_teams(std::size_t n, const F& f) {
    if (n == 0) return;
    const unsigned block = 128;
    std::size_t threads = n * WarpTeam::kSize;
    launch("team kernel", team_kernel<F>, unsigned((threads + block - 1) / block), block, uint32_t(n), f);
}
#else
template <class F>
struct AsSerialTeam {
    F f;
    void operator()(uint32_t t) const { f(t, SerialTeam{}); }
};

template <class F>
void parallel_for_teams(std::size_t n, const F& f) {
    parallel_for(n, AsSerialTeam<F>{f});
}
#endif

#ifdef PBF_BACKEND_CUDA
template <class F>
__global__ void once_kernel(F f) {
    wait_for_prior_grids();
    f();
}

template <class F>
void run_once(const F& f) { launch("run_once", once_kernel<F>, 1, 1, f); }
#else
template <class F>
void run_once(const F& f) { f(); }
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
