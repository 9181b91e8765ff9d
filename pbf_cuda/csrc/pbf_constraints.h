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
//
// Gradient correction (pbf.gradient_correction; Bonet & Lok 1999, Randles & Libersky 1996): the projection's
// Jacobian uses L_i grad W_ij in row i, L_i = (sum_j V_j (x_j - x_i) (x) grad W_ij + walls)^-1, V_j = m_j / rho0.
// The plain SPH divergence of a smooth divergence-free flow is not zero on a disordered particle set (2.5-3%
// of |grad v| after 100-300 steps of the gravity wave), and each step's projection removes that misread part,
// which drains the flow's energy; the corrected divergence is exact for every linear field (0.2-0.3% there).
// Rows keep the form sum_j a_ij (v_i - v_j), so J^T mu still sums to zero over the fluid (momentum is kept),
// and ApplyJT is the exact transpose, so the projection stays M-orthogonal and never adds energy.
#pragma once
#include "common.h"
#include "grid.h"
#include "kernel_policy.h"
#include "kernels.h"
#include "neighbor_list.h"

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
    float scorr_fine;       // s_corr's weight on a pair with a particle finer than level 0 (adaptive runs)
};

// A symmetric 3x3 matrix (the gradient correction L_i), stored as 6 floats per particle.
struct Sym3 {
    float xx, xy, xz, yy, yz, zz;
    PBF_HD Vec3 operator*(Vec3 v) const {
        return Vec3{xx * v.x + xy * v.y + xz * v.z, xy * v.x + yy * v.y + yz * v.z, xz * v.x + yz * v.y + zz * v.z};
    }
    PBF_HD static Sym3 load(const float* a, uint32_t i) {
        const float* e = a + 6 * std::size_t(i);
        return Sym3{e[0], e[1], e[2], e[3], e[4], e[5]};
    }
    PBF_HD void store(float* a, uint32_t i) const {
        float* e = a + 6 * std::size_t(i);
        e[0] = xx; e[1] = xy; e[2] = xz; e[3] = yy; e[4] = yz; e[5] = zz;
    }
};

// ---- the neighbour sums the four constraint kernels share ---------------------------------------
// The density constraint's walls around fluid particle i at xi: on_wall(r, r2, m_b) for every boundary particle
// within h0 when i is near a wall (boundary particles have the level-0 radius h0), from the walls' table (grid.h).
// Called alone by the sums that add the walls after their fluid pairs.
template <class Wall>
PBF_HD inline void for_each_constraint_wall(const GridGeometry& grid, const WallNeighbourhoods& walls, float h0,
                                            Vec3 xi, Wall&& on_wall) {
    if (walls.offset && near_wall(grid, xi, h0)) for_each_wall_neighbor<kListBatch>(grid, walls, xi, h0, on_wall);
}

// The density constraint's neighbourhood of fluid particle i at xi: on_fluid(j, r, r2, m_j, h_j) for every fluid
// neighbour (i itself included, r2 = 0), then its walls (for_each_constraint_wall).
template <class Policy, class Fluid, class Wall>
PBF_HD inline void for_each_constraint_neighbor(const GridGeometry& grid, const CellRanges& fluid,
                                                const WallNeighbourhoods& walls, const LevelRadii& radii, float h0,
                                                uint32_t i, Vec3 xi, Fluid&& on_fluid, Wall&& on_wall) {
    for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xi, on_fluid);
    for_each_constraint_wall(grid, walls, h0, xi, on_wall);
}

