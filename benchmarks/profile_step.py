"""Where one CUDA step's time goes, kernel by kernel (Nsight Compute).

    ncu --profile-from-start off --metrics gpu__time_duration.sum --csv \
        python3 benchmarks/profile_step.py run 1000000 growing > ncu_growing.csv
    python3 benchmarks/profile_step.py table ncu_growing.csv growing 1000000 COMMIT ["DEVICE"] >> step_profile.csv

`run N SCENE` steps SCENE (resampled to N particles; N = 0 keeps the scene's own) three times, then
profiles exactly one step (cudaProfilerStart/Stop around it, through cupy). `table` sums the kernels'
durations by kernel (the functor a parallel_for launched, a reduction's functor, or the Thrust/CUB
kernel) and writes rows (DEVICE names the GPU, an H100 where it is left out) scene, particles, kernel, launches, us, share, device, commit, method
(reports/gpu/data/step_profile.csv; docs/benchmarks.md).
"""
from __future__ import annotations

import io
import re
import sys

METHOD = "ncu gpu__time_duration.sum, one step after 3 warm-up steps"


def run(particles: int, scene_name: str) -> None:
    try:
        import cupy
    except ImportError:
        sys.exit("profile_step run: needs cupy (for cudaProfilerStart/Stop)")
    from pbf_cuda import Simulation, load_scene
    scene = load_scene(scene_name)
    if particles > 0:
        scene = scene.with_particle_count(particles)
    sim = Simulation(scene, backend="cuda", seed=0)
    sim.step(3)
    cupy.cuda.runtime.deviceSynchronize()
    cupy.cuda.profiler.start()
    sim.step(1)
    cupy.cuda.runtime.deviceSynchronize()
    cupy.cuda.profiler.stop()
    print("particles", sim.n_particles, file=sys.stderr)


def kernel_name(name: str) -> str:
    m = re.search(r"for_each_kernel<(?:pbf::|cuda_backend::)(\w+)", name)
    if m:
        return m.group(1)
    m = re.search(r"once_kernel<(?:pbf::|cuda_backend::)(\w+)", name)
    if m:
        return "once " + m.group(1)
    m = re.search(r"reduce_kernel<(?:pbf::|cuda_backend::)(\w+)", name)   # named by the functor it sums
    if m:
        return "reduction " + m.group(1)
    m = re.search(r"team_kernel<(?:pbf::|cuda_backend::)(\w+)", name)
    if m:
        return m.group(1)
    m = re.search(r"(?:pbf::|cuda_backend::)(\w+)>", name)
    if m:
        return "reduction " + m.group(1)
    return "Thrust/CUB " + re.sub(r"<.*", "", re.sub(r"^void ", "", name)).split("::")[-1]


def table(csv_path: str, scene: str, particles: int, commit: str, device: str = "NVIDIA H100 80GB HBM3"):
    import pandas as pd
    text = open(csv_path).read()
    frame = pd.read_csv(io.StringIO(text[text.find('"ID"'):]))
    frame = frame[frame["Metric Name"] == "gpu__time_duration.sum"].copy()
    scale = {"nsecond": 1e-3, "ns": 1e-3, "usecond": 1.0, "us": 1.0, "msecond": 1e3, "ms": 1e3}
    frame["us"] = (pd.to_numeric(frame["Metric Value"].astype(str).str.replace(",", ""), errors="coerce")
                   * frame["Metric Unit"].map(scale))
    frame["kernel"] = frame["Kernel Name"].map(kernel_name)
    g = frame.groupby("kernel")["us"].agg(["count", "sum"]).sort_values("sum", ascending=False).reset_index()
    total = g["sum"].sum()
    return pd.DataFrame({"scene": scene, "particles": particles, "kernel": g["kernel"], "launches": g["count"],
                         "us": g["sum"].round(3), "share": (g["sum"] / total).round(4), "device": device,
                         "commit": commit, "method": METHOD})


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "run":
        run(int(sys.argv[2]), sys.argv[3])
    elif len(sys.argv) >= 6 and sys.argv[1] == "table":
        table(sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5], *sys.argv[6:7]).to_csv(sys.stdout, index=False)
    else:
        sys.exit(__doc__)
