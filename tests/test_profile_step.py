"""benchmarks/profile_step.py: Nsight Compute's per-launch durations summed by kernel."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import profile_step  # noqa: E402

NCU = '''==PROF== Connected to process 1
"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size","Grid Size","Device","CC","Section Name","Metric Name","Metric Unit","Metric Value"
"0","1","python3","h","void cuda_backend::for_each_kernel<pbf::DensityLambda<pbf::UniformPolicy>>(unsigned int, T1)","1","7","(128, 1, 1)","(8, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","ns","1,000"
"1","1","python3","h","void cuda_backend::for_each_kernel<pbf::DensityLambda<pbf::UniformPolicy>>(unsigned int, T1)","1","7","(128, 1, 1)","(8, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","ns","3,000"
"2","1","python3","h","void cuda_backend::for_each_kernel<cuda_backend::Predict>(unsigned int, T1)","1","7","(128, 1, 1)","(8, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","usecond","1"
"3","1","python3","h","void cub::detail::radix_sort::DeviceRadixSortOnesweepKernel<int>(int)","1","7","(128, 1, 1)","(8, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","ns","1000"
"4","1","python3","h","void cuda_backend::once_kernel<cuda_backend::CgStepSize>(T1)","1","7","(1, 1, 1)","(1, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","ns","2000"
"5","1","python3","h","void cuda_backend::reduce_kernel<cuda_backend::CgResidualDots, pbf::Double2, pbf::Double2Add, cuda_backend::CgNextDirection>(unsigned int, T1, T2, T3, T2 *, T2 *, T4)","1","7","(256, 1, 1)","(8, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","ns","3000"
"6","1","python3","h","void cuda_backend::team_kernel<cuda_backend::MergePass>(unsigned int, T1)","1","7","(128, 1, 1)","(8, 1, 1)","0","9.0","Command line profiler metrics","gpu__time_duration.sum","ns","500"
'''


def test_kernels_are_summed_by_name_and_units(tmp_path):
    path = tmp_path / "ncu.csv"
    path.write_text(NCU)
    t = profile_step.table(str(path), "growing", 1000, "abc").set_index("kernel")
    assert t.loc["DensityLambda", "launches"] == 2 and t.loc["DensityLambda", "us"] == pytest.approx(4.0)
    assert t.loc["Predict", "us"] == pytest.approx(1.0)
    assert t.loc["Thrust/CUB DeviceRadixSortOnesweepKernel", "us"] == pytest.approx(1.0)
    assert t.loc["once CgStepSize", "us"] == pytest.approx(2.0)     # a one-thread kernel (run_once), not a reduction
    assert t.loc["reduction CgResidualDots", "us"] == pytest.approx(3.0)   # by the functor summed, not its finisher
    assert t.loc["MergePass", "us"] == pytest.approx(0.5)
    assert t["share"].sum() == pytest.approx(1.0, abs=1e-3)
    assert (t["commit"] == "abc").all()