// The same with data of each fluid candidate read beside its position: on_fluid(j, r, r2, m_j, h_j, gather(j))
// (for_each_fluid_neighbor_gathered).
template <class Policy, class Gather, class Fluid, class Wall>
PBF_HD inline void for_each_constraint_neighbor_gathered(const GridGeometry& grid, const CellRanges& fluid,
                                                         const WallNeighbourhoods& walls, const LevelRadii& radii,
                                                         float h0, uint32_t i, Vec3 xi, Gather&& gather,
                                                         Fluid&& on_fluid, Wall&& on_wall) {
    for_each_fluid_neighbor_gathered<Policy>(grid, fluid, radii, h0, i, xi, gather, on_fluid);
    for_each_constraint_wall(grid, walls, h0, xi, on_wall);
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

// (M^-1 J^T a)_i rho0 = sum_j coef(r2, m_j, h_j, a_j) grad W_ij + sum_b (a_i m_b / m_i) grad W_ib, with coef the
// fluid pair's weight a_i m_j / m_i + a_j (+ the tensile term): the position correction (Macklin eq. 12-14,
// a = lambda) and the velocity projection's M^-1 J^T (a = mu) are this one sum. Its wall terms, added to sum after
// the fluid pairs as for_each_constraint_neighbor visits them:
template <class Policy>
PBF_HD inline void add_wall_terms_transposed(const GridGeometry& grid, const WallNeighbourhoods& walls, float h0,
                                             Vec3 xi, float hi, float ai, float mi, Vec3& sum) {
    for_each_constraint_wall(grid, walls, h0, xi, [&](Vec3 r, float r2, float mb) {
        sum += (ai * mb / mi) * Policy::grad_W(r, r2, hi, h0);
    });
}

// a_j is read with j's position (for_each_fluid_neighbor_gathered) and handed to coef(r2, m_j, h_j, a_j).
template <class Policy, class Coef>
PBF_HD inline Vec3 sum_transposed(const GridGeometry& grid, const CellRanges& fluid,
                                  const WallNeighbourhoods& walls, const LevelRadii& radii, float h0, uint32_t i,
                                  Vec3 xi, float hi, float ai, float mi, const float* a, Coef&& coef) {
    Vec3 sum{0, 0, 0};
    for_each_fluid_neighbor_gathered<Policy>(grid, fluid, radii, h0, i, xi, [&](uint32_t j) { return a[j]; },
                                             [&](uint32_t j, Vec3 r, float r2, float mj, float hj, float aj) {
        if (j == i) return;
        float c = coef(r2, mj, hj, aj);
        sum += c * Policy::grad_W(r, r2, hi, hj);
    });
    add_wall_terms_transposed<Policy>(grid, walls, h0, xi, hi, ai, mi, sum);
    return sum;
}

// The velocity projection's warm start g = M^-1 J^T mu (ApplyJT below with the previous step's impulse mu) summed
// by another pass over the pairs at x*, the XSPH pass (ViscosityVorticity below), which visits them in ApplyJT's
// order: the fluid pairs in list order, then the walls (add_wall_terms_transposed), so g is ApplyJT's (bitwise on the
// CPU; on the GPU the two kernels may be contracted into FMAs differently) and the projection starts one neighbour
// pass later into its work (pbf_constraints_launch.h: solve_divergence).
// Only without the gradient correction, whose L is formed when the projection starts.
template <class Policy>
struct WarmStartImpulse {
    WallNeighbourhoods walls;
    ConstraintParams cp;
    const float* mu = nullptr;   // the previous step's impulse
    Float4* out = nullptr;       // g; nullptr: not summed by this pass
    PBF_HD void add_fluid(Vec3& sum, float mu_i, float mi, uint32_t j, float mj, Vec3 gw) const {
        float c = mu_i * mj / mi + mu[j];
        sum += c * gw;
    }
    PBF_HD void finish(const GridGeometry& grid, uint32_t i, Vec3 xi, float hi, float mu_i, float mi, Vec3 sum) const {
        add_wall_terms_transposed<Policy>(grid, walls, cp.h0, xi, hi, mu_i, mi, sum);
        out[i] = make_float4(cp.inv_rest_density * sum, 0.0f);
    }
};

// Density (eq. 1, 18) and lambda (eq. 4) of fluid particle i. Its sums (add, finish) are also taken along by the
// lists' build, which finds the pairs of the first density iteration in the order the lists will hold them
// (neighbor_list.h: FillNeighbors), so that iteration needs no pass of its own.
template <class Policy>
struct DensityLambda {
    GridGeometry grid;
    CellRanges fluid;
    WallNeighbourhoods walls;  // walls.offset == nullptr: no walls
    LevelRadii radii;
    ConstraintParams cp;
    float* lambda;
    float* density;
    struct Sums {
        float rho = 0.0f;
        JacobianRow row;
    };
    // fluid pair (i, j) within its support, i itself included (r2 = 0)
    PBF_HD void add(Sums& s, uint32_t i, uint32_t j, Vec3 r, float r2, float hi, float mj, float hj) const {
        s.rho += mj * Policy::W(r2, hi, hj);
        if (j != i) s.row.add_fluid(Policy::grad_W(r, r2, hi, hj), mj, cp.inv_rest_density);
    }
    // the walls (for_each_constraint_neighbor's order: after the fluid pairs), then lambda and the density
    PBF_HD void finish(Sums& s, uint32_t i, Vec3 xi, float mi, float hi) const {
        for_each_constraint_wall(grid, walls, cp.h0, xi, [&](Vec3 r, float r2, float mb) {
            s.rho += mb * Policy::W(r2, hi, cp.h0);
            s.row.add_wall(Policy::grad_W(r, r2, hi, cp.h0), mb, cp.inv_rest_density);
        });
        float c = s.rho * cp.inv_rest_density - 1.0f;
        if (cp.unilateral && c < 0.0f) c = 0.0f;
        float denom = s.row.diagonal(mi) + cp.relaxation;
        lambda[i] = denom > 0.0f ? -c / denom : 0.0f;
        density[i] = s.rho;
    }
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        Sums s;
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, cp.h0, i, xi,
            [&](uint32_t j, Vec3 r, float r2, float mj, float hj) { add(s, i, j, r, r2, hi, mj, hj); });
        finish(s, i, xi, mi, hi);
    }
};

