// The solver, written once over Thrust and compiled twice: by nvcc for the CUDA backend
// (backend_cuda.cu) and by g++ with Thrust's OpenMP device system for the CPU backend
// (backend_cpu.cpp). The including file defines PBF_BACKEND_NS (and PBF_BACKEND_CUDA for CUDA).
//
// The house of the C++ side (docs/architecture.md has the map):
//   kernels: kernels.h, grid.h, neighbor_list.h, pbf_constraints.h, smoothing.h, thermodynamics.h, adaptivity.h,
//            diagnostics.h, noise.h
//            (__host__ __device__ functors), kernel_policy.h (uniform vs adaptive runs as a policy type)
//   launch:  the dispatch layer, one mechanism a header: device_memory.h (device vectors, Thrust's policy),
//            kernel_launch.h (CUDA launches), parallel_for.h, counted_launch.h, row_order.h, reduce.h, sort.h,
//            cell_walk.h (the 27-colour walk), phase_clock.h (timers); solver_data.h (the arrays), and one
//            *_launch.h per phase beside its kernels: grid, pbf_constraints, smoothing, thermodynamics,
//            adaptivity, boundaries, diagnostics
//   here:    Solver, the ISolver the bindings see: set-up, the step in the paper's order, views, statistics.
#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include <thrust/copy.h>

#include "device_memory.h"
#include "solver_data.h"

#include "adaptivity_launch.h"
#include "boundaries_launch.h"
#include "diagnostics_launch.h"
#include "grid_launch.h"
#include "kernel_policy.h"
#include "pbf_constraints_launch.h"
#include "smoothing_launch.h"
#include "thermodynamics_launch.h"

namespace pbf {
namespace PBF_BACKEND_NS {

class Solver final : public ISolver {
public:
    explicit Solver(const Params& p) {
        d_.p = p;
        d_.radii = make_level_radii(p.h0, p.mass0);
        d_.grid = make_solver_grid(p);
        d_.cp = make_constraint_params(p);
        d_.atm = make_atmosphere_params(p);
        d_.ap = make_adapt_params(p, d_.radii);
        d_.smoothing = smoothing_active(p);
        d_.rates = step_rates(p);
        allocate_grid(d_);
    }

    // -- the step ----------------------------------------------------------------------------
    // One step (sections 3-5 of the paper; Macklin & Mueller 2013, Algorithm 1). The timers are the
    // phases of Table 1 ("pbf" holds "neighbors" and "solver"). The sums the host needs (the budget, the
    // check) go to d.step_sums in device memory and are read once, after the step (step() below).
    template <class Policy>
    void do_step() {
        SolverData& d = d_;
        d.atm.diurnal = diurnal_factor(d.p, d.time + 0.5 * double(d.p.dt));   // C1 at the step's mid-time
        StepSums* sums = raw(d.step_sums);
        start_budget(d);                             // the sums at x (the last step's end where nothing changed since)

        const WallNeighbourhoods walls = d.wall_neighbourhoods();
        d.clock.begin(kPhasePBF);
        d.clock.begin(kPhaseNeighbors);
        predict_positions(d);                        // x* = x + dt (v + dt g)
        build_neighbor_grid(d);                      // sort by the cell of x*, cell ranges
        // each particle's candidates, once per step; on the way, the first density iteration's rho and lambda
        bool first_summed = false;                   // whether the build summed the first density iteration
        if (d.p.iterations > 0) first_summed = build_neighbor_lists<Policy>(d, first_density_sums<Policy>(d, walls));
        else build_neighbor_lists<Policy>(d, NoPairSum{});
        d.clock.end(kPhaseNeighbors);
        d.clock.begin(kPhaseSolver);
        solve_density<Policy>(d, walls, first_summed);   // iterations { rho, lambda (eq. 1-4, 18); dp, s_corr; walls }
        update_velocity(d);                          // v = (x* - x) / dt (position projection only)
        // XSPH, viscosity and the vorticity at the final x* (its confinement rides the smoothing pass where one runs);
        // on the same pairs: the lists narrowed to them, the smoothing limiter's weight sums, the projection's warm start
        const XsphRiders taken = viscosity_vorticity<Policy>(d, limiter_weight_sums<Policy>(d), walls);
        if (!taken.narrowed) narrow_neighbor_lists<Policy>(d);   // x* is final: the lists keep the pairs within support
        d.clock.end(kPhaseSolver);
        d.clock.end(kPhasePBF);

        smooth_fields<Policy>(d, taken.pair_sum);    // temperature smoothing (eq. 12-17), vorticity confinement
        cloud_dynamics(d);                           // heating .. buoyancy (eq. 5-11, C1-C3)

        d.clock.begin(kPhasePBF);
        project_velocity<Policy>(d, walls, taken.warm_start);   // v = P(v + dt g), divergence-free at x* (velocity projection)
        d.clock.end(kPhasePBF);
        reduce_budget_into(d, d.pred, true, d.p.thermodynamics, &sums->end);
        d.clock.begin(kPhasePBF);
        commit_positions(d, d.pred, d.pos);          // x = x*, wrapped on periodic axes
        d.clock.end(kPhasePBF);
        d.end_budget_is_next_start = !d.p.periodic[1];   // wrapping x and z moves no mass up or down

        d.step += 1;
        d.time += d.p.dt;
        d.lists_ready = false;                       // the lists stay with this step's particles
        if (d.p.adaptive && d.step % d.p.adapt_every == 0) {
            adapt(d);                                // merging, splitting, compaction (section 5.2)
            d.end_budget_is_next_start = false;
        }
    }

