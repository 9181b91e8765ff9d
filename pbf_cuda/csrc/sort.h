// The sort of the dispatch layer:
//   sort_pairs(keys, values, ...) stable sort of key-value pairs by the keys' lowest bits (CUB's radix sort, Thrust)
#pragma once
#ifndef PBF_BACKEND_NS
#error "sort.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <thrust/sort.h>

#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>

#include "device_memory.h"

#ifdef PBF_BACKEND_CUDA
#include <cub/device/device_radix_sort.cuh>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

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

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