// L_i = B_i^-1, B_i = sum_j V_j (x_j - x_i) (x) grad W_ij + sum_b V_b (x_b - x_i) (x) grad W_ib (symmetric positive
// definite: grad W_ij is a negative multiple of x_i - x_j). Where B_i is near singular (det below 1e-3 of
// (trace / 3)^3: a particle with too few neighbours in some direction) L_i = identity, the plain gradient.
template <class Policy>
struct GradientCorrection {
    GridGeometry grid;
    CellRanges fluid;
    WallNeighbourhoods walls;
    LevelRadii radii;
    ConstraintParams cp;
    float* correction;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float hi = Policy::radius(radii, cp.h0, pi.w);
        float b[6] = {0, 0, 0, 0, 0, 0};
        auto add = [&](Vec3 r, Vec3 gw, float volume) {   // volume (x_j - x_i) (x) grad W_ij, r = x_i - x_j
            Vec3 d = -volume * r;
            b[0] += d.x * gw.x; b[1] += 0.5f * (d.x * gw.y + d.y * gw.x); b[2] += 0.5f * (d.x * gw.z + d.z * gw.x);
            b[3] += d.y * gw.y; b[4] += 0.5f * (d.y * gw.z + d.z * gw.y); b[5] += d.z * gw.z;
        };
        for_each_constraint_neighbor<Policy>(grid, fluid, walls, radii, cp.h0, i, xi,
            [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
                if (j != i) add(r, Policy::grad_W(r, r2, hi, hj), mj * cp.inv_rest_density);
            },
            [&](Vec3 r, float r2, float mb) { add(r, Policy::grad_W(r, r2, hi, cp.h0), mb * cp.inv_rest_density); });
        // inverse by cofactors
        float c00 = b[3] * b[5] - b[4] * b[4], c01 = b[2] * b[4] - b[1] * b[5], c02 = b[1] * b[4] - b[2] * b[3];
        float det = b[0] * c00 + b[1] * c01 + b[2] * c02;
        float t = (b[0] + b[3] + b[5]) / 3.0f;
        Sym3 l{1, 0, 0, 1, 0, 1};
        if (t > 0.0f && det > 1e-3f * t * t * t) {
            float inv = 1.0f / det;
            l = Sym3{c00 * inv, c01 * inv, c02 * inv, (b[0] * b[5] - b[2] * b[2]) * inv,
                     (b[1] * b[2] - b[0] * b[4]) * inv, (b[0] * b[3] - b[1] * b[1]) * inv};
        }
        l.store(correction, i);
    }
};