    // -- set-up ------------------------------------------------------------------------------
    void set_fluid(std::size_t n, const float* pos3, const float* vel3, const float* temperature,
                   const float* vapor, const float* cloud, const float* mass, const uint32_t* id) override {
        SolverData& d = d_;
        d.end_budget_is_next_start = false;
        std::size_t cap = std::max<std::size_t>(n, d.p.adaptive ? d.p.capacity : n);
        if (cap > 0xfffffff0u) throw std::length_error("particle capacity exceeds 2^32");
        d.capacity = cap;
        std::vector<Float4> hp(n), hv(n);
        uint32_t max_id = 0;
        for (std::size_t i = 0; i < n; ++i) {
            hp[i] = Float4{pos3[3 * i], pos3[3 * i + 1], pos3[3 * i + 2], mass[i]};
            hv[i] = Float4{vel3[3 * i], vel3[3 * i + 1], vel3[3 * i + 2], 0.0f};
            max_id = std::max(max_id, id[i]);
        }
        d.allocate(cap);
        d.n = n;
        thrust::copy(hp.begin(), hp.end(), d.pos.begin());
        thrust::copy(hv.begin(), hv.end(), d.vel.begin());
        thrust::copy(id, id + n, d.id.begin());
        if (d.p.thermodynamics) {
            thrust::copy(temperature, temperature + n, d.temperature.begin());
            thrust::copy(vapor, vapor + n, d.vapor.begin());
            thrust::copy(cloud, cloud + n, d.cloud.begin());
        }
        d.next_id = n ? max_id + 1 : 0;
        commit_positions(d, d.pos, d.pos);  // wrap into the periodic box
        d.energy_reference = n && energy_checked(d.p) ? mechanical_energy(d.p, reduce_budget(d, d.pos, true, false))
                                                      : std::nan("");
        d.energy_settling = true;
    }

    void set_boundary(std::size_t n, const float* pos3, const float* temperature, const float* vapor) override {
        set_boundary_particles(d_, n, pos3, temperature, vapor);
    }

    void set_projection_impulse(std::size_t n, const float* mu) override {
        if (!d_.p.velocity_projection) return;
        if (n != d_.n) throw std::invalid_argument("projection_impulse: length differs from the particle count");
        thrust::copy(mu, mu + n, d_.cg_mu.begin());
    }

