// Python bindings (nanobind) of the solver: module pbf_cuda._core.
// Compiled by g++; talks to the backends only through solver_api.h.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/unique_ptr.h>
#include <nanobind/stl/vector.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "kernels.h"
#include "noise.h"
#include "params.h"
#include "solver_api.h"
#include "thermodynamics.h"

namespace nb = nanobind;
using namespace nb::literals;

#ifdef PBF_WITH_CUDA
namespace pbf {
int cuda_device_capability();  // backend_cuda.cu
}
#endif
#ifndef PBF_CUDA_ARCHITECTURES
#define PBF_CUDA_ARCHITECTURES ""
#endif

namespace {

using FloatArray = nb::ndarray<const float, nb::c_contig, nb::device::cpu>;
using UIntArray = nb::ndarray<const uint32_t, nb::c_contig, nb::device::cpu>;

bool cuda_built() {
#ifdef PBF_WITH_CUDA
    return true;
#else
    return false;
#endif
}

int device_count() {
#ifdef PBF_WITH_CUDA
    return pbf::cuda_device_count();
#else
    return 0;
#endif
}

void require_rows(const char* name, std::size_t got, std::size_t want, std::size_t cols) {
    if (got != want * cols)
        throw std::invalid_argument(std::string(name) + ": expected " + std::to_string(want) +
                                    (cols > 1 ? " x " + std::to_string(cols) : std::string()) + " values, got " +
                                    std::to_string(got));
}

class PySolver {
public:
    PySolver(const pbf::Params& p, const std::string& backend) {
        if (backend == "cpu") {
            impl_ = pbf::make_cpu_solver(p);
        } else if (backend == "cuda") {
#ifdef PBF_WITH_CUDA
            if (pbf::cuda_device_count() == 0) throw std::runtime_error("backend 'cuda': no CUDA device is visible");
            impl_ = pbf::make_cuda_solver(p);
#else
            throw std::runtime_error("backend 'cuda': this build has no CUDA backend");
#endif
        } else {
            throw std::invalid_argument("backend = '" + backend + "': allowed 'cpu', 'cuda'");
        }
        thermodynamics_ = p.thermodynamics;
        large_scale_ = p.thermodynamics && p.large_scale_forcing;
    }

    void set_fluid(FloatArray pos, FloatArray vel, FloatArray temperature, FloatArray vapor, FloatArray cloud,
                   FloatArray mass, UIntArray id) {
        std::size_t n = id.size();
        require_rows("position", pos.size(), n, 3);
        require_rows("velocity", vel.size(), n, 3);
        require_rows("mass", mass.size(), n, 1);
        if (thermodynamics_) {
            require_rows("temperature", temperature.size(), n, 1);
            require_rows("vapor", vapor.size(), n, 1);
            require_rows("cloud", cloud.size(), n, 1);
        }
        impl_->set_fluid(n, pos.data(), vel.data(), thermodynamics_ ? temperature.data() : nullptr,
                         thermodynamics_ ? vapor.data() : nullptr, thermodynamics_ ? cloud.data() : nullptr,
                         mass.data(), id.data());
    }

    void set_boundary(FloatArray pos, FloatArray temperature, FloatArray vapor) {
        std::size_t n = pos.size() / 3;
        require_rows("boundary position", pos.size(), n, 3);
        bool t = temperature.size() == n && n > 0, v = vapor.size() == n && n > 0;
        impl_->set_boundary(n, pos.data(), t ? temperature.data() : nullptr, v ? vapor.data() : nullptr);
    }

    // Host copy of a solver array as a numpy array that owns its buffer.
    template <class T>
    nb::ndarray<nb::numpy, T> host_copy(const std::string& name, pbf::ArrayKind kind, const char* what) {
        pbf::ArrayView v = impl_->view(name);
        if (v.kind != kind) throw std::invalid_argument(name + " is not " + what);
        std::size_t cols = kind == pbf::ArrayKind::Float4 ? 4 : 1;
        T* buf = new T[v.n * cols + 1];
        impl_->copy_to_host(name, buf);
        nb::capsule owner(buf, [](void* p) noexcept { delete[] static_cast<T*>(p); });
        if (cols == 1) return nb::ndarray<nb::numpy, T>(buf, {v.n}, owner);
        return nb::ndarray<nb::numpy, T>(buf, {v.n, cols}, owner);
    }
    nb::ndarray<nb::numpy, float> get_float4(const std::string& name) {
        return host_copy<float>(name, pbf::ArrayKind::Float4, "a 4-vector array");
    }
    nb::ndarray<nb::numpy, float> get_float(const std::string& name) {
        return host_copy<float>(name, pbf::ArrayKind::Float, "a float array");
    }
    nb::ndarray<nb::numpy, uint32_t> get_uint(const std::string& name) {
        return host_copy<uint32_t>(name, pbf::ArrayKind::UInt, "an integer array");
    }