// The two halves of A = J M^-1 J^T for the velocity projection's conjugate gradient solve
// (pbf_constraints_launch.h: project_velocity): ApplyJT g_i = (M^-1 J^T p)_i, and ApplyJ q_i = (J g)_i together
// with the Jacobi preconditioner diag_i = sum_k |grad_k C_i|^2 / m_k.
// Corrected: the Jacobian with the gradient correction L (GradientCorrection above); a template parameter, so the
// plain projection compiles to exactly the code it had without the option.
template <class Policy, bool Corrected = false>
struct ApplyJT {
    GridGeometry grid;
    CellRanges fluid;
    WallNeighbourhoods walls;
    LevelRadii radii;
    ConstraintParams cp;
    const float* p;
    Float4* g;
    const float* correction;   // L, read when Corrected
    const int* stop = nullptr; // *stop set: nothing to do (the conjugate gradients have stopped)
    PBF_HD void operator()(uint32_t i) const {
        if (stop && *stop) return;
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        float li = p[i];
        if constexpr (!Corrected) {
            Vec3 dv = sum_transposed<Policy>(grid, fluid, walls, radii, cp.h0, i, xi, hi, li, mi, p,
                                             [&](float, float mj, float, float pj) { return li * mj / mi + pj; });
            g[i] = make_float4(cp.inv_rest_density * dv, 0.0f);
        } else {
            // (M^-1 J^T p)_i rho0 = L_i (sum_j p_i m_j / m_i grad W_ij + walls) + sum_j p_j L_j grad W_ij
            Vec3 own{0, 0, 0}, others{0, 0, 0};
            for_each_constraint_neighbor<Policy>(grid, fluid, walls, radii, cp.h0, i, xi,
                [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
                    if (j == i) return;
                    Vec3 gw = Policy::grad_W(r, r2, hi, hj);
                    own += (li * mj / mi) * gw;
                    others += p[j] * (Sym3::load(correction, j) * gw);
                },
                [&](Vec3 r, float r2, float mb) { own += (li * mb / mi) * Policy::grad_W(r, r2, hi, cp.h0); });
            Vec3 dv = Sym3::load(correction, i) * own + others;
            g[i] = make_float4(cp.inv_rest_density * dv, 0.0f);
        }
    }
};

