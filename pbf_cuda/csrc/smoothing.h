// Smoothing of scalar fields (section 4.1, eq. 12-17), in a conservative pairwise form.
// The paper's update for one particle (eq. 13, 16, 17a-b) is
//   c_ij      = V_j x_ij . grad W_ij / (|x_ij|^2 + eps)                   (eq. 13, 16; V_j = m_j / rho0)
//   C_i       = sum_j c_ij (T_i - T_j),  grad C_ii = sum_j c_ij,  grad C_ik = -c_ik
//   T*_i      = T_i + kappa lambda_i grad C_ii = T_i - beta_i sum_j c_ij (T_i - T_j),
//   beta_i    = kappa grad C_ii / |grad C_i|^2                              (eq. 17a-b)
// i.e. an explicit diffusion step whose coefficient beta_i depends only on the neighbourhood's
// geometry. Here beta is that of a full lattice neighbourhood at the particle's level,
// beta_l = beta_0 (h_l / h0)^2, and each pair exchanges with the mean coefficient:
//   m_i dT_i = -sum_j (beta_i + beta_j)/2 (m_i m_j / rho0) s_ij (T_i - T_j),  s_ij = x_ij . grad W_ij / (|x_ij|^2 + eps),
// which is antisymmetric in i, j, so sum_i m_i T_i is conserved exactly (the paper's form is not: it
// updates T_i alone). In the bulk of a lattice this is the paper's update. Walls exchange nothing
// (adiabatic walls). Temperature is smoothed as its anomaly T - T0(y) from the environment profile
// (T_i - T_j becomes T_i - T_j - (T0(y_i) - T0(y_j)), = T_i - T_j + lapse (y_i - y_j) for the paper's linear
// profile; environment.h): the resting atmosphere is a fixed
// point also next to the adiabatic walls, and within the pass sum m T0(y) is fixed, so sum m T is still
// conserved exactly. Up to three fields (temperature, vapor, cloud) share one neighbour pass; values are
// read from the input arrays and written to the output arrays (Jacobi).
//
// Limiter. Per unit mass the step is v*_i = v_i + sum_j c_ij (v_j - v_i), c_ij >= 0: a convex combination of
// the particle and its neighbours, so within their range, as long as S_i = sum_j c_ij <= 1. On a lattice
// S_i is about 0.9 kappa; between levels it is not bounded (a fine particle's neighbours hold up to 2^l times
// its mass; measured: a wet level-1 cluster among dry level-0 particles goes negative at kappa = 1, a level-4
// particle at kappa = 0.1 in a cumulus run). Where S can reach 1 (adaptive runs, or kappa > 0.5) a first pass
// sums S_i and every pair's exchange is scaled by min(1, S_cap / max(S_i, S_j)): symmetric in the pair, so
// sum m v stays exact, and sum_j c'_ij <= S_cap: no particle leaves its neighbourhood's range.
#pragma once
#include "common.h"
#include "environment.h"
#include "grid.h"
#include "kernel_policy.h"
#include "kernels.h"
#include "pbf_constraints.h"

