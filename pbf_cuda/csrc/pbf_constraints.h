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

// Density (eq. 1, 18) and lambda (eq. 4) of fluid particle i.
template <bool Adaptive>
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
        float hi = Adaptive ? radii.radius_of_mass(mi) : cp.h0;
        float rho = 0.0f;
        Vec3 grad_i{0, 0, 0};
        float sum_grad2 = 0.0f;  // sum_j |grad_j C_i|^2 / m_j
        for_each_fluid_neighbor<Adaptive>(grid, fluid, i, xi, cp.h0, [&](uint32_t j, Vec3 r, float r2) {
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : cp.h0;
            rho += mj * (Adaptive ? poly6_sym(r2, hi, hj) : poly6(r2, hi));
            if (j != i) {
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
                Vec3 gj = (mj * cp.inv_rest_density) * gw;
                grad_i += gj;
                sum_grad2 += dot(gj, gj) / mj;
            }
        });
        if (boundary.start && near_wall(grid, xi, cp.h0)) {
            for_each_neighbor(grid, boundary, xi, cp.h0, [&](uint32_t b, Vec3 r, float r2) {
                float mb = boundary.pos[b].w;
                rho += mb * (Adaptive ? poly6_sym(r2, hi, cp.h0) : poly6(r2, hi));
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, cp.h0) : spiky_gradient(r, r2, hi);
                grad_i += (mb * cp.inv_rest_density) * gw;
            });
        }
        float c = rho * cp.inv_rest_density - 1.0f;
        if (cp.unilateral && c < 0.0f) c = 0.0f;
        float denom = dot(grad_i, grad_i) / mi + sum_grad2 + cp.relaxation;
        lambda[i] = denom > 0.0f ? -c / denom : 0.0f;
        density[i] = rho;
    }
};

// The two halves of A = J M^-1 J^T for the velocity projection's conjugate gradient solve
// (solver_impl.inl: project_velocity): ApplyJT g_i = (M^-1 J^T p)_i, and ApplyJ q_i = (J g)_i together with
// the Jacobi preconditioner diag_i = sum_k |grad_k C_i|^2 / m_k.
template <bool Adaptive>
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
        float hi = Adaptive ? radii.radius_of_mass(mi) : cp.h0;
        float li = p[i];
        Vec3 dv{0, 0, 0};
        for_each_fluid_neighbor<Adaptive>(grid, fluid, i, xi, cp.h0, [&](uint32_t j, Vec3 r, float r2) {
            if (j == i) return;
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : cp.h0;
            Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
            dv += (li * mj / mi + p[j]) * gw;
        });
        if (boundary.start && near_wall(grid, xi, cp.h0)) {
            for_each_neighbor(grid, boundary, xi, cp.h0, [&](uint32_t b, Vec3 r, float r2) {
                float mb = boundary.pos[b].w;
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, cp.h0) : spiky_gradient(r, r2, hi);
                dv += (li * mb / mi) * gw;
            });
        }
        g[i] = make_float4(cp.inv_rest_density * dv, 0.0f);
    }
};

template <bool Adaptive>
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
        float hi = Adaptive ? radii.radius_of_mass(mi) : cp.h0;
        Vec3 ui = xyz(u[i]);
        float div = 0.0f;
        Vec3 grad_i{0, 0, 0};
        float sum_grad2 = 0.0f;
        for_each_fluid_neighbor<Adaptive>(grid, fluid, i, xi, cp.h0, [&](uint32_t j, Vec3 r, float r2) {
            if (j == i) return;
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : cp.h0;
            Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
            div += mj * dot(ui - xyz(u[j]), gw);
            if (diag) {
                Vec3 gj = (mj * cp.inv_rest_density) * gw;
                grad_i += gj;
                sum_grad2 += dot(gj, gj) / mj;
            }
        });
        if (boundary.start && near_wall(grid, xi, cp.h0)) {
            for_each_neighbor(grid, boundary, xi, cp.h0, [&](uint32_t b, Vec3 r, float r2) {
                float mb = boundary.pos[b].w;
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, cp.h0) : spiky_gradient(r, r2, hi);
                div += mb * dot(ui, gw);
                if (diag) grad_i += (mb * cp.inv_rest_density) * gw;
            });
        }
        q[i] = div * cp.inv_rest_density;
        if (diag) diag[i] = dot(grad_i, grad_i) / mi + sum_grad2;
    }
};