template <class Policy, bool Corrected = false>
struct ApplyJ {
    GridGeometry grid;
    CellRanges fluid;
    WallNeighbourhoods walls;
    LevelRadii radii;
    ConstraintParams cp;
    const Float4* u;
    float* q;
    float* diag;               // nullptr: not written
    const float* correction;   // L, read when Corrected
    const int* stop = nullptr; // *stop set: nothing to do (the conjugate gradients have stopped)
    // Where set (the first call, with diag): the conjugate gradients' start r = -J u, p = D^-1 r, with r in q.
    float* start_direction = nullptr;
    PBF_HD void operator()(uint32_t i) const {
        if (stop && *stop) return;
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, cp.h0, mi);
        Vec3 ui = xyz(u[i]);
        float div = 0.0f;
        JacobianRow row;
        Sym3 li{1, 0, 0, 1, 0, 1};
        if constexpr (Corrected) li = Sym3::load(correction, i);
        for_each_constraint_neighbor_gathered<Policy>(grid, fluid, walls, radii, cp.h0, i, xi,
            [&](uint32_t j) { return u[j]; },
            [&](uint32_t j, Vec3 r, float r2, float mj, float hj, const Float4& uj) {
                if (j == i) return;
                Vec3 gw = Policy::grad_W(r, r2, hi, hj);
                if constexpr (Corrected) gw = li * gw;
                div += mj * dot(ui - xyz(uj), gw);
                if (diag) row.add_fluid(gw, mj, cp.inv_rest_density);
            },
            [&](Vec3 r, float r2, float mb) {
                Vec3 gw = Policy::grad_W(r, r2, hi, cp.h0);
                if constexpr (Corrected) gw = li * gw;
                div += mb * dot(ui, gw);
                if (diag) row.add_wall(gw, mb, cp.inv_rest_density);
            });
        const float qi = div * cp.inv_rest_density;
        if (start_direction) {
            const float ri = -qi, di = row.diagonal(mi);
            q[i] = ri;
            diag[i] = di;
            start_direction[i] = di > 0.0f ? ri / di : 0.0f;
            return;
        }
        q[i] = qi;
        if (diag) diag[i] = row.diagonal(mi);
    }
};

// x^n for n >= 1 as the product ((x x) x) ... in that order; n = 4, the default pbf.scorr_n, without the loop (a
// uniform branch: n is the run's), which every pair of a PositionCorrection pass would otherwise run.
PBF_HD inline float repeated_product(float x, int n) {
    if (n == 4) return x * x * x * x;
    float p = x;
    for (int k = 1; k < n; ++k) p *= x;
    return p;
}

// Position correction dp_i (Macklin eq. 12-14, with the tensile term s_corr) applied to the
// predicted position; writes into a second buffer (Jacobi iteration), clamps to the walls.
template <class Policy>
struct PositionCorrection {
    GridGeometry grid;
    CellRanges fluid;
    WallNeighbourhoods walls;
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
        Vec3 dp = sum_transposed<Policy>(grid, fluid, walls, radii, cp.h0, i, xi, hi, li, mi, lambda,
                                         [&](float r2, float mj, float hj, float lambda_j) {
            float s = 0.0f;
            // s_corr = -k (W(r) / W(dq h))^n: between level-0 particles as in a uniform run, on a pair with a
            // fine particle at the pair's radii (policy) times scorr_fine; a pair it weighs 0 skips the kernels
            // (the shipped adaptive scenes: every fine pair).
            const bool fine_pair = hi < cp.h0 || hj < cp.h0;
            if (cp.scorr_k_lambda > 0.0f && !(fine_pair && cp.scorr_fine == 0.0f)) {
                float ratio = fine_pair ? Policy::tensile_ratio(r2, hi, hj, cp.scorr_dq, cp.scorr_inv_wdq)
                                        : UniformPolicy::tensile_ratio(r2, hi, hj, cp.scorr_dq, cp.scorr_inv_wdq);
                s = -cp.scorr_k_lambda * repeated_product(ratio, cp.scorr_n);
                if (fine_pair) s = Policy::tensile_scale(s, hi, hj, cp.h0) * cp.scorr_fine;
            }
            return li * mj / mi + lambda_j + s;
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
//
// Taken along, on the same pairs at the same positions in the same order (each where its pointer is set):
//   pair_sum     a sum a later pass of the step needs (the smoothing limiter's S_i, smoothing.h: LimiterWeight):
//                pair_sum(r, r2, h_i, h_j, m_j) summed over j != i into pair_sum.out[i];
//   narrowing    the lists narrowed to the pairs within support at x* (neighbor_list.h: RowNarrowing), for the
//                passes after this one;
//   warm_start   the velocity projection's first M^-1 J^T mu (WarmStartImpulse above).
template <class Policy, class PairSum>
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
    PairSum pair_sum;
    RowNarrowing narrowing;
    WarmStartImpulse<Policy> warm_start;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float mi = pi.w;
        float hi = Policy::radius(radii, h0, mi);
        Vec3 vi = xyz(vel[i]);
        Vec3 visc{0, 0, 0};
        Vec3 lap{0, 0, 0};
        Vec3 w{0, 0, 0};
        float summed = 0.0f;
        const bool warm = warm_start.out != nullptr;
        const float mu_i = warm ? warm_start.mu[i] : 0.0f;
        Vec3 impulse{0, 0, 0};
        const bool narrow = narrowing.count && fluid.listed(i);   // a row cut at the width stays as it is
        RowNarrowing::Cursor kept{};
        if (narrow) kept = narrowing.begin(i);
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xi, [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (narrow) narrowing.keep(kept, j);
            if (j == i) return;
            if (pair_sum.out) summed += pair_sum(r, r2, hi, hj, mj);
            float vol = mj / density[j];
            Vec3 dv = xyz(vel[j]) - vi;
            if (xsph > 0.0f) visc += (vol * Policy::W(r2, hi, hj)) * dv;
            if (want_vorticity || nu_dt > 0.0f || warm) {
                Vec3 gw = Policy::grad_W(r, r2, hi, hj);
                if (want_vorticity) w += vol * cross(gw, dv);
                if (nu_dt > 0.0f) lap -= (2.0f * mj * inv_rest_density * dot(r, gw) / (r2 + 0.01f * hi * hj)) * dv;
                if (warm) warm_start.add_fluid(impulse, mu_i, mi, j, mj, gw);
            }
        });
        vel_out[i] = make_float4(vi + xsph * visc + nu_dt * lap, 0.0f);
        if (want_vorticity) omega[i] = make_float4(w, length(w));
        if (pair_sum.out) pair_sum.out[i] = summed;
        if (narrow) narrowing.finish(i, kept);
        if (warm) warm_start.finish(grid, i, xi, hi, mu_i, mi, impulse);
    }
};

