// Kernel policies: what differs between uniform and adaptive runs (section 5.2), written once per kind of run.
// Every neighbour kernel that works at mixed levels (pbf_constraints.h, smoothing.h) is a template over a
// policy, and the solver picks the policy once per step (solver_impl.inl), so no kernel branches on it:
//   radius(radii, h0, m)          kernel radius of a particle of mass m: h0, or h_l = h0 2^(-l/3), m = m0 2^(-l)
//   W(r2, hi, hj), grad_W(...)    the pair's kernel: the plain kernel at h0, the symmetric kernel of eq. 19
//                                 (the mean of the kernels at both radii), or the kernel at the mean radius
//   support(hi, hj)               the pair's support: h0, max(h_i, h_j) (eq. 19), or (h_i + h_j) / 2
//   area_scaled(x, h, h0)         x (h / h0)^2: a per-level quantity that scales with h^2 (smoothing's beta)
//   tensile_ratio, tensile_scale  the s_corr term at the pair's own radii (PositionCorrection)
//   for_each_neighbor             the 27-cell search at h0, or the nested sub-cell search of grid.h
//   for_each_candidate            the same search with every radius widened by a skin (neighbor_list.h)
//   within_support                whether a candidate pair lies within its own support plus the skin
// Adaptive runs pick the pair kernel with adaptive.pair_kernel: eq. 19 (AdaptivePolicy, the paper's) or the
// kernel at the pair's mean radius (MeanRadiusPolicy), whose support (h_i + h_j)/2 gives a level-0 particle next
// to fine ones fewer neighbours (level 0 beside level 3: 0.75 h0, 0.42 of eq. 19's volume).
#pragma once
#include "common.h"
#include "grid.h"
#include "kernels.h"

