// The memory of the two backends (Open3D / PyTorch style): the device vectors and the execution policy of every
// Thrust call. The including backend file defines PBF_BACKEND_NS (and PBF_BACKEND_CUDA for nvcc), and the dispatch
// headers (parallel_for.h, counted_launch.h, reduce.h, sort.h, row_order.h, cell_walk.h, phase_clock.h) open that
// namespace; everything above them (the phases' launch code, *_launch.h) is written once against their functions.
//   dvec<T>, raw(v)             a device vector (Thrust) and its data pointer
//   exec()                      the execution policy of every Thrust call (sort, scan, fill, gather, copy_if)
//
// On the GPU every call is asynchronous on the default stream: exec() is Thrust's par_nosync with a caching
// allocator for the temporary storage of sorts, scans and reductions. Thrust's plain thrust::device policy
// synchronises the stream after every algorithm and allocates (cudaMalloc / cudaFree, both synchronising) the
// temporary storage of each one, so a step of ~100 launches waited for the GPU ~100 times. Only what the host
// must read waits now: the neighbour lists' size, the step's sums (one record, read once after the step with
// the timers; reduce_into writes a sum to device memory without a wait); the adaptive step's counts stay in device
// memory too (select_into, parallel_for_upto) and come with the step's sums. What made small scenes slow
// was mostly occupancy, not these waits (parallel_for.h; docs/benchmarks.md, "Launch overhead").
#pragma once
#ifndef PBF_BACKEND_NS
#error "device_memory.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <thrust/device_vector.h>
#include <thrust/execution_policy.h>

#include <cstddef>
#include <map>
#include <mutex>
#include <new>

#ifdef PBF_BACKEND_CUDA
#include <cub/util_namespace.cuh>
#include <cuda_runtime.h>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

#ifdef THRUST_CUB_WRAPPED_NAMESPACE
// Each backend wraps Thrust/CUB in its own namespace (set by CMake) so the two never collide.
namespace thrust = ::THRUST_CUB_WRAPPED_NAMESPACE::thrust;
#ifdef PBF_BACKEND_CUDA
namespace cub = ::THRUST_CUB_WRAPPED_NAMESPACE::cub;
#endif
#endif

template <class T>
using dvec = thrust::device_vector<T>;
template <class T>
T* raw(dvec<T>& v) { return thrust::raw_pointer_cast(v.data()); }
template <class T>
const T* raw(const dvec<T>& v) { return thrust::raw_pointer_cast(v.data()); }

#ifdef PBF_BACKEND_CUDA
// Temporary storage of Thrust's algorithms, kept for reuse: freed blocks go to a free list (by size) and the
// next request of at most that size takes one, so a step allocates nothing once the first steps have run.
// Every call runs on the default stream, so a block handed back before its kernel finished is only reused by
// work queued after that kernel. Shared by all solvers of the process (a mutex guards the lists).
class CachingTempAllocator {
public:
    using value_type = char;
    char* allocate(std::ptrdiff_t bytes) {
        std::lock_guard<std::mutex> lock(mutex_);
        auto it = free_.lower_bound(std::size_t(bytes));
        char* ptr = nullptr;
        std::size_t size = std::size_t(bytes);
        if (it != free_.end()) {
            ptr = it->second;
            size = it->first;
            free_.erase(it);
        } else if (cudaMalloc(reinterpret_cast<void**>(&ptr), size) != cudaSuccess) {
            cudaGetLastError();
            throw std::bad_alloc();
        }
        used_[ptr] = size;
        return ptr;
    }
    void deallocate(char* ptr, std::size_t) {
        std::lock_guard<std::mutex> lock(mutex_);
        auto it = used_.find(ptr);
        if (it == used_.end()) return;
        free_.emplace(it->second, ptr);
        used_.erase(it);
    }

private:
    std::mutex mutex_;
    std::multimap<std::size_t, char*> free_;
    std::map<char*, std::size_t> used_;
};

// The process's allocator; never destroyed (its blocks live as long as the CUDA context).
inline CachingTempAllocator& temp_allocator() {
    static CachingTempAllocator* a = new CachingTempAllocator();
    return *a;
}

inline auto exec() { return thrust::cuda::par_nosync(temp_allocator()); }
#else
inline auto exec() { return thrust::device; }
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
