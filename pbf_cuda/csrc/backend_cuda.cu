// CUDA backend: the shared solver source compiled by nvcc.
#define PBF_BACKEND_NS cuda_backend
#define PBF_BACKEND_CUDA 1
#include "solver_impl.inl"

namespace pbf {
std::unique_ptr<ISolver> make_cuda_solver(const Params& p) { return std::make_unique<cuda_backend::Solver>(p); }

int cuda_device_count() {
    int n = 0;
    if (cudaGetDeviceCount(&n) != cudaSuccess) {
        cudaGetLastError();  // clear: no driver or no device
        return 0;
    }
    return n;
}

// Compute capability of device 0 as major * 10 + minor (90 for an H100), or -1 without a device.
int cuda_device_capability() {
    cudaDeviceProp prop;
    if (cuda_device_count() == 0 || cudaGetDeviceProperties(&prop, 0) != cudaSuccess) return -1;
    return prop.major * 10 + prop.minor;
}

// Free and total memory of device 0 in bytes ({0, 0} without a device).
std::pair<std::size_t, std::size_t> cuda_memory_info() {
    std::size_t free_b = 0, total_b = 0;
    if (cuda_device_count() == 0 || cudaMemGetInfo(&free_b, &total_b) != cudaSuccess) {
        cudaGetLastError();
        return {0, 0};
    }
    return {free_b, total_b};
}

std::string cuda_device_name() {
    cudaDeviceProp prop;
    if (cuda_device_count() == 0 || cudaGetDeviceProperties(&prop, 0) != cudaSuccess) return "";
    return prop.name;
}
}  // namespace pbf
