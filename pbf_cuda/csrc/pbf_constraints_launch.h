// Launch code of the PBF phase (Macklin & Mueller 2013, Algorithm 1; paper eq. 1-4, 18; pbf_constraints.h):
// prediction, the density constraint's Jacobi iterations, the velocity update, XSPH / viscosity / vorticity
// confinement, and the divergence-free velocity projection of closed domains.
//
// Two ways to keep the fluid incompressible (Params::velocity_projection):
//  - position projection (Macklin & Mueller): the velocity is (x* - x) / dt after the density
//    constraint moved x*. Right for free surfaces (unilateral constraint), but every density error
//    left by the few Jacobi iterations comes back as velocity in the next step: it adds energy.
//  - velocity projection (closed domains, the atmosphere): the velocity is projected onto J v = 0
//    (divergence-free, pbf_constraints.h) after all forces, and the density constraint only moves
//    positions. The projection is M-orthogonal, so it removes only the compressing part of the flow
//    and never adds kinetic energy; the density constraint is bilateral, so heated air cannot leave a
//    rarefied layer behind.
#pragma once
#include <thrust/functional.h>

#include <algorithm>
#include <cmath>

#include "device_memory.h"
#include "kernels.h"
#include "parallel_for.h"
#include "pbf_constraints.h"
#include "reduce.h"
#include "solver_data.h"

