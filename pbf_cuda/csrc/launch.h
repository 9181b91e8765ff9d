// The dispatch layer of the two backends (Open3D / PyTorch style): how a kernel functor runs over n items,
// the device vectors, and the phase timers. Everything above it (the phases' launch code, *_launch.h) is
// written once against these few functions; the including backend file defines PBF_BACKEND_NS (and
// PBF_BACKEND_CUDA for nvcc), and this header opens that namespace:
//   parallel_for(n, f)          f(i) for i in [0, n): one CUDA thread per item, or a Thrust for_each (OpenMP loop)
//   parallel_for_teams(n, f)    f(t, team) with one team per item: a warp on the GPU, a thread on the CPU
//   parallel_for_in_order(n, order, f)  f(order[t]) on thread t (GPU; the CPU keeps the index order), and
//   order_tiles_by_length(n, length, min_saving, order)  that order: each block's tile longest item first (GPU)
//   parallel_for_upto(max_n, count, f), parallel_for_teams_upto(max_n, count, f)  the same for i in [0, *count),
//                               the count in device memory (at most max_n): the host does not wait for it
//   for_each_cell_by_colour(dims, periodic, done, epoch, f)  a team for each cell of a grid in 27 colours (c modulo
//                               3), colour after colour as far as the cells' neighbourhoods overlap (one launch on
//                               the GPU)
//   select_into(n, pred, out, count)  the indices i in [0, n) with pred(i), in order, and their count in device memory
//   reduce_over(n, f, init, op) op-reduction of f(i) over [0, n) (Thrust transform_reduce), read by the host
//   reduce_into(n, f, init, op, out[, then])  the same into *out in device memory: the host does not wait (one
//                               launch); then() runs once after the value is written
//   run_once(f)                 f() once: a one-thread kernel on the GPU (scalar work on device memory)
//   sort_pairs(keys, values, ...) stable sort of key-value pairs by the keys' lowest bits (CUB's radix sort, Thrust)
//   exec()                      the execution policy of every Thrust call (sort, scan, fill, gather, copy_if)
//
// On the GPU every call is asynchronous on the default stream: exec() is Thrust's par_nosync with a caching
// allocator for the temporary storage of sorts, scans and reductions. Thrust's plain thrust::device policy
// synchronises the stream after every algorithm and allocates (cudaMalloc / cudaFree, both synchronising) the
// temporary storage of each one, so a step of ~100 launches waited for the GPU ~100 times. Only what the host
// must read waits now: the neighbour lists' size, the step's sums (one record, read once after the step with
// the timers; reduce_into writes a sum to device memory without a wait); the adaptive step's counts stay in device
// memory too (select_into, parallel_for_upto) and come with the step's sums. What made small scenes slow
// was mostly occupancy, not these waits (parallel_for below; docs/benchmarks.md, "Launch overhead").
#pragma once
#ifndef PBF_BACKEND_NS
#error "launch.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS and include solver_impl.inl"
#endif
#include <thrust/copy.h>
#include <thrust/device_vector.h>
#include <thrust/execution_policy.h>
#include <thrust/fill.h>
#include <thrust/for_each.h>
#include <thrust/functional.h>
#include <thrust/gather.h>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/scan.h>
#include <thrust/sort.h>
#include <thrust/transform_reduce.h>

#include <chrono>
#include <map>
#include <mutex>
#include <new>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <utility>
#include <string>
#include <vector>

#include "common.h"
#include "solver_api.h"

#ifdef PBF_BACKEND_CUDA
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_select.cuh>
#include <cuda/atomic>
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

#ifdef PBF_BACKEND_CUDA
// PBF_MIN_BLOCKS (a build option): at least that many blocks of 128 threads per SM, i.e. a register cap.
#ifdef PBF_MIN_BLOCKS
#define PBF_LAUNCH_BOUNDS __launch_bounds__(128, PBF_MIN_BLOCKS)
#else
#define PBF_LAUNCH_BOUNDS
#endif
// Programmatic dependent launch (compute capability 9.0 and later): every kernel of this layer is launched with
// the stream serialisation relaxed, so the GPU prepares a kernel's launch while the kernel before it drains, and
// schedules its blocks as soon as the last block before it has exited instead of after the whole grid has been
// retired (a few microseconds less between two dependent launches). Each kernel first waits (griddepcontrol.wait)
// until the grids before it have completed and their writes are visible, so it reads exactly what it read under
// full serialisation: the results are the same to the bit. No kernel signals its dependants early
// (griddepcontrol.launch_dependents): tried at each kernel's start, the next kernel's blocks then sat on the SMs
// beside the running ones and made the solver phase of the 100k-particle steps 6-16% slower (docs/performance.md, "Speed of the
// step", change 10).
// Kernels that Thrust launches (sorts, scans) keep the full serialisation. Older GPUs launch as before.
// CLOUDPBF_PDL=0 in the environment switches it off (read once per process), for comparisons.
__device__ __forceinline__ void wait_for_prior_grids() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    asm volatile("griddepcontrol.wait;" ::: "memory");
#endif
}

// Whether the environment switches a GPU option off for comparisons: name=0 (the callers read it once per process).
inline bool switched_off_in_environment(const char* name) {
    const char* env = std::getenv(name);
    return env && std::string(env) == "0";
}

// Whether launches on the current device may overlap their predecessor's drain (see above).
inline bool programmatic_launch() {
    static const bool enabled = !switched_off_in_environment("CLOUDPBF_PDL");
    constexpr int kDevices = 64;
    static int capability[kDevices] = {};   // 0: not asked yet; else the major version + 1 (-1: no answer)
    if (!enabled) return false;
    int dev = 0;
    if (cudaGetDevice(&dev) != cudaSuccess || dev < 0 || dev >= kDevices) return false;
    if (capability[dev] == 0) {
        int major = 0;
        capability[dev] = cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, dev) == cudaSuccess ? major + 1 : -1;
    }
    return capability[dev] >= 9 + 1;
}