    // Zero-copy view (DLPack): CUDA memory on the GPU backend, host memory on the CPU backend.
    nb::object view(nb::handle self, const std::string& name) {
        pbf::ArrayView v = impl_->view(name);
        int device_type = v.on_device ? nb::device::cuda::value : nb::device::cpu::value;
        nb::dlpack::dtype dt = v.kind == pbf::ArrayKind::UInt ? nb::dtype<uint32_t>() : nb::dtype<float>();
        std::size_t shape[2] = {v.n, 4};
        std::size_t ndim = v.kind == pbf::ArrayKind::Float4 ? 2 : 1;
        nb::ndarray<> arr(v.data, ndim, shape, self, nullptr, dt, device_type, 0);
        return nb::cast(arr, nb::rv_policy::reference_internal, self);
    }

    std::vector<std::tuple<std::string, double, long long>> timings() const {
        pbf::PhaseTotals t = impl_->timings();
        std::vector<std::tuple<std::string, double, long long>> out;
        for (int p = 0; p < pbf::kNumPhases; ++p) out.emplace_back(pbf::phase_name(p), t.total_ms[p], t.count[p]);
        return out;
    }

    nb::dict stats() {
        pbf::StepStats s = impl_->stats();
        nb::dict d;
        d["step"] = s.step;
        d["time"] = s.time;
        d["n_particles"] = s.n_particles;
        d["density_error_mean"] = s.density_error_mean;
        d["density_error_max"] = s.density_error_max;
        d["neighbor_lists"] = s.neighbor_lists;
        d["neighbor_candidates"] = s.neighbor_candidates;
        d["neighbor_row_width"] = s.neighbor_row_width;
        d["wall_candidates"] = s.wall_candidates;
        d["density_excess_mean"] = s.density_excess_mean;
        d["density_deficit_mean"] = s.density_deficit_mean;
        d["max_speed"] = s.max_speed;
        d["dt"] = s.dt;
        d["cfl"] = s.cfl;
        d["min_position"] = std::vector<double>(s.min_position, s.min_position + 3);
        d["max_position"] = std::vector<double>(s.max_position, s.max_position + 3);
        d["level_counts"] = s.level_counts;
        d["splits"] = s.splits;
        d["merges"] = s.merges;
        d["split_capacity_rejects"] = s.split_capacity_rejects;
        d["splits_last_step"] = s.split_last;
        d["merges_last_step"] = s.merge_last;
        d["split_capacity_rejects_last_step"] = s.capacity_rejects_last;
        if (s.budget.valid) {
            const pbf::StepBudget& b = s.budget;
            d["mass"] = b.mass;
            d["mass_centre_height"] = b.mass_centre_height;
            d["kinetic_energy"] = b.kinetic_energy;
            d["potential_energy"] = b.potential_energy;
            d["mean_temperature"] = b.mean_temperature;
            d["heat_source"] = b.heat_source;
            d["heat_latent"] = b.heat_latent;
            d["heat_adiabatic"] = b.heat_adiabatic;
            d["heat_smoothing"] = b.heat_smoothing;
            d["total_water"] = b.total_water;
            d["heat_source_total"] = b.totals[0];
            d["heat_latent_total"] = b.totals[1];
            d["heat_adiabatic_total"] = b.totals[2];
            d["heat_smoothing_total"] = b.totals[3];
            d["heat_relaxation"] = b.heat_relaxation;
            d["water_relaxation"] = b.water_relaxation;
            d["water_rain"] = b.water_rain;
            d["heat_relaxation_total"] = b.totals[4];
            d["water_relaxation_total"] = b.totals[5];
            d["water_rain_total"] = b.totals[6];
            if (large_scale_) {   // only with a [forcing] section: the stats of every other scene stay as they were
                d["heat_subsidence"] = b.heat_subsidence;
                d["heat_radiation"] = b.heat_radiation;
                d["water_subsidence"] = b.water_subsidence;
                d["water_tendency"] = b.water_tendency;
                d["heat_subsidence_total"] = b.totals[7];
                d["heat_radiation_total"] = b.totals[8];
                d["water_subsidence_total"] = b.totals[9];
                d["water_tendency_total"] = b.totals[10];
            }
        }
        return d;
    }