namespace pbf {
namespace PBF_BACKEND_NS {

struct Predict {
    Float4* vel;
    const Float4* pos;
    Float4* pred;
    Vec3 gravity;
    float dt;
    PBF_HD void operator()(uint32_t i) const {
        Float4 v = vel[i];
        Vec3 u = xyz(v) + dt * gravity;
        vel[i] = make_float4(u, v.w);
        Float4 p = pos[i];
        pred[i] = make_float4(xyz(p) + dt * u, p.w);
    }
};

struct UpdateVelocity {
    const Float4* pos;
    const Float4* pred;
    Float4* vel;
    float inv_dt;
    PBF_HD void operator()(uint32_t i) const {
        vel[i] = make_float4(inv_dt * (xyz(pred[i]) - xyz(pos[i])), 0.0f);
    }
};

// Conjugate-gradient helpers of the velocity projection (z = r / diag is the Jacobi preconditioner; the start
// r = -J v, p = z is written by the first ApplyJ, pbf_constraints.h). The scalars
// live in a CgState in device memory (pbf_constraints.h); the vector kernels read them and do nothing once
// state->stop is set.
// (a . b, c . d) in double.
struct CgDots {
    const float *a, *b, *c, *d;
    PBF_HD Double2 operator()(uint32_t i) const {
        return Double2{double(a[i]) * double(b[i]), double(c[i]) * double(d[i])};
    }
};
// (p . A p, p . D p): q = A p.
struct CgDirectionDots {
    const float* p;
    const float* q;
    const float* diag;
    PBF_HD Double2 operator()(uint32_t i) const {
        return Double2{double(p[i]) * double(q[i]), double(p[i]) * p[i] * diag[i]};
    }
};
// (p . A p, p . D p) without q: p . A p = p . J M^-1 J^T p = (M g) . g = sum_i m_i |g_i|^2 for g = M^-1 J^T p
// (ApplyJT is the exact transpose of ApplyJ), so the last iteration, whose q would only update a residual no one
// reads, needs no ApplyJ pass.
struct CgDirectionEnergy {
    const Float4* pos;   // w: mass
    const Float4* g;
    const float* p;
    const float* diag;
    PBF_HD Double2 operator()(uint32_t i) const {
        const Float4 gi = g[i];
        const double g2 = double(gi.x) * gi.x + double(gi.y) * gi.y + double(gi.z) * gi.z;
        return Double2{double(pos[i].w) * g2, double(p[i]) * p[i] * diag[i]};
    }
};
// (r . D^-1 r, r . r).
struct CgResidualDots {
    const float* r;
    const float* diag;
    PBF_HD Double2 operator()(uint32_t i) const {
        return Double2{diag[i] > 0.0f ? double(r[i]) * r[i] / diag[i] : 0.0, double(r[i]) * double(r[i])};
    }
};
// The first residual: rz = r . z; stop where it is zero or already below the tolerance (rr <= tol2).
struct CgBegin {
    CgState* s;
    double tol2;
    PBF_HD void operator()() const {
        s->rz = s->dots.x;
        s->stop = !(s->rz > 0.0) || (tol2 > 0.0 && s->dots.y <= tol2);
    }
};
// A direction whose Rayleigh quotient p.A p / p.D p is tiny lies in the near-null space of A (modes the SPH
// divergence barely sees); float32 matrix products cannot resolve it, and a step along it would be huge and
// arbitrary: no step is taken along it (CgUpdate), and the solve stops there (CgNextDirection).
PBF_HD inline bool cg_step_resolved(const Double2& direction) { return direction.x > 1e-5 * direction.y; }

// beta = rz_new / rz for the next direction; stop where the last direction was not resolved or the new residual is
// below the tolerance.
struct CgNextDirection {
    CgState* s;
    double tol2;
    PBF_HD void operator()() const {
        if (s->stop) return;
        if (!cg_step_resolved(s->direction)) {
            s->stop = 1;
            return;
        }
        s->beta = float(s->dots.x / s->rz);
        s->rz = s->dots.x;
        s->stop = !(s->rz > 0.0) || (tol2 > 0.0 && s->dots.y <= tol2);
    }
};
// v += alpha g; r -= alpha q; mu += alpha p, with alpha = rz / p.A p from the direction's reduction (each thread
// forms the same alpha); nothing where the direction is not resolved (cg_step_resolved).
struct CgUpdate {
    const CgState* s;
    const Float4* g;
    const float* q;      // nullptr: the last iteration, the residual is not updated
    const float* p;
    Float4* v;
    float* r;
    float* mu;
    PBF_HD void operator()(uint32_t i) const {
        if (s->stop || !cg_step_resolved(s->direction)) return;
        const float alpha = float(s->rz / s->direction.x);
        Float4 a = v[i], b = g[i];
        v[i] = Float4{a.x + alpha * b.x, a.y + alpha * b.y, a.z + alpha * b.z, a.w};
        if (q) r[i] -= alpha * q[i];
        mu[i] += alpha * p[i];
    }
};
struct CgDirection {
    const CgState* s;
    const float* r;
    const float* diag;
    float* p;
    PBF_HD void operator()(uint32_t i) const {
        if (s->stop) return;
        float z = diag[i] > 0.0f ? r[i] / diag[i] : 0.0f;
        p[i] = z + s->beta * p[i];
    }
};

// The density solve's net vertical shift (sum m y after - before) / sum m, m, from its sums in device memory (0
// where the column has no mass); run by the last block of the sum after (reduce_into's then).
struct ColumnShift {
    StepSums* s;
    PBF_HD void operator()() const {
        s->shift = s->shift_before.y > 0.0 ? float((s->shift_after.x - s->shift_before.x) / s->shift_before.y) : 0.0f;
    }
};

// vel += uniform (where with_uniform: gravity's dt g), then vel += dv (per particle), in that order.
struct AddVelocity {
    const Float4* dv;
    Float4* vel;
    Vec3 uniform;
    bool with_uniform;
    PBF_HD void operator()(uint32_t i) const {
        Float4 v = vel[i], d = dv[i];
        if (with_uniform) v = Float4{v.x + uniform.x, v.y + uniform.y, v.z + uniform.z, v.w};
        vel[i] = Float4{v.x + d.x, v.y + d.y, v.z + d.z, v.w};
    }
};

// The constraint's constants (s_corr's reference W(dq h0) once per run).
inline ConstraintParams make_constraint_params(const Params& p) {
    ConstraintParams cp{};
    cp.rest_density = p.rest_density;
    cp.inv_rest_density = 1.0f / p.rest_density;
    cp.relaxation = p.relaxation;
    cp.h0 = p.h0;
    cp.unilateral = p.unilateral;
    cp.scorr_k_lambda = p.scorr_k * p.lambda_ref;
    cp.scorr_n = p.scorr_n;
    float wdq = poly6(p.scorr_dq * p.h0 * p.scorr_dq * p.h0, p.h0);
    cp.scorr_inv_wdq = wdq > 0.0f ? 1.0f / wdq : 0.0f;
    cp.scorr_dq = p.scorr_dq;
    cp.scorr_fine = p.scorr_fine;
    return cp;
}

inline Vec3 gravity_of(const Params& p) { return Vec3{p.gravity[0], p.gravity[1], p.gravity[2]}; }

// x* = x + dt (v + dt g); with the velocity projection gravity is added after the forces (project_velocity).
inline void predict_positions(SolverData& d) {
    const Vec3 g = d.p.velocity_projection ? Vec3{0, 0, 0} : gravity_of(d.p);
    parallel_for(d.n, Predict{raw(d.vel), raw(d.pos), raw(d.pred), g, d.p.dt});
}

struct KeepHeight {
    const Float4* pred;
    float* height;
    PBF_HD void operator()(uint32_t i) const { height[i] = pred[i].y; }
};
// shift = y(after) - y(before) of the density constraint; returns the heat its temperature change will book,
// m (Gamma_d shift + T0(y) - T0(y - shift)) (kg K; AtmosphereParams::shift_change).
struct VerticalShift {
    AtmosphereParams a;
    const Float4* pred;
    float* shift;
    PBF_HD double operator()(uint32_t i) const {
        float dy = pred[i].y - shift[i];
        shift[i] = dy;
        return double(pred[i].w) * double(a.shift_change(pred[i].y, dy));
    }
};

// The first density iteration's sums (DensityLambda at x* as predicted), for the lists' build to take along
// (build_neighbor_lists, FillNeighbors): that iteration then needs no pass of its own (solve_density).
template <class Policy>
DensityLambda<Policy> first_density_sums(SolverData& d, const WallNeighbourhoods& walls) {
    return DensityLambda<Policy>{d.grid, d.fluid_ranges(d.pred), walls, d.radii, d.cp, raw(d.lambda), raw(d.density)};
}

// Density constraint iterations on the predicted positions (eq. 1-4, 18). With pbf.shift_keeps_anomaly the
// vertical shift they give each particle is kept (d.shift_y) for the cloud dynamics (thermodynamics.h).
// first_summed: the lists' build has summed the first iteration's density and lambda (first_density_sums).
template <class Policy>
void solve_density(SolverData& d, const WallNeighbourhoods& walls, bool first_summed) {
    const bool keep_shift = !d.shift_y.empty();
    if (keep_shift) parallel_for(d.n, KeepHeight{raw(d.pred), raw(d.shift_y)});
    // pbf.remove_shift_drift: the solve's net vertical shift sum m dy / sum m is the closed column's rigid mode
    // (as the column drift is for velocities; docs/physics.md, Shift drift), subtracted from every particle afterwards.
    // VerticalMomentum with the positions in place of the velocities sums (m y, m).
    const bool closed_column = d.p.velocity_projection && d.p.remove_shift_drift && !d.p.periodic[1] && d.n > 0;
    StepSums* sums = raw(d.step_sums);
    if (closed_column)
        reduce_into(d.n, VerticalMomentum{raw(d.pred), raw(d.pred)}, Double2{0.0, 0.0}, Double2Add{}, &sums->shift_before);
    ConstraintParams cp = d.cp;                 // s_corr's k at this step (time_step.h: pbf.scorr_dt_power)
    cp.scorr_k_lambda *= d.rates.scorr;
    for (int it = 0; it < d.p.iterations; ++it) {
        CellRanges fl = d.fluid_ranges(d.pred);
        if (!(it == 0 && first_summed))
            parallel_for_in_order(d.n, d.list_pass_order(),
                                  DensityLambda<Policy>{d.grid, fl, walls, d.radii, d.cp, raw(d.lambda), raw(d.density)});
        parallel_for_in_order(d.n, d.list_pass_order(),
                              PositionCorrection<Policy>{d.grid, fl, walls, d.radii, cp, raw(d.lambda), raw(d.pos_tmp)});
        d.pred.swap(d.pos_tmp);
    }
    if (closed_column) {
        reduce_into(d.n, VerticalMomentum{raw(d.pred), raw(d.pred)}, Double2{0.0, 0.0}, Double2Add{}, &sums->shift_after,
                    ColumnShift{sums});
        parallel_for(d.n, RemoveVerticalShift{raw(d.pred), &sums->shift, &sums->shift_before, d.grid.domain[1]});
    }
    if (keep_shift)
        reduce_into(d.n, VerticalShift{d.atm, raw(d.pred), raw(d.shift_y)}, 0.0, thrust::plus<double>(), &sums->shift_heat);
}

// XSPH viscosity, physical viscosity or vorticity confinement switched on (viscosity_vorticity below).
inline bool viscosity_vorticity_active(const Params& p) {
    return p.xsph > 0.0f || p.vorticity > 0.0f || p.viscosity > 0.0f;
}

// Once the density iterations have placed x* for the step, the lists keep only the pairs within support there
// (RowNarrowing, neighbor_list.h), where neighbour passes follow the XSPH pass at x*: the velocity projection's
// 2 divergence_iterations + 1, smoothing (with the vorticity confinement, or the confinement's own pass). The XSPH
// pass takes the narrowing along (viscosity_vorticity below); where no XSPH pass runs, a pass of its own narrows
// the lists where at least three passes follow to pay for it. Where none follows (the dam break), nothing narrows:
// the XSPH pass's stores would only cost time (on the 2-core AMD the CPU dam break's step was a few percent slower
// with them).
inline int passes_after_xsph(const SolverData& d) {
    const Params& p = d.p;
    return (p.velocity_projection ? 2 * p.divergence_iterations + 1 : 0) + (p.vorticity > 0.0f ? 1 : 0) +
           (d.smoothing ? 1 : 0);
}

inline RowNarrowing list_narrowing(SolverData& d) {
    if (!d.lists_ready || passes_after_xsph(d) == 0) return RowNarrowing{};
    return RowNarrowing{raw(d.nbr_count), raw(d.nbr_index), d.nbr_row, d.nbr_slot};
}

template <class Policy>
void narrow_neighbor_lists(SolverData& d) {
    if (!d.lists_ready || passes_after_xsph(d) < 3) return;
    parallel_for(d.n, NarrowNeighbors<Policy>{d.grid, d.fluid_ranges(d.pred), d.radii, d.p.h0, list_narrowing(d)});
}

// v = (x* - x) / dt: the position projection's velocity (the velocity projection keeps v).
inline void update_velocity(SolverData& d) {
    if (!d.p.velocity_projection) parallel_for(d.n, UpdateVelocity{raw(d.pos), raw(d.pred), raw(d.vel), 1.0f / d.p.dt});
}

// The velocity projection's warm start M^-1 J^T mu_prev, summed by the XSPH pass where the projection runs without
// the gradient correction (WarmStartImpulse, pbf_constraints.h). It waits in pos_tmp, the density iterations' second
// buffer, which nothing reads between them and the next step's sort.
template <class Policy>
WarmStartImpulse<Policy> warm_start_impulse(SolverData& d, const WallNeighbourhoods& walls) {
    if (!d.p.velocity_projection || d.p.gradient_correction) return WarmStartImpulse<Policy>{walls, d.cp};
    return WarmStartImpulse<Policy>{walls, d.cp, raw(d.cg_mu), raw(d.pos_tmp)};
}

// The vorticity confinement (ConfinementSum, pbf_constraints.h) on this step's velocities; off (vel nullptr) where
// pbf.vorticity is 0. Where the smoothing pass runs it takes the confinement along (smoothing_launch.h), else it has
// a pass of its own after the XSPH pass (viscosity_vorticity below).
inline ConfinementSum confinement(SolverData& d) {
    if (!(d.p.vorticity > 0.0f)) return ConfinementSum{d.p.vorticity, d.p.dt, nullptr, nullptr};
    return ConfinementSum{d.p.vorticity, d.p.dt, raw(d.density), raw(d.omega), raw(d.vel)};
}

// What the XSPH pass took along (ViscosityVorticity): the pair sum's out, where set, holds its sums; the lists are
// narrowed; the warm start's impulse is in pos_tmp (warm_start_impulse).
struct XsphRiders {
    bool pair_sum = false, narrowed = false, warm_start = false;
};

// XSPH viscosity, physical viscosity and the vorticity omega (Macklin eq. 15-17), where switched on, with pair_sum,
// the lists' narrowing and the projection's warm start taken along (ViscosityVorticity), then the vorticity
// confinement where no smoothing pass takes it along. Returns what was taken along: nothing where the pass did not
// run.
template <class Policy, class PairSum>
XsphRiders viscosity_vorticity(SolverData& d, const PairSum& pair_sum, const WallNeighbourhoods& walls) {
    const Params& p = d.p;
    if (!viscosity_vorticity_active(p)) return XsphRiders{};
    const float dt = p.dt;
    CellRanges fl = d.fluid_ranges(d.pred);
    bool vort = p.vorticity > 0.0f;
    const RowNarrowing narrowing = list_narrowing(d);
    const WarmStartImpulse<Policy> warm = warm_start_impulse<Policy>(d, walls);
    parallel_for_in_order(d.n, d.list_pass_order(),
                          ViscosityVorticity<Policy, PairSum>{d.grid, fl, d.radii, p.h0, d.rates.xsph, p.viscosity * dt,
                                                              d.cp.inv_rest_density, vort, raw(d.vel), raw(d.density),
                                                              raw(d.vel_tmp), vort ? raw(d.omega) : nullptr, pair_sum,
                                                              narrowing, warm});
    d.vel.swap(d.vel_tmp);
    if (vort && !d.smoothing) parallel_for(d.n, VorticityConfinement<Policy>{d.grid, fl, d.radii, p.h0, confinement(d)});
    return XsphRiders{pair_sum.out != nullptr, narrowing.count != nullptr, warm.out != nullptr};
}

// Divergence-free velocity projection at the predicted positions (pbf_constraints.h): preconditioned
// conjugate gradients on A mu = -J v, A = J M^-1 J^T, updating v += alpha M^-1 J^T p as it goes.
// The kinetic energy of v falls with every iteration (CG minimises it along conjugate directions).
// Warm start: the previous step's mu (the pressure impulse, which changes slowly) is applied first,
// v += M^-1 J^T mu_prev, and CG solves for the correction, so a few iterations reach the projection. warm_ready:
// the XSPH pass has summed M^-1 J^T mu_prev into pos_tmp (warm_start_impulse).
// The host queues all divergence_iterations iterations without reading a scalar: the dot products go to
// d.cg_state, the reduction's last block forms the new direction's weight and the stop flag there (CgBegin,
// CgNextDirection as reduce_into's then), each update thread forms alpha, and once the solve has converged or stalled
// (state.stop) the remaining kernels return at once (a few microseconds each instead of a wait per dot product).
template <class Policy, bool Corrected>
void solve_divergence(SolverData& d, const WallNeighbourhoods& bnd, bool warm_ready, Vec3 gravity_dv) {
    CellRanges fl = d.fluid_ranges(d.pred);
    const std::size_t n = d.n;
    const GridGeometry& grid = d.grid;
    const LevelRadii& radii = d.radii;
    const ConstraintParams& cp = d.cp;
    float* r = raw(d.cg_r);
    float* p = raw(d.cg_p);
    float* q = raw(d.cg_q);
    float* diag = raw(d.cg_diag);
    Float4* g = raw(d.vel_tmp);
    Float4* v = raw(d.vel);
    float* mu = raw(d.cg_mu);
    CgState* s = raw(d.cg_state);
    const int* stop = &s->stop;
    float* L = nullptr;   // gradient correction (pbf_constraints.h), at this step's predicted positions
    if constexpr (Corrected) {
        L = raw(d.grad_correction);
        parallel_for(n, GradientCorrection<Policy>{grid, fl, bnd, radii, cp, L});
    }
    const uint32_t* order = d.list_pass_order();   // the list passes' thread order (grid_launch.h: order_list_passes)
    if (!warm_ready) parallel_for_in_order(n, order, ApplyJT<Policy, Corrected>{grid, fl, bnd, radii, cp, mu, g, L});
    // v += dt gravity (where there is gravity), then v += M^-1 J^T mu_prev: one pass
    const bool gravity = gravity_dv.x != 0.0f || gravity_dv.y != 0.0f || gravity_dv.z != 0.0f;
    parallel_for(n, AddVelocity{warm_ready ? raw(d.pos_tmp) : g, v, gravity_dv, gravity});
    // r = -J v, z = r / diag, p = z
    parallel_for_in_order(n, order, ApplyJ<Policy, Corrected>{grid, fl, bnd, radii, cp, v, r, diag, L, nullptr, p});
    // Stop once the RMS divergence would change the density by less than divergence_tolerance per step:
    // projecting further only removes flow that the SPH divergence of a disordered particle set misreads.
    const double tol2 = double(d.p.divergence_tolerance) * d.p.divergence_tolerance / (double(d.p.dt) * d.p.dt) * n;
    reduce_into(n, CgDots{r, p, r, r}, Double2{0.0, 0.0}, Double2Add{}, &s->dots, CgBegin{s, tol2});   // (r . z, r . r)
    for (int it = 0; it < d.p.divergence_iterations; ++it) {
        const bool last = it + 1 == d.p.divergence_iterations;
        parallel_for_in_order(n, order, ApplyJT<Policy, Corrected>{grid, fl, bnd, radii, cp, p, g, L, stop});   // g = M^-1 J^T p
        if (!last) {
            parallel_for_in_order(n, order, ApplyJ<Policy, Corrected>{grid, fl, bnd, radii, cp, g, q, nullptr, L, stop});   // q = A p
            reduce_into(n, CgDirectionDots{p, q, diag}, Double2{0.0, 0.0}, Double2Add{}, &s->direction);
        } else {   // p . A p = sum m |g|^2: the residual after the last step is not needed
            reduce_into(n, CgDirectionEnergy{fl.pos, g, p, diag}, Double2{0.0, 0.0}, Double2Add{}, &s->direction);
        }
        // alpha = rz / p.A p; v += alpha g; r -= alpha q; mu += alpha p
        parallel_for(n, CgUpdate{s, g, last ? nullptr : q, p, v, r, mu});
        if (last) break;
        reduce_into(n, CgResidualDots{r, diag}, Double2{0.0, 0.0}, Double2Add{}, &s->dots, CgNextDirection{s, tol2});
        parallel_for(n, CgDirection{s, r, diag, p});                                  // p = z + beta p
    }
}

// Column drift (pbf_constraints.h): u_y -= sum m u_y / sum m.
inline void remove_column_drift(SolverData& d) {
    if (d.n == 0) return;
    StepSums* sums = raw(d.step_sums);
    reduce_into(d.n, VerticalMomentum{raw(d.pred), raw(d.vel)}, Double2{0.0, 0.0}, Double2Add{}, &sums->column);
    parallel_for(d.n, RemoveVerticalDrift{raw(d.vel), &sums->column});
}

// The velocity projection's part of the step (closed domains): v = P(v + dt g), after all forces.
template <class Policy>
void project_velocity(SolverData& d, const WallNeighbourhoods& walls, bool warm_ready) {
    if (!d.p.velocity_projection) return;
    d.clock.begin(kPhaseSolver);
    const Vec3 gravity_dv = d.p.dt * gravity_of(d.p);
    if (d.p.gradient_correction)
        solve_divergence<Policy, true>(d, walls, false, gravity_dv);
    else
        solve_divergence<Policy, false>(d, walls, warm_ready, gravity_dv);
    if (d.p.remove_column_drift && !d.p.periodic[1]) remove_column_drift(d);   // sum m u_y = 0
    d.clock.end(kPhaseSolver);
}

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
