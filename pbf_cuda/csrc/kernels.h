// SPH smoothing kernels (Mueller et al. 2003) and the paper's symmetric kernel for
// particles of different radii (eq. 19).
//   poly6   W(r, h)      = 315 / (64 pi h^9) (h^2 - r^2)^3          density, eq. 1 / eq. 18
//   spiky   grad W(r, h) = -45 / (pi h^6) (h - r)^2 r_hat            constraint gradients, eq. 3-4
// Radii in m; W in 1/m^3; grad W in 1/m^4.
#pragma once
#include "common.h"
#include "params.h"

namespace pbf {

PBF_HOT float poly6(float r2, float h) {
    float h2 = h * h;
    if (r2 >= h2) return 0.0f;
    float d = h2 - r2;
    float h3 = h2 * h;
    return (315.0f / (64.0f * kPi)) * d * d * d / (h3 * h3 * h3);
}

// Gradient with respect to x_i of W(x_i - x_j): r = x_i - x_j.
PBF_HOT Vec3 spiky_gradient(Vec3 r, float r2, float h) {
    if (r2 >= h * h || r2 <= 0.0f) return Vec3{0, 0, 0};
    float rl = sqrtf(r2);
    float d = h - rl;
    float h3 = h * h * h;
    float coef = -(45.0f / kPi) * d * d / (h3 * h3 * rl);
    return coef * r;
}

// Kernel radius per adaptive level: h_l = h0 2^(-l/3) (section 5.2). The level of a particle is
// read from its mass, m = m0 2^(-l), which is an exact power-of-two multiple of m0.
struct LevelRadii {
    float h[kMaxLevels];
    int m0_exponent;  // biased binary exponent of the level-0 mass m0 (bits 23-30 of the float), fixed per run
    // m = m0 2^-l exactly, so l is the difference of the binary exponents; no division, which
    // --use_fast_math would make approximate (m0 / m0 = 0.99999994 reads as level 1). The exponents are read
    // from the bits (masses are normal floats): every neighbour pair of an adaptive pass asks for its level, and
    // frexpf is a library call on the CPU and a dozen instructions on the GPU.
    PBF_HD int level_of_mass(float m) const {
        int l = m0_exponent - int((float_bits(m) >> 23) & 0xffu);
        return l < 0 ? 0 : (l >= kMaxLevels ? kMaxLevels - 1 : l);
    }
    PBF_HD float radius_of_mass(float m) const { return h[level_of_mass(m)]; }
    // How far a merged particle can sit outside the cell it was sorted into: it moves to the midpoint
    // of a pair within h_l of each other (l >= 1), i.e. by at most h_1 / 2.
    PBF_HD float moved_slack() const { return 0.5f * h[1]; }
};

inline LevelRadii make_level_radii(float h0, float m0) {
    LevelRadii lr{};
    for (int l = 0; l < kMaxLevels; ++l) lr.h[l] = h0 * std::pow(2.0f, -l / 3.0f);
    lr.m0_exponent = int((float_bits(m0) >> 23) & 0xffu);
    return lr;
}

// Symmetric kernels of eq. 19: the mean of the kernel at both radii. With equal radii they reduce
// to the plain kernel (the non-adaptive path calls poly6 / spiky_gradient directly).
PBF_HOT float poly6_sym(float r2, float hi, float hj) {
    return hi == hj ? poly6(r2, hi) : 0.5f * (poly6(r2, hi) + poly6(r2, hj));
}
PBF_HOT Vec3 spiky_gradient_sym(Vec3 r, float r2, float hi, float hj) {
    if (hi == hj) return spiky_gradient(r, r2, hi);
    return 0.5f * (spiky_gradient(r, r2, hi) + spiky_gradient(r, r2, hj));
}

}  // namespace pbf