    void set_budget_totals(const double* totals) override {
        for (int k = 0; k < StepBudget::kTotals; ++k) d_.last_stats.budget.totals[k] = totals[k];
    }

    void set_clock(long long step, double time, uint32_t next_id) override {
        d_.step = step;
        d_.time = time;
        d_.last_good = step;
        d_.next_id = std::max(d_.next_id, next_id);
    }

    // -- stepping ----------------------------------------------------------------------------
    // Each step, then its sums (and the check's, where the step is checked) copied to the host in one read: the
    // budget record and the check.
    std::string step(int n) override {
        for (int s = 0; s < n; ++s) {
            if (!d_.p.adaptive) do_step<UniformPolicy>();
            else if (d_.p.pair_kernel_mean_radius) do_step<MeanRadiusPolicy>();
            else do_step<AdaptivePolicy>();
            const bool controlled = d_.p.cfl > 0.0f;   // the CFL-controlled step needs the state's max |v| / h
            const bool checked = d_.step % d_.p.check_every == 0;
            if ((checked || controlled) && d_.n > 0) reduce_checks_into(d_, &raw(d_.step_sums)->checks);
            const StepSums sums = d_.step_sums[0];
            finish_adapt(d_, sums.adapt);   // the particle count after the step's splitting and merging, if any
            d_.clock.collect(d_.totals);
#ifdef PBF_BACKEND_CUDA
            cudaError_t err = cudaGetLastError();
            if (err != cudaSuccess) return std::string("cuda|") + cudaGetErrorString(err);
#endif
            record_budget(d_, sums);
            take_list_size(d_, sums.list_size);
            if (checked) {
                std::string failure = check(d_, sums.checks, sums.end);
                if (!failure.empty()) return failure;
            }
            if (controlled && d_.n > 0) set_time_step(next_time_step(d_.p, sums.checks.rate_max));
        }
        return std::string();
    }

    // The step in use, s: the scene's dt, or the CFL-controlled one (time_step.h). Setting it re-derives every
    // per-step coefficient (the relaxations' c(dt), the atmosphere's dt and decays).
    double time_step() const override { return d_.p.dt; }
    void set_time_step(double dt) override {
        if (!(dt > 0.0) || !std::isfinite(dt)) throw std::invalid_argument("time step must be positive and finite");
        if (float(dt) == d_.p.dt) return;
        d_.p.dt = float(dt);
        d_.rates = step_rates(d_.p);
        d_.atm = make_atmosphere_params(d_.p);
    }
    void set_neighbor_row_width(unsigned width) override { d_.nbr_width = std::max<uint32_t>(d_.nbr_width, width); }

    void adapt_now() override {
        if (!d_.p.adaptive) throw std::invalid_argument("adapt_now: the scene is not adaptive");
        d_.end_budget_is_next_start = false;
        thrust::copy(exec(), d_.pos.begin(), d_.pos.begin() + d_.n, d_.pred.begin());
        build_neighbor_grid(d_);
        adapt(d_);
        const StepSums sums = d_.step_sums[0];
        finish_adapt(d_, sums.adapt);
        d_.clock.collect(d_.totals);
    }

    std::size_t size() const override { return d_.n; }
    long long step_count() const override { return d_.step; }
    double time() const override { return d_.time; }
    uint32_t next_id() const override { return d_.next_id; }

