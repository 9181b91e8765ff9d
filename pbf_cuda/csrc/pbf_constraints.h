// Position Based Fluids density constraint (Macklin & Mueller 2013; paper eq. 1-4 and 18),
// written with inverse-mass weights so that particles of different adaptive levels
// (m_i = m0 2^-l) are corrected in proportion to 1/m:
//   rho_i   = sum_j m_j W_ij + sum_b m_b W_ib                          (eq. 1, eq. 18)
//   C_i     = rho_i / rho0 - 1                                           (eq. 2; max(., 0) if unilateral)
//   lambda_i = -C_i / (sum_k |grad_k C_i|^2 / m_k + eps)                (eq. 4)
//   dp_i    = 1/rho0 sum_j (lambda_i m_j / m_i + lambda_j + s_corr) grad W_ij
//             + 1/rho0 sum_b lambda_i m_b / m_i grad W_ib               (Macklin eq. 12-14)
// Boundary particles (walls) have no constraint of their own and never move.
//
// The velocity projection (projection = "velocity") uses the same Jacobian J = grad C on velocities:
//   D_i     = dC_i/dt = 1/rho0 sum_j m_j (v_i - v_j) . grad W_ij + 1/rho0 sum_b m_b v_i . grad W_ib
//   mu_i    = -D_i / (sum_k |grad_k C_i|^2 / m_k + eps)
//   dv_i    = 1/rho0 sum_j (mu_i m_j / m_i + mu_j) grad W_ij + 1/rho0 sum_b mu_i m_b / m_i grad W_ib
// i.e. dv = M^-1 J^T mu: an M-orthogonal projection onto J v = 0, which removes only the compressing
// part of the velocity (DFSPH's divergence-free solver, Bender & Koschier 2015, in PBF's lambda form).
// mu solves (J M^-1 J^T) mu = -J v, the minimiser of the kinetic energy of v + M^-1 J^T mu; it is found by
// Jacobi-preconditioned conjugate gradients (ApplyJT, ApplyJ below), whose every iterate lowers the kinetic
// energy, so the projection never adds energy even when it stops before convergence.
#pragma once
#include "common.h"
#include "grid.h"
#include "kernel_policy.h"
#include "kernels.h"

namespace pbf {

struct ConstraintParams {
    float rest_density;
    float inv_rest_density;
    float relaxation;
    float h0;
    bool unilateral;
    float scorr_k_lambda;   // scorr_k * lambda_ref
    int scorr_n;
    float scorr_inv_wdq;    // 1 / W(dq * h0)
    float scorr_dq;         // dq / h
};

// ---- the neighbour sums the four constraint kernels share ---------------------------------------
// The density constraint's neighbourhood of fluid particle i at xi: on_fluid(j, r, r2, m_j, h_j) for every fluid
// neighbour (i itself included, r2 = 0), then on_wall(r, r2, m_b) for every boundary particle within h0 when i is
// near a wall (boundary particles have the level-0 radius h0).
template <class Policy, class Fluid, class Wall>
PBF_HD inline void for_each_constraint_neighbor(const GridGeometry& grid, const CellRanges& fluid,
                                                const CellRanges& boundary, const LevelRadii& radii, float h0,
                                                uint32_t i, Vec3 xi, Fluid&& on_fluid, Wall&& on_wall) {
    for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xi, on_fluid);
    if (boundary.start && near_wall(grid, xi, h0)) {
        for_each_neighbor(grid, boundary, xi, h0, [&](uint32_t b, Vec3 r, float r2) { on_wall(r, r2, boundary.pos[b].w); });
    }
}

// Row i of the constraint Jacobian J = grad C, summed over the neighbourhood: grad_i C_i and the Jacobi diagonal
// sum_k |grad_k C_i|^2 / m_k (the denominator of eq. 4 without epsilon). Fluid neighbours contribute
// grad_j C_i = -(m_j / rho0) grad W_ij to the sum and its negative to grad_i C_i; walls only to grad_i C_i.
struct JacobianRow {
    Vec3 grad_i{0, 0, 0};
    float sum_grad2 = 0.0f;   // sum_j |grad_j C_i|^2 / m_j
    PBF_HD void add_fluid(Vec3 gw, float mj, float inv_rest_density) {
        Vec3 gj = (mj * inv_rest_density) * gw;
        grad_i += gj;
        sum_grad2 += dot(gj, gj) / mj;
    }
    PBF_HD void add_wall(Vec3 gw, float mb, float inv_rest_density) { grad_i += (mb * inv_rest_density) * gw; }
    PBF_HD float diagonal(float mi) const { return dot(grad_i, grad_i) / mi + sum_grad2; }
};

