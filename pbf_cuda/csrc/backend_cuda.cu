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

// Device-to-device copy bandwidth of device 0 in bytes per second, counting every byte read and every byte
// written (2 nbytes per copy): the denominator of the step's bandwidth roofline (cloudpbf/roofline.py). The mean
// over `repeats` copies after one warm-up copy, timed with events; 0 without a device or the memory.
double cuda_copy_bandwidth(std::size_t nbytes, int repeats) {
    if (cuda_device_count() == 0 || nbytes == 0 || repeats < 1) return 0.0;
    void* src = nullptr;
    void* dst = nullptr;
    if (cudaMalloc(&src, nbytes) != cudaSuccess || cudaMalloc(&dst, nbytes) != cudaSuccess) {
        cudaGetLastError();
        if (src) cudaFree(src);
        return 0.0;
    }
    cudaEvent_t start, stop;
    cudaEventCreate(&start);
    cudaEventCreate(&stop);
    cudaMemset(src, 1, nbytes);
    cudaMemcpy(dst, src, nbytes, cudaMemcpyDeviceToDevice);
    cudaEventRecord(start);
    for (int r = 0; r < repeats; ++r) cudaMemcpyAsync(dst, src, nbytes, cudaMemcpyDeviceToDevice);
    cudaEventRecord(stop);
    cudaEventSynchronize(stop);
    float ms = 0.0f;
    cudaEventElapsedTime(&ms, start, stop);
    cudaEventDestroy(start);
    cudaEventDestroy(stop);
    cudaFree(src);
    cudaFree(dst);
    return ms > 0.0f ? 2.0 * double(nbytes) * repeats / (1e-3 * ms) : 0.0;
}

std::string cuda_device_name() {
    cudaDeviceProp prop;
    if (cuda_device_count() == 0 || cudaGetDeviceProperties(&prop, 0) != cudaSuccess) return "";
    return prop.name;
}
}  // namespace pbf
