"""The bandwidth roofline of one particle step: the bytes a step must move at the least, over a copy
bandwidth measured on the same device in the same run.

The least a step can move: each of its neighbour passes (the sweeps that cannot be fused, because each
needs its neighbours' results of the one before: a density iteration's lambda, then its position
correction; the projection's J^T then J; ...) reads every particle's own inputs once and writes its outputs
once. Neighbours' values are taken to come from cache, the elementwise updates between two passes are
fused into them, and nothing the implementation chose is counted (neighbour lists, sort scratch beyond one
key-value pass, statistics). So `roofline_ms = particles * step_bytes / copy_bandwidth` is a floor no
implementation of the same algorithm can go below on that device, and `step_ms / roofline_ms` says how far
a step is from it: how much of the step is neighbour gathering and latency rather than streaming.

The copy bandwidth counts every byte read and every byte written (a device-to-device copy of n bytes moves
2 n); the CPU's is a copy of a 256 MiB array split across one thread per core.
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pbf_cuda.kernels import _core
from pbf_cuda.scene import Scene

FLOAT, UINT, FLOAT4 = 4, 4, 16       # bytes: a float, a uint32, a float4 (x, y, z, mass)


def step_passes(scene: Scene) -> list[tuple[str, int, int]]:
    """(pass, bytes read, bytes written) per particle for one step of `scene`, in the step's order
    (Solver::do_step). Uniform runs: the adaptive phases are not counted."""
    p = scene.pbf
    velocity = p.projection == "velocity"
    thermo = scene.thermodynamics
    fields = 3 if thermo else 0                           # temperature, vapor, cloud
    record = 3 * FLOAT4 + UINT + (FLOAT if velocity else 0) + fields * FLOAT   # pos, pred, vel, id, mu, T v c
    passes = [("predict x* = x + dt v", 2 * FLOAT4, FLOAT4),
              ("cell keys", FLOAT4, 2 * UINT),
              ("sort (one key-value pass)", 2 * UINT, 2 * UINT),
              ("reorder the records", record, record)]
    for _ in range(p.iterations):
        passes += [("density, lambda (eq. 1-4)", FLOAT4, 2 * FLOAT),
                   ("position correction (eq. 18)", FLOAT4 + FLOAT, FLOAT4)]
    if not velocity:
        passes.append(("v = (x* - x) / dt", 2 * FLOAT4, FLOAT4))
    if p.xsph > 0 or p.viscosity > 0 or p.vorticity > 0:
        passes.append(("XSPH, viscosity, curl v", 2 * FLOAT4 + FLOAT, FLOAT4 + (FLOAT4 if p.vorticity > 0 else 0)))
    if p.vorticity > 0:
        passes.append(("vorticity confinement", 3 * FLOAT4 + FLOAT, FLOAT4))
    if scene.smoothing_active:
        n = len(scene.smoothing.fields)
        passes.append(("smoothing (eq. 12-17)", FLOAT4 + n * FLOAT, n * FLOAT))
    if thermo:
        passes.append(("cloud dynamics (eq. 5-11)", 3 * FLOAT4 + fields * FLOAT, FLOAT4 + fields * FLOAT))
    if velocity:
        if p.gradient_correction:
            passes.append(("gradient correction L_i", FLOAT4, 6 * FLOAT))
        passes += [("J^T mu_prev", FLOAT4 + FLOAT, FLOAT4),
                   ("J v, CG start", 3 * FLOAT4, FLOAT4 + 3 * FLOAT)]
        for k in range(p.divergence_iterations):
            passes.append(("CG: g = M^-1 J^T p", FLOAT4 + FLOAT, FLOAT4))
            if k + 1 < p.divergence_iterations:
                passes.append(("CG: q = J g, update", 3 * FLOAT4 + 3 * FLOAT, FLOAT4 + 3 * FLOAT))
            else:   # the last step needs no residual: p.Ap = sum m |g|^2, then v and mu
                passes.append(("CG: last update", 3 * FLOAT4 + 2 * FLOAT, FLOAT4 + FLOAT))
    passes.append(("commit x = x*", FLOAT4, FLOAT4))
    return passes


def step_bytes(scene: Scene) -> int:
    """The least bytes one step moves per particle (step_passes, read + written)."""
    return sum(r + w for _, r, w in step_passes(scene))


def copy_bandwidth(backend: str, nbytes: int = 1 << 30, repeats: int = 20) -> float | None:
    """Copy bandwidth of the backend's device in bytes/s (read + written); None where it cannot be measured."""
    if backend == "cuda":
        measure = getattr(_core(), "cuda_copy_bandwidth", None)
        value = measure(nbytes, repeats) if measure else 0.0
        return value or None
    nbytes = min(nbytes, 1 << 28)
    src = np.ones(nbytes // 8, dtype=np.float64)
    dst = np.empty_like(src)
    threads = os.cpu_count() or 1
    edges = np.linspace(0, src.size, threads + 1).astype(int)
    bounds = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def copy(b):
        np.copyto(dst[b[0]:b[1]], src[b[0]:b[1]])

    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(copy, bounds))                       # warm-up: touch every page
        t0 = time.perf_counter()
        for _ in range(max(1, repeats // 4)):
            list(pool.map(copy, bounds))
        elapsed = time.perf_counter() - t0
    return 2.0 * src.nbytes * max(1, repeats // 4) / elapsed


def roofline_ms(scene: Scene, particles: int, bandwidth: float | None) -> float | None:
    """The step's floor in ms at `particles` particles and `bandwidth` bytes/s."""
    if not bandwidth:
        return None
    return 1e3 * particles * step_bytes(scene) / bandwidth