    std::unique_ptr<pbf::ISolver> impl_;
    bool thermodynamics_ = false;
    bool large_scale_ = false;
};

// sum_k |grad_k C_i|^2 / m_k for a full lattice neighbourhood (constraint denominator of eq. 4).
double reference_gradient_norm2(float h, float d, float m, float rho0) {
    int r = int(std::ceil(h / d)) + 1;
    double gx = 0, gy = 0, gz = 0, s = 0;
    for (int i = -r; i <= r; ++i)
        for (int j = -r; j <= r; ++j)
            for (int k = -r; k <= r; ++k) {
                if (!i && !j && !k) continue;
                pbf::Vec3 x{-d * i, -d * j, -d * k};
                pbf::Vec3 g = pbf::spiky_gradient(x, pbf::dot(x, x), h);
                double f = m / rho0;
                gx += f * g.x; gy += f * g.y; gz += f * g.z;
                s += f * f * pbf::dot(g, g) / m;
            }
    return (gx * gx + gy * gy + gz * gz) / m + s;
}

}  // namespace

#ifndef PBF_SOURCE_HASH
#define PBF_SOURCE_HASH "unknown"
#endif

// beta_0 = grad C_ii / |grad C_i|^2 of the smoothing constraint (eq. 13, 16, 17) for a full lattice
// neighbourhood, m^2 (negative: grad C_ii < 0). The solver multiplies it by kappa.
double reference_smoothing_beta(float h, float d, float m, float rho0, float eps_rel) {
    int r = int(std::ceil(h / d)) + 1;
    double g = 0, s = 0;
    for (int i = -r; i <= r; ++i)
        for (int j = -r; j <= r; ++j)
            for (int k = -r; k <= r; ++k) {
                if (!i && !j && !k) continue;
                pbf::Vec3 x{-d * i, -d * j, -d * k};
                float r2 = pbf::dot(x, x);
                pbf::Vec3 gw = pbf::spiky_gradient(x, r2, h);
                double c = double(m) / rho0 * pbf::dot(x, gw) / (r2 + eps_rel * h * h);
                g += c;
                s += c * c;
            }
    double norm2 = g * g + s;
    return norm2 > 0 ? g / norm2 : 0.0;
}