// Vorticity confinement force f_i = eps (N x omega_i), N = eta / |eta|, eta = grad |omega|
// (Macklin eq. 16), added to the velocity over one step: eta summed over the pairs j != i (add), then the force
// applied (apply). A pass of its own (VorticityConfinement below), or taken along by the smoothing pass, which
// visits the same pairs at x* in the same order (SmoothScalars, smoothing.h), so the velocities are the same (bitwise
// on the CPU; on the GPU the two kernels may be contracted into FMAs differently).
struct ConfinementSum {
    float epsilon;
    float dt;
    const float* density;
    const Float4* omega;   // xyz = omega, w = |omega| (ViscosityVorticity)
    Float4* vel = nullptr; // nullptr: no vorticity confinement in this pass
    PBF_HD void add(Vec3& eta, float wi, uint32_t j, float mj, Vec3 gw) const {
        eta += ((mj / density[j]) * (omega[j].w - wi)) * gw;
    }
    PBF_HD void apply(uint32_t i, Vec3 eta) const {
        float len = length(eta);
        if (len > 1e-20f) {
            Vec3 n = (1.0f / len) * eta;
            Vec3 f = epsilon * cross(n, xyz(omega[i]));
            Float4 v = vel[i];
            vel[i] = Float4{v.x + dt * f.x, v.y + dt * f.y, v.z + dt * f.z, v.w};
        }
    }
};

template <class Policy>
struct VorticityConfinement {
    GridGeometry grid;
    CellRanges fluid;
    LevelRadii radii;
    float h0;
    ConfinementSum confinement;
    PBF_HD void operator()(uint32_t i) const {
        Float4 pi = fluid.pos[i];
        Vec3 xi = xyz(pi);
        float hi = Policy::radius(radii, h0, pi.w);
        float wi = confinement.omega[i].w;
        Vec3 eta{0, 0, 0};
        for_each_fluid_neighbor<Policy>(grid, fluid, radii, h0, i, xi, [&](uint32_t j, Vec3 r, float r2, float mj, float hj) {
            if (j == i) return;
            confinement.add(eta, wi, j, mj, Policy::grad_W(r, r2, hi, hj));
        });
        confinement.apply(i, eta);
    }
};