    ArrayView view(const std::string& name) override {
        SolverData& d = d_;
        d.end_budget_is_next_start = false;   // the caller may write through the view
        ArrayView v;
#ifdef PBF_BACKEND_CUDA
        v.on_device = true;
#endif
        auto f4 = [&](dvec<Float4>& a, std::size_t n) { v.data = raw(a); v.n = n; v.kind = ArrayKind::Float4; };
        auto f1 = [&](dvec<float>& a, std::size_t n) { v.data = raw(a); v.n = n; v.kind = ArrayKind::Float; };
        if (name == "position") f4(d.pos, d.n);
        else if (name == "velocity") f4(d.vel, d.n);
        else if (name == "id") { v.data = raw(d.id); v.n = d.n; v.kind = ArrayKind::UInt; }
        else if (name == "temperature" && d.p.thermodynamics) f1(d.temperature, d.n);
        else if (name == "vapor" && d.p.thermodynamics) f1(d.vapor, d.n);
        else if (name == "cloud" && d.p.thermodynamics) f1(d.cloud, d.n);
        else if (name == "density") f1(d.density, d.n);
        else if (name == "projection_impulse" && d.p.velocity_projection) f1(d.cg_mu, d.n);
        else if (name == "boundary_position") f4(d.bpos, d.nb);
        else if (name == "boundary_temperature") f1(d.btemperature, d.nb);
        else if (name == "boundary_vapor") f1(d.bvapor, d.nb);
        else throw std::invalid_argument("unknown or inactive array '" + name + "'");
        if (v.n == 0) v.data = nullptr;
        return v;
    }

    void copy_to_host(const std::string& name, void* dst) override {
        ArrayView v = view(name);
        if (v.n == 0) return;
        std::size_t bytes = v.n * (v.kind == ArrayKind::Float4 ? 16 : 4);
#ifdef PBF_BACKEND_CUDA
        cudaError_t err = cudaMemcpy(dst, v.data, bytes, cudaMemcpyDeviceToHost);
        if (err != cudaSuccess) throw std::runtime_error(std::string("cudaMemcpy: ") + cudaGetErrorString(err));
#else
        std::copy(static_cast<const char*>(v.data), static_cast<const char*>(v.data) + bytes, static_cast<char*>(dst));
#endif
    }

    PhaseTotals timings() const override { return d_.totals; }
    void reset_timings() override { d_.totals = PhaseTotals{}; }

    StepStats stats() override {
        const SolverData& d = d_;
        StepStats s = d.last_stats;
        // Before the first step: the state's totals, and no heat from any process yet.
        if (!s.budget.valid && d.n > 0) budget_state(s.budget, reduce_budget(d, d.pos, true, false));
        s.step = d.step;
        s.time = d.time;
        s.n_particles = d.n;
        s.dt = d.p.dt;
        s.neighbor_lists = d.p.neighbor_list && !d.lists_given_up;
        s.neighbor_candidates = s.neighbor_lists && d.step > 0 ? d.list_entries : 0;
        s.neighbor_row_width = s.neighbor_lists && d.step > 0 ? d.nbr_width : 0;
        s.wall_candidates = d.wall_pos.size();
        if (d.n > 0) {
            Reduced r = reduce_checks(d);
            s.density_error_mean = r.err_sum / double(d.n);
            s.density_error_max = r.err_max;
            s.density_excess_mean = r.excess_sum / double(d.n);
            s.density_deficit_mean = r.deficit_sum / double(d.n);
            s.max_speed = std::sqrt(double(r.speed2_max));
            s.cfl = double(d.p.dt) * r.rate_max;
            for (int k = 0; k < 3; ++k) { s.min_position[k] = r.lo[k]; s.max_position[k] = r.hi[k]; }
        }
        s.level_counts.assign(std::size_t(std::max(d.p.max_level, 0) + 1), 0);
        if (!d.p.adaptive) {  // every particle is level 0: no host copy of the positions
            s.level_counts[0] = (long long)d.n;
            return s;
        }
        std::vector<Float4> hp(d.n);
        if (d.n) thrust::copy(d.pos.begin(), d.pos.begin() + d.n, hp.begin());
        for (auto& q : hp) {
            int l = d.radii.level_of_mass(q.w);
            if (l >= int(s.level_counts.size())) s.level_counts.resize(l + 1, 0);
            s.level_counts[l] += 1;
        }
        return s;
    }

private:
    SolverData d_;
};

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