namespace pbf {

struct SmoothingFields {
    const float* in[3];       // nullptr: field not smoothed
    float* out[3];
};

constexpr float kSmoothingWeightCap = 0.5f;  // S_cap of the limiter: at most half a particle's value exchanged

// The pair's exchange coefficient per unit mass of i, c_ij = (beta_i + beta_j)/2 (m_j / rho0) s_ij >= 0
// (beta < 0, and x_ij . grad W_ij < 0 for the spiky kernel).
struct SmoothingPair {
    float h0, inv_rest_density, beta0, eps_rel;
    // ... with the pair's kernel gradient gw = grad W_ij given
    template <class Policy>
    PBF_HD float coefficient(Vec3 r, float r2, float hi, float hj, float mj, Vec3 gw) const {
        float beta_i = Policy::area_scaled(beta0, hi, h0);     // beta_l = beta_0 (h_l / h0)^2
        float beta_j = Policy::area_scaled(beta0, hj, h0);
        return 0.5f * (beta_i + beta_j) * mj * inv_rest_density * dot(r, gw) / (r2 + eps_rel * hi * hj);
    }
    template <class Policy>
    PBF_HD float coefficient(Vec3 r, float r2, float hi, float hj, float mj) const {
        return coefficient<Policy>(r, r2, hi, hj, mj, Policy::grad_W(r, r2, hi, hj));
    }
};

// The limiter's weight of pair (i, j), max(c_ij, 0): S_i sums it over j != i. out: where S_i goes (nullptr: the step
// does not need it). Summed by SmoothingWeightSums, or by the XSPH pass, which visits the same pairs at the same
// positions in the same order (ViscosityVorticity's PairSum, pbf_constraints.h), so S_i is the same (bitwise on the
// CPU; on the GPU the two kernels may be contracted into FMAs differently).
template <class Policy>
struct LimiterWeight {
    SmoothingPair pair;
    float* out;
    PBF_HD float operator()(Vec3 r, float r2, float hi, float hj, float mj) const {
        return fmaxf(pair.coefficient<Policy>(r, r2, hi, hj, mj), 0.0f);
    }
};

// S_i = sum_j c_ij of the limiter, as a pass of its own (where no XSPH pass runs to take it along).
template <class Policy>
struct SmoothingWeightSums {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    LimiterWeight<Policy> weight;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        float hi = Policy::radius(radii, weight.pair.h0, pi.w);
        float s = 0.0f;
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, weight.pair.h0, i, xyz(pi), [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (j != i) s += weight(r, r2, hi, hj, mj);
        });
        weight.out[i] = s;
    }
};

// The fields' Jacobi step, with the vorticity confinement taken along where confinement.vel is set (ConfinementSum,
// pbf_constraints.h: the same pairs at x*, the same gradients).
template <class Policy>
struct SmoothScalars {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    SmoothingPair pair;       // beta0: kappa grad C_ii / |grad C_i|^2 of a full level-0 lattice (eq. 17), m^2
    EnvironmentProfile env;   // T0(y) (temperature is smoothed as its anomaly T - T0(y))
    const float* weight_sum;  // S_i of the limiter; nullptr: no limiter
    SmoothingFields f;
    ConfinementSum confinement;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float hi = Policy::radius(radii, pair.h0, pi.w);
        float s_i = weight_sum ? weight_sum[i] : 0.0f;
        float vi[3], dT[3] = {0, 0, 0};
        for (int k = 0; k < 3; ++k) vi[k] = f.in[k] ? f.in[k][i] : 0.0f;
        const bool confine = confinement.vel != nullptr;
        const float wi = confine ? confinement.omega[i].w : 0.0f;
        Vec3 eta{0, 0, 0};
        // Read with j's position: the limiter's S_j and fields 0 and 1 (temperature and vapour, the fields the
        // shipped scenes smooth); field 2 (cloud water) is read per pair.
        struct Fields {
            float v[2];
            float s;
        };
        auto gather = [&](uint32_t j) {
            return Fields{{f.in[0] ? f.in[0][j] : 0.0f, f.in[1] ? f.in[1][j] : 0.0f}, weight_sum ? weight_sum[j] : 0.0f};
        };
        for_each_fluid_neighbor_gathered<Policy>(grid, fluid, radii, pair.h0, i, xi, gather,
                                                 [&](uint32_t j, Vec3 r, float r2, float mj, float hj, const Fields& nj) {
            if (j == i) return;
            Vec3 gw = Policy::grad_W(r, r2, hi, hj);
            if (confine) confinement.add(eta, wi, j, mj, gw);
            float c = pair.coefficient<Policy>(r, r2, hi, hj, mj, gw);
            if (weight_sum) {
                float s = fmaxf(s_i, nj.s);
                if (s > kSmoothingWeightCap) c *= kSmoothingWeightCap / s;
            }
            if (f.in[0]) dT[0] -= c * (vi[0] - nj.v[0] - env.change(xi.y, r.y));
            if (f.in[1]) dT[1] -= c * (vi[1] - nj.v[1]);
            if (f.in[2]) dT[2] -= c * (vi[2] - f.in[2][j]);
        });
        for (int k = 0; k < 3; ++k)
            if (f.in[k]) f.out[k][i] = vi[k] + dT[k];
        if (confine) confinement.apply(i, eta);
    }
};

}  // namespace pbf