// (M^-1 J^T a)_i rho0 = sum_j coef(j, r2, m_j, h_j) grad W_ij + sum_b (a_i m_b / m_i) grad W_ib, with coef the
// fluid pair's weight a_i m_j / m_i + a_j (+ the tensile term): the position correction (Macklin eq. 12-14,
// a = lambda) and the velocity projection's M^-1 J^T (a = mu) are this one sum.
template <class Policy, class Coef>
PBF_HD inline Vec3 sum_transposed(const GridGeometry& grid, const CellRanges& fluid, const CellRanges& boundary,
                                  const LevelRadii& radii, float h0, uint32_t i, Vec3 xi, float hi, float ai, float mi,
                                  Coef&& coef) {
    Vec3 sum{0, 0, 0};
    for_each_constraint_neighbor<Policy>(grid, fluid, boundary, radii, h0, i, xi,
        [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (j == i) return;
            float c = coef(j, r2, mj, hj);
            sum += c * Policy::grad_W(r, r2, hi, hj);
        },
        [&](Vec3 r, float r2, float mb) { sum += (ai * mb / mi) * Policy::grad_W(r, r2, hi, h0); });
    return sum;
}

// Density (eq. 1, 18) and lambda (eq. 4) of fluid particle i.
template <class Policy>
struct DensityLambda {
    GridGeometry grid;
    CellRanges fluid;
    CellRanges boundary;  // boundary.start == nullptr: no walls
    LevelRadii radii;
    ConstraintParams cp;
    float* lambda;
    float* density;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        float rho = 0.0f;
        JacobianRow row;
        for_each_constraint_neighbor<Policy>(grid, fluid, boundary, radii, cp.h0, i, xi,
            [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
                rho += mj * Policy::W(r2, hi, hj);
                if (j != i) row.add_fluid(Policy::grad_W(r, r2, hi, hj), mj, cp.inv_rest_density);
            },
            [&](Vec3 r, float r2, float mb) {
                rho += mb * Policy::W(r2, hi, cp.h0);
                row.add_wall(Policy::grad_W(r, r2, hi, cp.h0), mb, cp.inv_rest_density);
            });
        float c = rho * cp.inv_rest_density - 1.0f;
        if (cp.unilateral && c < 0.0f) c = 0.0f;
        float denom = row.diagonal(mi) + cp.relaxation;
        lambda[i] = denom > 0.0f ? -c / denom : 0.0f;
        density[i] = rho;
    }
};

// The two halves of A = J M^-1 J^T for the velocity projection's conjugate gradient solve
// (pbf_constraints_launch.h: project_velocity): ApplyJT g_i = (M^-1 J^T p)_i, and ApplyJ q_i = (J g)_i together
// with the Jacobi preconditioner diag_i = sum_k |grad_k C_i|^2 / m_k.
template <class Policy>
struct ApplyJT {
    GridGeometry grid;
    CellRanges fluid;
    CellRanges boundary;
    LevelRadii radii;
    ConstraintParams cp;
    const float* p;
    Float4* g;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        float li = p[i];
        Vec3 dv = sum_transposed<Policy>(grid, fluid, boundary, radii, cp.h0, i, xi, hi, li, mi,
                                         [&](uint32_t j, float, float mj, float) { return li * mj / mi + p[j]; });
        g[i] = make_float4(cp.inv_rest_density * dv, 0.0f);
    }
};

template <class Policy>
struct ApplyJ {
    GridGeometry grid;
    CellRanges fluid;
    CellRanges boundary;
    LevelRadii radii;
    ConstraintParams cp;
    const Float4* u;
    float* q;
    float* diag;   // nullptr: not written
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        Vec3 ui = xyz(u[i]);
        float div = 0.0f;
        JacobianRow row;
        for_each_constraint_neighbor<Policy>(grid, fluid, boundary, radii, cp.h0, i, xi,
            [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
                if (j == i) return;
                Vec3 gw = Policy::grad_W(r, r2, hi, hj);
                div += mj * dot(ui - xyz(u[j]), gw);
                if (diag) row.add_fluid(gw, mj, cp.inv_rest_density);
            },
            [&](Vec3 r, float r2, float mb) {
                Vec3 gw = Policy::grad_W(r, r2, hi, cp.h0);
                div += mb * dot(ui, gw);
                if (diag) row.add_wall(gw, mb, cp.inv_rest_density);
            });
        q[i] = div * cp.inv_rest_density;
        if (diag) diag[i] = row.diagonal(mi);
    }
};