// Column drift. In a box closed at the floor and the lid, incompressible air has no net vertical momentum:
// the flux through every horizontal plane is zero (the volume below it is closed), so the integral of u_y
// over the box is too. A drift of the whole column is the velocity projection's slowest mode: its SPH
// divergence is zero except in the layers next to the floor and the lid, and a few conjugate-gradient
// iterations do not carry the column-high pressure that stops it. What the projection leaves of it (the
// horizontal mean of eq. 6's buoyancy, the walls' reactions) lifts the column as a whole: the air next
// to the floor rarefies and the mass centre rises (docs/physics.md, Column drift). Subtracting the
// mass-weighted mean u_y, P = sum m u_y / sum m, is the M-orthogonal projection onto zero net momentum:
// it removes M P^2 / 2 of kinetic energy and never adds any. One mode only: removing the mean per height
// bin instead also fights the bins' sampling noise, and drained a gravity wave (38% of its energy in two
// periods against 17% without). The grid baseline needs no such step: its pressure solve is exact.
struct Double2 {
    double x, y;
};
struct Double2Add {
    PBF_HD Double2 operator()(const Double2& a, const Double2& b) const { return Double2{a.x + b.x, a.y + b.y}; }
};

// The scalars of the velocity projection's conjugate gradients, kept in device memory (pbf_constraints_launch.h:
// solve_divergence): the reductions write them and, in their last block, turn them into the new direction's weight
// and the stop flag; the vector kernels read them (and form the step size), so the host never waits for a dot product.
struct CgState {
    double rz;          // r . z of the current residual (z = D^-1 r)
    Double2 dots;       // the residual's last reduction: (r . z, r . r)
    Double2 direction;  // the direction's last reduction: (p . A p, p . D p)
    float beta;         // the weight of the old direction in the new one (the step along p: CgUpdate)
    int stop;           // 1: converged or stalled; the remaining iterations leave v and mu as they are
};

// y -= shift, kept inside the floor and the lid (the density solve's share of the column drift), m. The shift is
// read from device memory (ColumnShift, pbf_constraints_launch.h); where the column has no mass it stays put.
struct RemoveVerticalShift {
    Float4* pos;
    const float* shift;
    const Double2* mass_sums;   // .y: sum m
    float top;
    PBF_HD void operator()(uint32_t i) const {
        if (!(mass_sums->y > 0.0)) return;
        Float4 x = pos[i];
        float y = x.y - *shift;
        y = y < 0.0f ? 0.0f : (y > top ? top : y);
        pos[i] = Float4{x.x, y, x.z, x.w};
    }
};

// (sum m u_y, sum m) of the fluid particles, kg m/s and kg.
struct VerticalMomentum {
    const Float4* pos;   // .w: mass, kg
    const Float4* vel;
    PBF_HD Double2 operator()(uint32_t i) const {
        double m = pos[i].w, u = vel[i].y;
        if (!(fabs(u) < 1e30)) return Double2{0.0, 0.0};   // a NaN particle stays the one the step's check names
        return Double2{m * u, m};
    }
};

// u_y -= drift = sum m u_y / sum m, m/s, from the sums in device memory (each thread forms the same drift; no change
// where the column has no mass).
struct RemoveVerticalDrift {
    Float4* vel;
    const Double2* column;   // (sum m u_y, sum m)
    PBF_HD void operator()(uint32_t i) const {
        if (!(column->y > 0.0)) return;
        const float drift = float(column->x / column->y);
        Float4 u = vel[i];
        vel[i] = Float4{u.x, u.y - drift, u.z, u.w};
    }
};

}  // namespace pbf
