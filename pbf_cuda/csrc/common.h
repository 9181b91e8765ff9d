// Shared basics for both backends: the host/device macro and small vector math.
// Everything here compiles with nvcc (CUDA backend) and with g++ (OpenMP backend).
#pragma once
#include <math.h>   // the C names the device code calls unqualified (sqrtf, isfinite) in the global namespace
#include <cmath>
#include <cstdint>
#include <cstring>

#if defined(__CUDACC__)
#define PBF_HD __host__ __device__
#else
#define PBF_HD
#endif
#define PBF_INLINE PBF_HD inline
// Small functions of the neighbour loops: always inlined by the CPU compiler (g++ left the kernel gradient as a
// call, which spills the loop's floating-point registers around it); nvcc inlines them on its own, and forcing it
// there is left alone (inlining across the call could let it contract into FMAs the GPU build does not make today).
#ifdef __CUDACC__
#define PBF_HOT PBF_HD inline
#else
#define PBF_HOT inline __attribute__((always_inline))
#endif

namespace pbf {

constexpr float kPi = 3.14159265358979323846f;

// The bits of a float (IEEE 754 binary32): one register move on the GPU, a copy the compiler removes on the CPU.
PBF_INLINE uint32_t float_bits(float x) {
#if defined(__CUDA_ARCH__)
    return __float_as_uint(x);
#else
    uint32_t u;
    std::memcpy(&u, &x, sizeof u);
    return u;
#endif
}

// A team of threads that works on one item together and shares its loops: one warp of 32 lanes on the
// GPU, a single thread on the CPU. any() is a vote over the team; ballot() gathers the members' votes into a
// mask (bit k: member k's); sync() makes the writes of every lane visible to the others (no-ops for a team of one).
struct SerialTeam {
    static constexpr uint32_t kSize = 1;
    PBF_HD uint32_t rank() const { return 0; }
    PBF_HD bool any(bool p) const { return p; }
    PBF_HD uint32_t ballot(bool p) const { return p ? 1u : 0u; }
    PBF_HD void sync() const {}
    template <class T>
    PBF_HD T broadcast(const T& v, uint32_t) const { return v; }
};

#if defined(__CUDACC__)
struct WarpTeam {
    static constexpr uint32_t kSize = 32;
    uint32_t lane;
    PBF_HD uint32_t rank() const { return lane; }
#if defined(__CUDA_ARCH__)
    __device__ bool any(bool p) const { return __any_sync(0xffffffffu, p); }
    __device__ uint32_t ballot(bool p) const { return __ballot_sync(0xffffffffu, p); }
    __device__ void sync() const { __syncwarp(); }
    // Lane src's v, for every lane (v shuffled as 32-bit words).
    template <class T>
    __device__ T broadcast(const T& v, uint32_t src) const {
        static_assert(sizeof(T) % 4 == 0, "broadcast: a type of whole 32-bit words");
        uint32_t w[sizeof(T) / 4];
        memcpy(w, &v, sizeof(T));
        for (uint32_t k = 0; k < sizeof(T) / 4; ++k) w[k] = __shfl_sync(0xffffffffu, w[k], int(src));
        T out;
        memcpy(&out, w, sizeof(T));
        return out;
    }
#else
    bool any(bool p) const { return p; }  // host pass of nvcc only; teams run on the device
    uint32_t ballot(bool p) const { return p ? 1u : 0u; }
    void sync() const {}
    template <class T>
    T broadcast(const T& v, uint32_t) const { return v; }
#endif
};
#endif

// Index of the lowest set bit of a non-zero mask.
PBF_HD inline uint32_t lowest_set_bit(uint32_t mask) {
#if defined(__CUDA_ARCH__)
    return uint32_t(__ffs(int(mask)) - 1);
#else
    return uint32_t(__builtin_ctz(mask));
#endif
}

struct Vec3 {
    float x, y, z;
};

// Position (x, y, z) and mass in w; velocity (x, y, z) and w unused. 16 bytes: one vector load.
struct alignas(16) Float4 {
    float x, y, z, w;
};

PBF_INLINE Vec3 make_vec3(float x, float y, float z) { return Vec3{x, y, z}; }
PBF_INLINE Vec3 xyz(const Float4& a) { return Vec3{a.x, a.y, a.z}; }
PBF_INLINE Float4 make_float4(const Vec3& a, float w) { return Float4{a.x, a.y, a.z, w}; }
PBF_INLINE Vec3 operator+(Vec3 a, Vec3 b) { return Vec3{a.x + b.x, a.y + b.y, a.z + b.z}; }
PBF_INLINE Vec3 operator-(Vec3 a, Vec3 b) { return Vec3{a.x - b.x, a.y - b.y, a.z - b.z}; }
PBF_INLINE Vec3 operator-(Vec3 a) { return Vec3{-a.x, -a.y, -a.z}; }
PBF_INLINE Vec3 operator*(float s, Vec3 a) { return Vec3{s * a.x, s * a.y, s * a.z}; }
PBF_INLINE Vec3 operator*(Vec3 a, float s) { return Vec3{s * a.x, s * a.y, s * a.z}; }
PBF_INLINE Vec3& operator+=(Vec3& a, Vec3 b) { a.x += b.x; a.y += b.y; a.z += b.z; return a; }
PBF_INLINE Vec3& operator-=(Vec3& a, Vec3 b) { a.x -= b.x; a.y -= b.y; a.z -= b.z; return a; }
PBF_INLINE float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
PBF_INLINE Vec3 cross(Vec3 a, Vec3 b) {
    return Vec3{a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
PBF_INLINE float length(Vec3 a) { return sqrtf(dot(a, a)); }
PBF_INLINE float component(Vec3 a, int axis) { return axis == 0 ? a.x : (axis == 1 ? a.y : a.z); }
PBF_INLINE void set_component(Vec3& a, int axis, float v) {
    if (axis == 0) a.x = v; else if (axis == 1) a.y = v; else a.z = v;
}
PBF_INLINE bool finite3(Vec3 a) { return isfinite(a.x) && isfinite(a.y) && isfinite(a.z); }

// 32-bit integer hash (lowbias32): deterministic per-particle pseudo-random numbers.
PBF_INLINE uint32_t hash_u32(uint32_t x) {
    x ^= x >> 16; x *= 0x7feb352dU; x ^= x >> 15; x *= 0x846ca68bU; x ^= x >> 16;
    return x;
}
PBF_INLINE float hash_unit(uint32_t x) { return (hash_u32(x) >> 8) * (1.0f / 16777216.0f); }

}  // namespace pbf