namespace pbf {

// |r| < support + extra: within the pair's support (extra 0), or within that support widened by the lists' skin.
PBF_HD inline bool within_radius(float r2, float support, float extra) {
    float s = support + extra;
    return r2 < s * s;
}

// Every particle is level 0: radius h0, plain kernels, the uniform grid search.
struct UniformPolicy {
    static PBF_HD float radius(const LevelRadii&, float h0, float) { return h0; }
    static PBF_HD float support(float hi, float) { return hi; }
    static PBF_HOT float W(float r2, float hi, float) { return poly6(r2, hi); }
    static PBF_HOT Vec3 grad_W(Vec3 r, float r2, float hi, float) { return spiky_gradient(r, r2, hi); }
    static PBF_HD float area_scaled(float x, float, float) { return x; }
    // W(r) / W(dq h0), with 1 / W(dq h0) precomputed.
    static PBF_HD float tensile_ratio(float r2, float hi, float, float, float inv_wdq) { return poly6(r2, hi) * inv_wdq; }
    static PBF_HD float tensile_scale(float s, float, float, float) { return s; }
    template <class F>
    static PBF_HD void for_each_neighbor(const GridGeometry& g, const CellRanges& set, uint32_t, Vec3 q, float h0, F&& f) {
        pbf::for_each_neighbor(g, set, q, h0, f);
    }
    template <class F>
    static PBF_HD void for_each_candidate(const GridGeometry& g, const CellRanges& set, uint32_t, Vec3 q, float h0,
                                          float skin, F&& f) {
        pbf::for_each_neighbor(g, set, q, h0 + skin, f);
    }
    // The search above already tests h0 + skin.
    static PBF_HD bool within_support(float, float, float, float) { return true; }
};

// Particles of several levels: radius from the mass, symmetric kernels (eq. 19), the nested search.
struct AdaptivePolicy {
    static PBF_HD float radius(const LevelRadii& radii, float, float m) { return radii.radius_of_mass(m); }
    static PBF_HD float support(float hi, float hj) { return fmaxf(hi, hj); }
    static PBF_HOT float W(float r2, float hi, float hj) { return poly6_sym(r2, hi, hj); }
    static PBF_HOT Vec3 grad_W(Vec3 r, float r2, float hi, float hj) { return spiky_gradient_sym(r, r2, hi, hj); }
    static PBF_HD float area_scaled(float x, float h, float h0) { return x * (h * h) / (h0 * h0); }
    // W(r) / W(dq h) with the pair's own kernel (eq. 19) at dq times the pair's mean radius, so a fine pair at its
    // own spacing feels what a level-0 pair does at its spacing.
    static PBF_HD float tensile_ratio(float r2, float hi, float hj, float dq, float) {
        float hm = dq * 0.5f * (hi + hj);
        float wdq = poly6_sym(hm * hm, hi, hj);
        return wdq > 0.0f ? poly6_sym(r2, hi, hj) / wdq : 0.0f;
    }
    // lambda_ref (a unit violation's lambda) scales as h^5 (sum |grad C|^2 / m ~ m / h^8, m ~ h^3), so the
    // displacement s grad W / rho0 scales with h at every level, as it does at level 0.
    static PBF_HD float tensile_scale(float s, float hi, float hj, float h0) {
        float q = 0.5f * (hi + hj) / h0;
        return s * (q * q * q * q * q);
    }
    template <class F>
    static PBF_HD void for_each_neighbor(const GridGeometry& g, const CellRanges& set, uint32_t i, Vec3 q, float,
                                         F&& f) {
        for_each_neighbor_nested(g, set, i, q, f);
    }
    template <class F>
    static PBF_HD void for_each_candidate(const GridGeometry& g, const CellRanges& set, uint32_t i, Vec3 q, float,
                                          float skin, F&& f) {
        for_each_neighbor_nested(g, set, i, q, f, skin);
    }
    // The pair's own support (eq. 19), widened by the lists' skin.
    static PBF_HD bool within_support(float r2, float hi, float hj, float skin) {
        return within_radius(r2, support(hi, hj), skin);
    }
};

// Particles of several levels with the kernel at the pair's mean radius h_ij = (h_i + h_j) / 2, symmetric in i
// and j as eq. 19's mean of kernels is (so pair forces stay equal and opposite), with support h_ij instead of
// max(h_i, h_j). Between equal levels h_ij = h_i exactly (a doubling and a halving), so those pairs see the plain
// kernel, bitwise as under AdaptivePolicy. Everything that is not the pair's kernel is AdaptivePolicy's.
struct MeanRadiusPolicy : AdaptivePolicy {
    static PBF_HD float support(float hi, float hj) { return 0.5f * (hi + hj); }
    static PBF_HOT float W(float r2, float hi, float hj) { return poly6(r2, support(hi, hj)); }
    static PBF_HOT Vec3 grad_W(Vec3 r, float r2, float hi, float hj) { return spiky_gradient(r, r2, support(hi, hj)); }
    // W(r) / W(dq h_ij) at the pair's mean radius: a fine pair at its own spacing feels what a level-0 pair does.
    static PBF_HD float tensile_ratio(float r2, float hi, float hj, float dq, float) {
        float h = support(hi, hj);
        float hm = dq * h;
        float wdq = poly6(hm * hm, h);
        return wdq > 0.0f ? poly6(r2, h) / wdq : 0.0f;
    }
    // Declared again, not inherited: AdaptivePolicy's calls AdaptivePolicy::support (static members bind early).
    static PBF_HD bool within_support(float r2, float hi, float hj, float skin) {
        return within_radius(r2, support(hi, hj), skin);
    }
};

// f(j, r, r2, m_j, h_j) for the fluid neighbours j of particle i at q (i itself included, r2 = 0): the policy's
// search, with each neighbour's mass and kernel radius. With this step's neighbour lists (neighbor_list.h) the
// candidates come from i's list, in the order the search found them, and f is called where |r| is below the
// pair's support (max(h_i, h_j) with eq. 19, (h_i + h_j) / 2 at the mean radius, h0 in uniform runs: the search's
// own test); the search's wider cell-level tests
// in adaptive runs only added pairs whose kernels are exactly zero.
// The list is read kListBatch candidates at a time: their indices, then their positions, then the pairs in list
// order, so that a thread has several independent gathers in flight instead of one index-then-position chain
// per pair (the passes are bound by the latency of those gathers, docs/benchmarks.md).
#ifndef PBF_LIST_BATCH
#define PBF_LIST_BATCH 4
#endif
constexpr uint32_t kListBatch = PBF_LIST_BATCH;
static_assert(kListBatch >= 1 && kListBatch <= 16, "PBF_LIST_BATCH: candidates read at a time, 1 to 16 (4 measured best)");

// r = x_i - x_j (minimum image) and whether the pair lies within its support: the one test every list pass and
// the lists' narrowing (neighbor_list.h) make, written once so that both see the same pairs.
template <class Policy>
PBF_HD inline bool supported_pair(const GridGeometry& g, const LevelRadii& radii, float h0, Vec3 q, float hi,
                                  const Float4& pj, Vec3& r, float& r2, float& hj) {
    r = min_image(g, Vec3{q.x - pj.x, q.y - pj.y, q.z - pj.z});
    r2 = dot(r, r);
    hj = Policy::radius(radii, h0, pj.w);
    return within_radius(r2, Policy::support(hi, hj), 0.0f);
}

// No per-neighbour data besides the position (for_each_fluid_neighbor below).
struct NoNeighborData {};
struct GatherNothing {
    PBF_HD NoNeighborData operator()(uint32_t) const { return {}; }
};

// for_each_fluid_neighbor with data of each candidate j read beside its position: f(j, r, r2, m_j, h_j, gather(j)).
// gather(j) is called for every candidate of the batch, within support or not, right after the batch's positions,
// so a pass that needs j's lambda, impulse or velocity has those loads in flight with the positions instead of one
// dependent load per pair (the same sums in the same order: only the loads move).
template <class Policy, class Gather, class F>
PBF_HD inline void for_each_fluid_neighbor_gathered(const GridGeometry& g, const CellRanges& fluid,
                                                    const LevelRadii& radii, float h0, uint32_t i, Vec3 q,
                                                    Gather&& gather, F&& f) {
    using Data = decltype(gather(0u));
    if (fluid.listed(i)) {
        const float hi = Policy::radius(radii, h0, fluid.pos[i].w);
        auto visit = [&](uint32_t j, const Float4& pj, const Data& dj) {
            Vec3 r;
            float r2, hj;
            if (supported_pair<Policy>(g, radii, h0, q, hi, pj, r, r2, hj)) f(j, r, r2, pj.w, hj, dj);
        };
        const uint32_t e = fluid.nbr_count[i];
        uint32_t k = 0;
        for (; k + kListBatch <= e; k += kListBatch) {
            uint32_t j[kListBatch];
            Float4 pj[kListBatch];
            Data dj[kListBatch];
            for (uint32_t b = 0; b < kListBatch; ++b) j[b] = fluid.candidate(i, k + b);
            for (uint32_t b = 0; b < kListBatch; ++b) pj[b] = fluid.pos[j[b]];
            for (uint32_t b = 0; b < kListBatch; ++b) dj[b] = gather(j[b]);
            for (uint32_t b = 0; b < kListBatch; ++b) visit(j[b], pj[b], dj[b]);
        }
        for (; k < e; ++k) {
            uint32_t j = fluid.candidate(i, k);
            visit(j, fluid.pos[j], gather(j));
        }
        return;
    }
    Policy::for_each_neighbor(g, fluid, i, q, h0, [&](uint32_t j, Vec3 r, float r2) {
        float mj = fluid.pos[j].w;
        f(j, r, r2, mj, Policy::radius(radii, h0, mj), gather(j));
    });
}

template <class Policy, class F>
PBF_HD inline void for_each_fluid_neighbor(const GridGeometry& g, const CellRanges& fluid, const LevelRadii& radii,
                                           float h0, uint32_t i, Vec3 q, F&& f) {
    for_each_fluid_neighbor_gathered<Policy>(g, fluid, radii, h0, i, q, GatherNothing{},
        [&](uint32_t j, Vec3 r, float r2, float mj, float hj, NoNeighborData) { f(j, r, r2, mj, hj); });
}

}  // namespace pbf