// Position correction dp_i (Macklin eq. 12-14, with the tensile term s_corr) applied to the
// predicted position; writes into a second buffer (Jacobi iteration), clamps to the walls.
template <class Policy>
struct PositionCorrection {
    GridGeometry grid;
    CellRanges fluid;
    CellRanges boundary;
    LevelRadii radii;
    ConstraintParams cp;
    const float* lambda;
    Float4* pos_out;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        float li = lambda[i];
        Vec3 dp = sum_transposed<Policy>(grid, fluid, boundary, radii, cp.h0, i, xi, hi, li, mi,
                                         [&](uint32_t j, float r2, float mj, float hj) {
            float s = 0.0f;
            if (cp.scorr_k_lambda > 0.0f) {   // s_corr = -k (W(r) / W(dq h))^n, at the pair's radii (policy)
                float ratio = Policy::tensile_ratio(r2, hi, hj, cp.scorr_dq, cp.scorr_inv_wdq);
                float p = ratio;
                for (int k = 1; k < cp.scorr_n; ++k) p *= ratio;
                s = Policy::tensile_scale(-cp.scorr_k_lambda * p, hi, hj, cp.h0);
            }
            return li * mj / mi + lambda[j] + s;
        });
        Vec3 x = xi + cp.inv_rest_density * dp;
        // Collision with the walls: keep the particle inside the box on wall axes.
        for (int a = 0; a < 3; ++a) {
            if (grid.periodic[a]) continue;
            float v = component(x, a);
            v = v < 0.0f ? 0.0f : (v > grid.domain[a] ? grid.domain[a] : v);
            set_component(x, a, v);
        }
        pos_out[i] = make_float4(x, mi);
    }
};

// XSPH viscosity and the vorticity omega_i = curl v (Macklin eq. 15-17):
//   v_i <- v_i + c sum_j V_j (v_j - v_i) W_ij,   omega_i = sum_j V_j grad_i W_ij x (v_j - v_i),
// with V_j = m_j / rho_j.
//
// Physical viscosity (Morris et al. 1997), pairwise so that momentum is conserved:
//   dv_i = nu dt lap(v)_i,  lap(v)_i = 2 sum_j (m_j / rho0) (v_i - v_j) (x_ij . grad W_ij) / (|x_ij|^2 + eps)
// (the same SPH Laplacian as the smoothing of eq. 13; explicit, stable for nu dt / d^2 below ~0.1).
template <class Policy>
struct ViscosityVorticity {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    float h0;
    float xsph;
    float nu_dt;            // kinematic viscosity times dt, m^2
    float inv_rest_density;
    bool want_vorticity;
    const Float4* vel;
    const float* density;
    Float4* vel_out;
    Float4* omega;  // xyz = omega, w = |omega|
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float hi = Policy::radius(radii, h0, pi.w);
        Vec3 vi = xyz(vel[i]);
        Vec3 visc{0, 0, 0};
        Vec3 lap{0, 0, 0};
        Vec3 w{0, 0, 0};
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xi, [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (j == i) return;
            float vol = mj / density[j];
            Vec3 dv = xyz(vel[j]) - vi;
            if (xsph > 0.0f) visc += (vol * Policy::W(r2, hi, hj)) * dv;
            if (want_vorticity || nu_dt > 0.0f) {
                Vec3 gw = Policy::grad_W(r, r2, hi, hj);
                if (want_vorticity) w += vol * cross(gw, dv);
                if (nu_dt > 0.0f) lap -= (2.0f * mj * inv_rest_density * dot(r, gw) / (r2 + 0.01f * hi * hj)) * dv;
            }
        });
        vel_out[i] = make_float4(vi + xsph * visc + nu_dt * lap, 0.0f);
        if (want_vorticity) omega[i] = make_float4(w, length(w));
    }
};

// Vorticity confinement force f_i = eps (N x omega_i), N = eta / |eta|, eta = grad |omega|
// (Macklin eq. 16), added to the velocity over one step.
template <class Policy>
struct VorticityConfinement {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    float h0;
    float epsilon;
    float dt;
    const float* density;
    const Float4* omega;
    Float4* vel;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float hi = Policy::radius(radii, h0, pi.w);
        float wi = omega[i].w;
        Vec3 eta{0, 0, 0};
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xi, [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (j == i) return;
            eta += ((mj / density[j]) * (omega[j].w - wi)) * Policy::grad_W(r, r2, hi, hj);
        });
        float len = length(eta);
        if (len > 1e-20f) {
            Vec3 n = (1.0f / len) * eta;
            Vec3 f = epsilon * cross(n, xyz(omega[i]));
            Float4 v = vel[i];
            vel[i] = Float4{v.x + dt * f.x, v.y + dt * f.y, v.z + dt * f.z, v.w};
        }
    }
};

}  // namespace pbf
