"""What a host read costs between GPU kernels: a small kernel launched back to back, against the same kernel each
followed by a 4-byte read to the host, and each followed by a device synchronisation.

    python3 benchmarks/host_round_trip.py [--reps 2000]

The adaptive step once read four counts back to the host (adaptivity_launch.h); each read leaves the GPU idle for
the round trip, which this measures (docs/performance.md, "Speed of the step", change 16). Needs CuPy and a GPU.
"""
import argparse
import sys
import time


def per_kernel_us(cp, kernel, a, wait, reps):
    """Microseconds per iteration of kernel(a) followed by wait ('none', 'read' or 'sync'); cp: the cupy module."""
    cp.cuda.runtime.deviceSynchronize()
    t0 = time.perf_counter()
    for _ in range(reps):
        kernel(a, a)
        if wait == "read":
            int(a[0:1].get()[0])
        elif wait == "sync":
            cp.cuda.runtime.deviceSynchronize()
    cp.cuda.runtime.deviceSynchronize()
    return (time.perf_counter() - t0) / reps * 1e6


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=2000, help="iterations per measurement (default 2000)")
    args = parser.parse_args(argv)
    try:
        import cupy as cp
    except ImportError:
        sys.exit("host_round_trip: needs CuPy and a GPU")
    a = cp.zeros(1 << 19, dtype=cp.float32)
    kernel = cp.ElementwiseKernel("float32 x", "float32 y", "y = x + 1.0f", "increment")
    per_kernel_us(cp, kernel, a, "none", 100)   # compile and warm up
    print(f"device: {cp.cuda.runtime.getDeviceProperties(0)['name'].decode()}")
    for repeat in range(3):
        back, read, sync = (per_kernel_us(cp, kernel, a, w, args.reps) for w in ("none", "read", "sync"))
        print(f"us per kernel: back to back {back:.1f}, each with a 4-byte read {read:.1f}, "
              f"each with a device synchronisation {sync:.1f}")


if __name__ == "__main__":
    main()
