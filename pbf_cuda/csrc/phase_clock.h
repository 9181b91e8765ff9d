// The phase timers of the step (PhaseTotals in solver_api.h): begin(phase) and end(phase) around a phase's launches,
// collect(totals) once per step.
#pragma once
#ifndef PBF_BACKEND_NS
#error "phase_clock.h belongs to a backend: backend_cpu.cpp or backend_cuda.cu define PBF_BACKEND_NS"
#endif
#include <chrono>
#include <cstddef>
#include <vector>

#include "solver_api.h"

#ifdef PBF_BACKEND_CUDA
#include <cuda_runtime.h>
#endif

namespace pbf {
namespace PBF_BACKEND_NS {

// ---- phase timers: CUDA events on the GPU, steady clock on the CPU ------------------------------
#ifdef PBF_BACKEND_CUDA
class PhaseClock {
public:
    ~PhaseClock() {
        for (auto& e : events_) cudaEventDestroy(e);
    }
    void begin(int p) { open_[p] = record(); }
    void end(int p) {
        pairs_.push_back({p, open_[p], record()});
        ran_[p] = true;
    }
    // Called once per step after the device work was issued: waits and accumulates.
    void collect(PhaseTotals& totals) {
        if (!pairs_.empty()) cudaEventSynchronize(events_[pairs_.back().stop]);
        for (auto& pr : pairs_) {
            float ms = 0.0f;
            cudaEventElapsedTime(&ms, events_[pr.start], events_[pr.stop]);
            totals.total_ms[pr.phase] += ms;
        }
        for (int p = 0; p < kNumPhases; ++p)
            if (ran_[p]) totals.count[p] += 1, ran_[p] = false;
        pairs_.clear();
        used_ = 0;
    }

private:
    struct Pair { int phase, start, stop; };
    int record() {
        if (used_ == events_.size()) {
            cudaEvent_t e;
            cudaEventCreate(&e);
            events_.push_back(e);
        }
        cudaEventRecord(events_[used_]);
        return int(used_++);
    }
    std::vector<cudaEvent_t> events_;
    std::size_t used_ = 0;
    std::vector<Pair> pairs_;
    int open_[kNumPhases] = {};
    bool ran_[kNumPhases] = {};
};
#else
class PhaseClock {
public:
    void begin(int p) { open_[p] = std::chrono::steady_clock::now(); }
    void end(int p) {
        pending_[p] += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - open_[p]).count();
        ran_[p] = true;
    }
    void collect(PhaseTotals& totals) {
        for (int p = 0; p < kNumPhases; ++p) {
            totals.total_ms[p] += pending_[p];
            pending_[p] = 0.0;
            if (ran_[p]) totals.count[p] += 1, ran_[p] = false;
        }
    }

private:
    std::chrono::steady_clock::time_point open_[kNumPhases];
    double pending_[kNumPhases] = {};
    bool ran_[kNumPhases] = {};
};
#endif

}  // namespace PBF_BACKEND_NS
}  // namespace pbf