// kernel<<<blocks, threads>>>(args...) on the default stream, programmatically dependent where the GPU allows it;
// what names the launch goes into the error.
template <class... Params, class... Args>
void launch(const char* what, void (*kernel)(Params...), unsigned blocks, unsigned threads, Args&&... args) {
    cudaLaunchAttribute attribute[1];
    attribute[0].id = cudaLaunchAttributeProgrammaticStreamSerialization;
    attribute[0].val.programmaticStreamSerializationAllowed = 1;
    cudaLaunchConfig_t config = {};
    config.gridDim = dim3(blocks);
    config.blockDim = dim3(threads);
    config.dynamicSmemBytes = 0;
    config.stream = 0;
    config.attrs = attribute;
    config.numAttrs = programmatic_launch() ? 1 : 0;
    cudaError_t err = cudaLaunchKernelEx(&config, kernel, std::forward<Args>(args)...);
    if (err != cudaSuccess) throw std::runtime_error(std::string(what) + " launch: " + cudaGetErrorString(err));
}

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
inline void order_tiles_by_length(std::size_t, const uint32_t*, uint32_t, uint32_t*) {}
#endif

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

// Stable sort of keys[0, n) with values[0, n) alongside, by the keys' lowest key_bits bits (every key must be below
// 2^key_bits). keys_alt and values_alt (as large) are the sort's second buffers; where the result ends in them they
// are swapped in, so it is always in keys and values. On the GPU CUB's radix sort over key_bits bits only, one pass
// per 8 bits (the neighbour grid's 17-bit cell keys of a 1M-particle run: 3 passes instead of a 32-bit key's 4);
// on the CPU Thrust's sort. The order is that of a stable sort either way.
inline void sort_pairs(dvec<uint32_t>& keys, dvec<uint32_t>& values, dvec<uint32_t>& keys_alt,
                       dvec<uint32_t>& values_alt, std::size_t n, int key_bits) {
    if (n < 2) return;
#ifdef PBF_BACKEND_CUDA
    cub::DoubleBuffer<uint32_t> k(raw(keys), raw(keys_alt)), v(raw(values), raw(values_alt));
    std::size_t bytes = 0;
    cudaError_t err = cub::DeviceRadixSort::SortPairs(nullptr, bytes, k, v, int(n), 0, key_bits, cudaStream_t(0));
    if (err == cudaSuccess) {
        char* tmp = temp_allocator().allocate(std::ptrdiff_t(bytes));
        err = cub::DeviceRadixSort::SortPairs(tmp, bytes, k, v, int(n), 0, key_bits, cudaStream_t(0));
        temp_allocator().deallocate(tmp, bytes);
    }
    if (err != cudaSuccess) throw std::runtime_error(std::string("sort_pairs: ") + cudaGetErrorString(err));
    if (k.selector) keys.swap(keys_alt);
    if (v.selector) values.swap(values_alt);
#else
    (void)keys_alt;
    (void)values_alt;
    (void)key_bits;
    thrust::sort_by_key(exec(), keys.begin(), keys.begin() + n, values.begin());
#endif
}

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
template <class F>
struct AsSerialTeam {
    F f;
    void operator()(uint32_t t) const { f(t, SerialTeam{}); }
};

template <class F>
void parallel_for_teams(std::size_t n, const F& f) {
    parallel_for(n, AsSerialTeam<F>{f});
}

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

// ---- phase timers: CUDA events on the GPU, steady clock on the CPU ------------------------------
#ifdef PBF_BACKEND_CUDA
class PhaseClock {
public:
    ~PhaseClock() {
        for (auto& e : events_) cudaEventDestroy(e);
    }
    void begin(int p) { open_[p] = record(); }
    void end(int p) {
        pairs_.push_back({p, open_[p], record()});
        ran_[p] = true;
    }
    // Called once per step after the device work was issued: waits and accumulates.
    void collect(PhaseTotals& totals) {
        if (!pairs_.empty()) cudaEventSynchronize(events_[pairs_.back().stop]);
        for (auto& pr : pairs_) {
            float ms = 0.0f;
            cudaEventElapsedTime(&ms, events_[pr.start], events_[pr.stop]);
            totals.total_ms[pr.phase] += ms;
        }
        for (int p = 0; p < kNumPhases; ++p)
            if (ran_[p]) totals.count[p] += 1, ran_[p] = false;
        pairs_.clear();
        used_ = 0;
    }

private:
    struct Pair { int phase, start, stop; };
    int record() {
        if (used_ == events_.size()) {
            cudaEvent_t e;
            cudaEventCreate(&e);
            events_.push_back(e);
        }
        cudaEventRecord(events_[used_]);
        return int(used_++);
    }
    std::vector<cudaEvent_t> events_;
    std::size_t used_ = 0;
    std::vector<Pair> pairs_;
    int open_[kNumPhases] = {};
    bool ran_[kNumPhases] = {};
};
#else
class PhaseClock {
public:
    void begin(int p) { open_[p] = std::chrono::steady_clock::now(); }
    void end(int p) {
        pending_[p] += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - open_[p]).count();
        ran_[p] = true;
    }
    void collect(PhaseTotals& totals) {
        for (int p = 0; p < kNumPhases; ++p) {
            totals.total_ms[p] += pending_[p];
            pending_[p] = 0.0;
            if (ran_[p]) totals.count[p] += 1, ran_[p] = false;
        }
    }

private:
    std::chrono::steady_clock::time_point open_[kNumPhases];
    double pending_[kNumPhases] = {};
    bool ran_[kNumPhases] = {};
};
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