NB_MODULE(_core, m) {
    m.doc() = "cloudpbf particle solver core (one C++ source; CUDA and OpenMP backends)";

    // Params: one attribute per parameter of PBF_PARAMS (params.h); arrays read and write as lists.
    nb::class_<pbf::Params> params(m, "Params");
    params.def(nb::init<>());
#define PBF_BIND_SCALAR(type, name, source, value) params.def_rw(#name, &pbf::Params::name);
#define PBF_BIND_ARRAY(type, name, length, source, ...)                                            \
    params.def_prop_rw(                                                                            \
        #name, [](const pbf::Params& p) { return std::vector<type>(p.name, p.name + length); },    \
        [](pbf::Params& p, const std::vector<type>& v) {                                           \
            if (v.size() != length) throw std::invalid_argument(#name ": expected " #length " values"); \
            for (int k = 0; k < length; ++k) p.name[k] = v[k];                                     \
        });
    PBF_PARAMS(PBF_BIND_SCALAR, PBF_BIND_ARRAY)
#undef PBF_BIND_SCALAR
#undef PBF_BIND_ARRAY
    // The declaration itself: (name, C++ type, length (0: a scalar), scene field ("": computed by
    // pbf_cuda.simulation.build_params)) per parameter, in the order of params.h.
    m.def("declared_params", []() {
        std::vector<std::tuple<std::string, std::string, int, std::string>> out;
#define PBF_DECLARED_SCALAR(type, name, source, value) out.emplace_back(#name, #type, 0, source);
#define PBF_DECLARED_ARRAY(type, name, length, source, ...) out.emplace_back(#name, #type, length, source);
        PBF_PARAMS(PBF_DECLARED_SCALAR, PBF_DECLARED_ARRAY)
#undef PBF_DECLARED_SCALAR
#undef PBF_DECLARED_ARRAY
        return out;
    });

    nb::class_<PySolver>(m, "Solver")
        .def(nb::init<const pbf::Params&, const std::string&>(), "params"_a, "backend"_a)
        .def("set_fluid", &PySolver::set_fluid, "position"_a, "velocity"_a, "temperature"_a, "vapor"_a,
             "cloud"_a, "mass"_a, "id"_a)
        .def("set_boundary", &PySolver::set_boundary, "position"_a, "temperature"_a, "vapor"_a)
        .def("set_projection_impulse", [](PySolver& s, FloatArray mu) { s.impl_->set_projection_impulse(mu.size(), mu.data()); })
        .def("set_budget_totals", [](PySolver& s, std::vector<double> t) {
            // 4 or 7 values: a checkpoint written before the forcing terms existed (they start at 0).
            if (t.size() != 4 && t.size() != 7 && t.size() != std::size_t(pbf::StepBudget::kTotals))
                throw std::invalid_argument("set_budget_totals: expected 4, 7 or " +
                                            std::to_string(pbf::StepBudget::kTotals) + " values");
            t.resize(pbf::StepBudget::kTotals, 0.0);
            s.impl_->set_budget_totals(t.data());
        })
        .def("set_clock", [](PySolver& s, long long step, double t, uint32_t next) { s.impl_->set_clock(step, t, next); })
        .def("time_step", [](PySolver& s) { return s.impl_->time_step(); })
        .def("set_time_step", [](PySolver& s, double dt) { s.impl_->set_time_step(dt); })
        .def("set_neighbor_row_width", [](PySolver& s, unsigned w) { s.impl_->set_neighbor_row_width(w); })
        .def("step", [](PySolver& s, int n) {
            std::string failure;
            {
                nb::gil_scoped_release release;
                failure = s.impl_->step(n);
            }
            if (!failure.empty()) throw std::runtime_error(failure);
        }, "n"_a)
        .def("adapt_now", [](PySolver& s) { s.impl_->adapt_now(); }, nb::call_guard<nb::gil_scoped_release>())
        .def("size", [](PySolver& s) { return s.impl_->size(); })
        .def("step_count", [](PySolver& s) { return s.impl_->step_count(); })
        .def("time", [](PySolver& s) { return s.impl_->time(); })
        .def("next_id", [](PySolver& s) { return s.impl_->next_id(); })
        .def("get_float4", &PySolver::get_float4)
        .def("get_float", &PySolver::get_float)
        .def("get_uint", &PySolver::get_uint)
        .def("view", [](nb::handle self, const std::string& name) {
            return nb::cast<PySolver&>(self).view(self, name);
        })
        .def("view_info", [](PySolver& s, const std::string& name) {
            pbf::ArrayView v = s.impl_->view(name);
            std::size_t cols = v.kind == pbf::ArrayKind::Float4 ? 4 : 1;
            const char* typestr = v.kind == pbf::ArrayKind::UInt ? "<u4" : "<f4";
            return std::make_tuple(reinterpret_cast<std::uintptr_t>(v.data), v.n, cols, std::string(typestr),
                                   v.on_device);
        })
        .def("timings", &PySolver::timings)
        .def("reset_timings", [](PySolver& s) { s.impl_->reset_timings(); })
        .def("stats", &PySolver::stats);

    m.def("source_hash", []() { return std::string(PBF_SOURCE_HASH); });  // csrc hash (CMakeLists.txt)
    m.def("cuda_built", &cuda_built);
    m.def("cuda_device_count", &device_count);
    // The CUDA architectures compiled in (CMake syntax, comma-separated: "75-real,...,90-real,90-virtual").
    m.def("cuda_architectures", []() { return std::string(PBF_CUDA_ARCHITECTURES); });
    // Device 0's compute capability as major * 10 + minor, -1 without a device or a CUDA build.
    m.def("cuda_device_capability", []() {
#ifdef PBF_WITH_CUDA
        return pbf::cuda_device_capability();
#else
        return -1;
#endif
    });
#ifdef PBF_WITH_CUDA
    // (free, total) bytes of device 0: the memory check before a run (pbf_cuda/memory.py).
    m.def("cuda_memory_info", []() {
        auto info = pbf::cuda_memory_info();
        return std::make_tuple(info.first, info.second);
    });
    // Device-to-device copy bandwidth in bytes/s (read + written): the step's bandwidth roofline.
    m.def("cuda_copy_bandwidth", &pbf::cuda_copy_bandwidth, "nbytes"_a, "repeats"_a = 20);
#endif
    m.def("cuda_device_name", []() {
#ifdef PBF_WITH_CUDA
        return pbf::cuda_device_name();
#else
        return std::string();
#endif
    });
    m.def("poly6", [](FloatArray r, float h) {
        std::size_t n = r.size();
        float* out = new float[n + 1];
        for (std::size_t i = 0; i < n; ++i) out[i] = pbf::poly6(r.data()[i] * r.data()[i], h);
        nb::capsule owner(out, [](void* p) noexcept { delete[] static_cast<float*>(p); });
        return nb::ndarray<nb::numpy, float>(out, {n}, owner);
    });
    m.def("spiky_gradient", [](FloatArray x, float h) {
        std::size_t n = x.size() / 3;
        float* out = new float[3 * n + 1];
        for (std::size_t i = 0; i < n; ++i) {
            pbf::Vec3 r{x.data()[3 * i], x.data()[3 * i + 1], x.data()[3 * i + 2]};
            pbf::Vec3 g = pbf::spiky_gradient(r, pbf::dot(r, r), h);
            out[3 * i] = g.x; out[3 * i + 1] = g.y; out[3 * i + 2] = g.z;
        }
        nb::capsule owner(out, [](void* p) noexcept { delete[] static_cast<float*>(p); });
        return nb::ndarray<nb::numpy, float>(out, {n, 3}, owner);
    });
    m.def("reference_gradient_norm2", &reference_gradient_norm2, "h"_a, "spacing"_a, "mass"_a, "rest_density"_a);
    m.def("reference_smoothing_beta", &reference_smoothing_beta, "h"_a, "spacing"_a, "mass"_a, "rest_density"_a,
          "eps_rel"_a);
    m.def("simplex2", [](nb::ndarray<const double, nb::c_contig, nb::device::cpu> x,
                         nb::ndarray<const double, nb::c_contig, nb::device::cpu> y) {
        std::size_t n = x.size();
        if (y.size() != n) throw std::invalid_argument("simplex2: x and y differ in length");
        double* out = new double[n + 1];
        for (std::size_t i = 0; i < n; ++i) out[i] = pbf::simplex2(x.data()[i], y.data()[i]);
        nb::capsule owner(out, [](void* p) noexcept { delete[] static_cast<double*>(p); });
        return nb::ndarray<nb::numpy, double>(out, {n}, owner);
    });
    // The solver's exact phase-transition update (eq. 9-11), vectorised, for tests and the grid baseline.
    m.def("phase_transition", [](FloatArray T, FloatArray v, FloatArray w, float dt, float alpha, float Q,
                                 float A, float B, float C) {
        std::size_t n = T.size();
        if (v.size() != n || w.size() != n) throw std::invalid_argument("phase_transition: arrays differ in length");
        pbf::AtmosphereParams a{};
        a.dt = dt; a.phase_rate = alpha; a.latent_heat = Q; a.sat_a = A; a.sat_b = B; a.sat_c = C;
        float* out = new float[3 * n + 1];
        for (std::size_t i = 0; i < n; ++i) {
            float t = T.data()[i], vv = v.data()[i], ww = w.data()[i];
            pbf::phase_transition(a, t, vv, ww);
            out[3 * i] = t; out[3 * i + 1] = vv; out[3 * i + 2] = ww;
        }
        nb::capsule owner(out, [](void* p) noexcept { delete[] static_cast<float*>(p); });
        return nb::ndarray<nb::numpy, float>(out, {n, 3}, owner);
    }, "temperature"_a, "vapor"_a, "cloud"_a, "dt"_a, "alpha"_a, "latent_heat"_a, "A"_a, "B"_a, "C"_a);
}
