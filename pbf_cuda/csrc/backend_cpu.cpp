// CPU backend: the shared solver source compiled by g++ with Thrust's OpenMP device system.
// THRUST_DEVICE_SYSTEM and the wrapped CUB/Thrust namespace are set by CMake for this file only,
// so its Thrust symbols never collide with the CUDA backend's.
#define PBF_BACKEND_NS omp_backend
#include "solver_impl.inl"

namespace pbf {
std::unique_ptr<ISolver> make_cpu_solver(const Params& p) { return std::make_unique<omp_backend::Solver>(p); }
}  // namespace pbf
