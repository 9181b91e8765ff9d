// The launches whose count of items an earlier launch wrote to device memory:
//   parallel_for_upto(max_n, count, f), parallel_for_teams_upto(max_n, count, f)  those for i in [0, *count),
//                               the count in device memory (at most max_n): the host does not wait for it
//   select_into(n, pred, out, count)  the indices i in [0, n) with pred(i), in order, and their count in device memory
#pragma once
#ifndef PBF_BACKEND_NS
#error "counted_launch.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <thrust/copy.h>
#include <thrust/iterator/counting_iterator.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>

#include "common.h"
#include "device_memory.h"
#include "kernel_launch.h"
#include "parallel_for.h"

#ifdef PBF_BACKEND_CUDA
#include <cub/device/device_select.cuh>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

#ifdef PBF_BACKEND_CUDA
// The counted launches (parallel_for_upto, parallel_for_teams_upto below) walk their items in strides over at most
// this many blocks: enough to fill the GPU; the items are few where the count is not known on the host (the adaptive
// step's split candidates).
constexpr unsigned kCountedBlocks = 2048;

template <class F>
__global__ void PBF_LAUNCH_BOUNDS for_each_counted_kernel(const uint32_t* count, F f) {
    wait_for_prior_grids();
    const uint32_t n = *count;
    for (uint32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x) f(i);
}
template <class F>
void parallel_for_upto(std::size_t max_n, const uint32_t* count, const F& f) {
    if (max_n == 0) return;
    const unsigned block = 128;
    const std::size_t wanted = (max_n + block - 1) / block;
    launch("parallel_for_upto", for_each_counted_kernel<F>, unsigned(std::min<std::size_t>(wanted, kCountedBlocks)),
           block, count, f);
}

template <class F>
__global__ void team_counted_kernel(const uint32_t* count, F f) {
    wait_for_prior_grids();
    const uint32_t n = *count, teams = gridDim.x * (blockDim.x / WarpTeam::kSize);
    for (uint32_t t = (blockIdx.x * blockDim.x + threadIdx.x) / WarpTeam::kSize; t < n; t += teams)
        f(t, WarpTeam{threadIdx.x % WarpTeam::kSize});   // whole warps walk together: t is the warp's
}
template <class F>
void parallel_for_teams_upto(std::size_t max_n, const uint32_t* count, const F& f) {
    if (max_n == 0) return;
    const unsigned block = 128;
    const std::size_t wanted = (max_n * WarpTeam::kSize + block - 1) / block;
    launch("team kernel (counted)", team_counted_kernel<F>, unsigned(std::min<std::size_t>(wanted, kCountedBlocks)),
           block, count, f);
}

// out[0, *count) = the indices i in [0, n) with pred(i), in index order; *count in device memory, so the host does
// not wait (CUB's DeviceSelect; Thrust's copy_if returns the count to the host, which waits for it).
template <class Pred>
void select_into(std::size_t n, const Pred& pred, uint32_t* out, uint32_t* count) {
    cudaError_t err = cudaSuccess;
    if (n == 0) {
        err = cudaMemsetAsync(count, 0, sizeof(uint32_t), cudaStream_t(0));
    } else {
        thrust::counting_iterator<uint32_t> first(0);
        std::size_t bytes = 0;
        err = cub::DeviceSelect::If(nullptr, bytes, first, out, count, int64_t(n), pred, cudaStream_t(0));
        if (err == cudaSuccess) {
            char* tmp = temp_allocator().allocate(std::ptrdiff_t(bytes));
            err = cub::DeviceSelect::If(tmp, bytes, first, out, count, int64_t(n), pred, cudaStream_t(0));
            temp_allocator().deallocate(tmp, bytes);
        }
    }
    if (err != cudaSuccess) throw std::runtime_error(std::string("select_into: ") + cudaGetErrorString(err));
}
#else
// The CPU's device memory is the host's: the counts are read where they are.
template <class F>
void parallel_for_upto(std::size_t, const uint32_t* count, const F& f) { parallel_for(*count, f); }
template <class F>
void parallel_for_teams_upto(std::size_t, const uint32_t* count, const F& f) { parallel_for_teams(*count, f); }
template <class Pred>
void select_into(std::size_t n, const Pred& pred, uint32_t* out, uint32_t* count) {
    uint32_t* end = thrust::copy_if(exec(), thrust::counting_iterator<uint32_t>(0),
                                    thrust::counting_iterator<uint32_t>(uint32_t(n)), out, pred);
    *count = uint32_t(end - out);
}
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
