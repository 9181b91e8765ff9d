// Smoothing of scalar fields (section 4.1, eq. 12-17): one constraint C_i = lap(T)_i = 0 per
// particle, linearised and solved for lambda_i like PBF, then relaxed by kappa:
//   c_ij      = V_j x_ij . grad W_ij / (|x_ij|^2 + eps h^2)             (eq. 13, 16; V_j = m_j / rho0)
//   C_i       = sum_j c_ij (T_i - T_j)                                   (eq. 13)
//   grad C_ii = sum_j c_ij,  grad C_ik = -c_ik                           (eq. 16)
//   lambda_i  = -C_i / |grad C_i|^2                                      (eq. 17a)
//   T*_i      = T_i + kappa lambda_i grad C_ii                           (eq. 17b)
// Boundary particles contribute their (fixed) values to C_i and grad C_ii. Up to three fields
// (temperature, vapor, cloud) are smoothed in one neighbour pass; values are read from the
// input arrays and written to the output arrays (Jacobi).
#pragma once
#include "common.h"
#include "grid.h"
#include "kernels.h"

namespace pbf {

struct SmoothingFields {
    const float* in[3];       // nullptr: field not smoothed
    float* out[3];
    const float* boundary[3]; // boundary particles' values (nullptr: no walls)
};

template <bool Adaptive>
struct SmoothScalars {
    GridGeometry grid;
    CellRanges fluid;
    CellRanges boundary;
    LevelRadii radii;
    float h0;
    float inv_rest_density;
    float kappa;
    float eps_rel;  // epsilon of eq. 13 relative to h^2
    SmoothingFields f;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float hi = Adaptive ? radii.radius_of_mass(pi.w) : h0;
        float eps = eps_rel * hi * hi;
        float vi[3], C[3] = {0, 0, 0};
        for (int k = 0; k < 3; ++k) vi[k] = f.in[k] ? f.in[k][i] : 0.0f;
        float g_ii = 0.0f, g_off2 = 0.0f;
        for_each_neighbor(grid, fluid, xi, h0, [&](uint32_t j, Vec3 r, float r2) {
            if (j == i) return;
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : h0;
            Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
            float c = mj * inv_rest_density * dot(r, gw) / (r2 + eps);
            g_ii += c;
            g_off2 += c * c;
            for (int k = 0; k < 3; ++k)
                if (f.in[k]) C[k] += c * (vi[k] - f.in[k][j]);
        });
        if (boundary.start && near_wall(grid, xi, h0)) {
            for_each_neighbor(grid, boundary, xi, h0, [&](uint32_t b, Vec3 r, float r2) {
                float mb = boundary.pos[b].w;
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, h0) : spiky_gradient(r, r2, hi);
                float c = mb * inv_rest_density * dot(r, gw) / (r2 + eps);
                g_ii += c;
                for (int k = 0; k < 3; ++k)
                    if (f.in[k] && f.boundary[k]) C[k] += c * (vi[k] - f.boundary[k][b]);
            });
        }
        float norm2 = g_ii * g_ii + g_off2;
        for (int k = 0; k < 3; ++k) {
            if (!f.in[k]) continue;
            float lambda = norm2 > 0.0f ? -C[k] / norm2 : 0.0f;   // eq. 17a
            f.out[k][i] = vi[k] + kappa * lambda * g_ii;           // eq. 17b
        }
    }
};

}  // namespace pbf
