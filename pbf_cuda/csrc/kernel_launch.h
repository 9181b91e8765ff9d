// How the CUDA backend launches its own kernels (the dispatch headers' parallel_for, reductions, colour walk):
// launch(what, kernel, blocks, threads, args...) on the default stream with programmatic dependent launch, the
// kernels' first call wait_for_prior_grids(), and their register cap PBF_LAUNCH_BOUNDS. Nothing on the CPU backend,
// whose loops are OpenMP's.
#pragma once
#ifndef PBF_BACKEND_NS
#error "kernel_launch.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <utility>

#ifdef PBF_BACKEND_CUDA
#include <cuda_runtime.h>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

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
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