// Position correction dp_i (Macklin eq. 12-14, with the tensile term s_corr) applied to the
// predicted position; writes into a second buffer (Jacobi iteration), clamps to the walls.
template <bool Adaptive>
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
        float hi = Adaptive ? radii.radius_of_mass(mi) : cp.h0;
        float li = lambda[i];
        Vec3 dp{0, 0, 0};
        for_each_fluid_neighbor<Adaptive>(grid, fluid, i, xi, cp.h0, [&](uint32_t j, Vec3 r, float r2) {
            if (j == i) return;
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : cp.h0;
            float s = 0.0f;
            if (cp.scorr_k_lambda > 0.0f) {
                // W(r) / W(dq h) with the pair's own kernel (eq. 19) at dq times the pair's mean radius, so a fine
                // pair at its own spacing feels what a level-0 pair does at its spacing.
                float ratio;
                if (Adaptive) {
                    float hm = cp.scorr_dq * 0.5f * (hi + hj);
                    float wdq = poly6_sym(hm * hm, hi, hj);
                    ratio = wdq > 0.0f ? poly6_sym(r2, hi, hj) / wdq : 0.0f;
                } else {
                    ratio = poly6(r2, hi) * cp.scorr_inv_wdq;
                }
                float p = ratio;
                for (int k = 1; k < cp.scorr_n; ++k) p *= ratio;
                s = -cp.scorr_k_lambda * p;
                if (Adaptive) {
                    // lambda_ref (a unit violation's lambda) scales as h^5 (sum |grad C|^2 / m ~ m / h^8, m ~ h^3),
                    // so the displacement s grad W / rho0 scales with h at every level, as it does at level 0.
                    float q = 0.5f * (hi + hj) / cp.h0;
                    s *= q * q * q * q * q;
                }
            }
            Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
            dp += (li * mj / mi + lambda[j] + s) * gw;
        });
        if (boundary.start && near_wall(grid, xi, cp.h0)) {
            for_each_neighbor(grid, boundary, xi, cp.h0, [&](uint32_t b, Vec3 r, float r2) {
                float mb = boundary.pos[b].w;
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, cp.h0) : spiky_gradient(r, r2, hi);
                dp += (li * mb / mi) * gw;
            });
        }
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
template <bool Adaptive>
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
        float hi = Adaptive ? radii.radius_of_mass(pi.w) : h0;
        Vec3 vi = xyz(vel[i]);
        Vec3 visc{0, 0, 0};
        Vec3 lap{0, 0, 0};
        Vec3 w{0, 0, 0};
        for_each_fluid_neighbor<Adaptive>(grid, fluid, i, xi, h0, [&](uint32_t j, Vec3 r, float r2) {
            if (j == i) return;
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : h0;
            float vol = mj / density[j];
            Vec3 dv = xyz(vel[j]) - vi;
            if (xsph > 0.0f) visc += (vol * (Adaptive ? poly6_sym(r2, hi, hj) : poly6(r2, hi))) * dv;
            if (want_vorticity || nu_dt > 0.0f) {
                Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
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
template <bool Adaptive>
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
        float hi = Adaptive ? radii.radius_of_mass(pi.w) : h0;
        float wi = omega[i].w;
        Vec3 eta{0, 0, 0};
        for_each_fluid_neighbor<Adaptive>(grid, fluid, i, xi, h0, [&](uint32_t j, Vec3 r, float r2) {
            if (j == i) return;
            float mj = fluid.pos[j].w;
            float hj = Adaptive ? radii.radius_of_mass(mj) : h0;
            Vec3 gw = Adaptive ? spiky_gradient_sym(r, r2, hi, hj) : spiky_gradient(r, r2, hi);
            eta += ((mj / density[j]) * (omega[j].w - wi)) * gw;
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
