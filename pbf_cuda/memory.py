"""Memory a particle simulation needs, estimated before anything is allocated.

The estimate counts the solver's per-slot arrays as SolverData::allocate makes them for the scene's
options (solver_data.h; :func:`solver_bytes_per_slot`), the radix sort's scratch, the neighbour lists,
the boundary particles,
the uniform cell grid, and the host arrays built while the initial state is made.  Adaptive scenes
reserve ``adaptive.capacity`` slots per initial particle.  :func:`check_memory` compares it with
what the chosen device has available and raises :class:`~pbf_cuda.scene.SceneError` naming the
particle count and the memory needed.  tests/test_memory_estimate.py measures the bytes per slot the
CPU solver allocates against :func:`solver_bytes_per_slot`, so the two cannot drift apart.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

from .scene import Scene, SceneError

__all__ = ["MemoryEstimate", "estimate_memory", "available_memory", "check_memory", "solver_bytes_per_slot",
           "cuda_memory_in_use"]

FLOAT4, FLOAT, UINT = 16, 4, 4
SORT_SCRATCH_BYTES = 1           # the radix sort's own scratch (CUB's digit histograms and look-back tiles, under
                                 # a byte per particle); its second buffers are uint_tmp and perm_alt
ADAPTIVE_SLOT_ARRAY_BYTES = 21   # SolverData::allocate's split/merge bookkeeping: a uint8 flag, the shape energy,
                                 # the split count, slot and candidate, the merge partner (4 bytes each)
ADAPTIVE_STEP_BYTES = 43         # made during a step: room for the sub-cells and the merge walk's mark per cell
                                 # (a cell holds several slots)
ADAPTIVE_BYTES_PER_SLOT = ADAPTIVE_SLOT_ARRAY_BYTES + ADAPTIVE_STEP_BYTES
BYTES_PER_BOUNDARY = 256         # float4 position, three floats, and the walls' table: each boundary particle
                                 # copied (float4) into the segments of the 11-14 cells that reach it
                                 # (stats()["wall_candidates"]: growing, dam_break, cycling)
BYTES_PER_CELL = 12              # fluid cell start/end and the walls' table offset (uint32 each)
HOST_BYTES_PER_PARTICLE = 160    # numpy arrays while the initial state is built (float64 lattices)
HOST_BYTES_PER_BOUNDARY = 96
LIST_ROW_WIDTH = 1.4             # the lists' row width over the mean candidates of a uniform run: the longest
                                 # row of a disordered run plus the eighth the solver adds (neighbor_list.h)
ADAPTIVE_LIST_ROW_WIDTH = 4.0    # the same in adaptive runs: a coarse particle beside finer ones lists more
MAX_CELLS = 2**32 - 1            # the solver's cell index is a uint32
MAX_SLOTS = 2**32 - 2            # particle ids are uint32
MAX_LIST_ENTRIES = 2**32 - 1     # the solver keeps at most this many list slots (n x row width)
SAFETY = 0.8                     # use at most this fraction of what is available


@dataclass(frozen=True)
class MemoryEstimate:
    fluid: int          # initial fluid particles
    slots: int          # preallocated particle slots (adaptive capacity included)
    boundary: int       # boundary particles
    cells: int          # cells of the neighbour grid
    device_bytes: int   # solver arrays on the backend's device
    host_bytes: int     # numpy arrays on the host while the state is built

    def describe(self) -> str:
        extra = f" ({self.slots:,} slots with the adaptive capacity)" if self.slots != self.fluid else ""
        return (f"{self.fluid:,} fluid particles{extra}, {self.boundary:,} boundary particles, "
                f"{self.cells:,} grid cells")


def _lattice(scene: Scene) -> tuple[list[int], list[int]]:
    """Sites per axis of the domain lattice and boundary layers per wall axis (initial_state's lattice)."""
    d = scene.particles.spacing
    counts = [max(1, int(round(L / d))) for L in scene.domain.size]
    h = scene.kernel_radius
    ext = [int(math.ceil(h / (L / n))) if b == "wall" else 0
           for L, n, b in zip(scene.domain.size, counts, scene.domain.boundary)]
    return counts, ext


def boundary_count(scene: Scene) -> int:
    """Boundary particles of the scene (the shell of initial_state.boundary_particles), counted."""
    counts, ext = _lattice(scene)
    if not any(ext):
        return 0
    return math.prod(n + 2 * e for n, e in zip(counts, ext)) - math.prod(counts)


def cell_count(scene: Scene) -> int:
    """Cells of the solver's neighbour grid (grid.h: cells of at least the kernel radius)."""
    h = scene.kernel_radius
    total = 1
    for L, b in zip(scene.domain.size, scene.domain.boundary):
        if b == "periodic":
            total *= max(3, int(math.floor(L / h)))
        else:
            total *= max(1, int(math.ceil((L + 2.0 * h) / h - 1e-4)))
    return total


def particle_slots(scene: Scene, n: int) -> int:
    """Particle slots the solver preallocates for `n` initial particles: n, or adaptive.capacity times n
    for an adaptive scene (room for the children of splits)."""
    if scene.adaptive.enabled:
        return max(n, int(math.ceil(n * scene.adaptive.capacity)))
    return n


def solver_bytes_per_slot(scene: Scene) -> int:
    """Bytes per particle slot of the solver's arrays, as SolverData::allocate makes them for the scene:
    pos, pred, pos_tmp, vel, vel_tmp (and omega with vorticity confinement) as float4; id, uint_tmp, keys,
    perm, perm_alt as uint32; lambda, density, float_tmp as float; the velocity projection's r, p, q, diag, mu (and
    the gradient correction's 6 floats, the shift's 1); temperature, vapor, cloud; one output per smoothed
    field; the sort's scratch; the adaptive bookkeeping. (Measured on an H100: 170 bytes per particle for
    `growing` without neighbour lists at 240M particles, all device memory the run held, when the sort's second
    buffers were 8 bytes of Thrust's scratch; this gives 169.)"""
    p = scene.pbf
    bytes_ = (5 + (p.vorticity > 0)) * FLOAT4 + 5 * UINT + 3 * FLOAT + SORT_SCRATCH_BYTES
    if p.projection == "velocity":
        bytes_ += (5 + 6 * p.gradient_correction + (p.shift_keeps_anomaly and scene.thermodynamics)) * FLOAT
    if scene.thermodynamics:
        bytes_ += 3 * FLOAT
    if scene.smoothing_active:
        bytes_ += len(scene.smoothing.fields) * FLOAT
    if scene.adaptive.enabled:
        bytes_ += ADAPTIVE_BYTES_PER_SLOT
    return int(bytes_)


def neighbor_list_bytes_per_slot(scene: Scene, slots: int = 1, backend: str = "cpu") -> int:
    """Bytes per particle slot of the per-step neighbour lists (pbf.neighbor_list): a count and a row of
    uint32 candidates, the row LIST_ROW_WIDTH times the candidates within (1 + skin) kernel radii of a full
    lattice neighbourhood (ADAPTIVE_LIST_ROW_WIDTH in adaptive scenes), and on the GPU the list passes' thread
    order (a uint32, solver_data.h: pass_order). Past MAX_LIST_ENTRIES slots in all (`slots` rows) the solver gives
    the lists up and searches the cells (grid_launch.h): the counts (and the order) only."""
    if not scene.pbf.neighbor_list:
        return 0
    per_slot = UINT * (2 if backend == "cuda" else 1)
    candidates = 4.0 / 3.0 * math.pi * (1.1 * scene.particles.kernel_ratio) ** 3
    width = candidates * (ADAPTIVE_LIST_ROW_WIDTH if scene.adaptive.enabled else LIST_ROW_WIDTH)
    if slots * width > MAX_LIST_ENTRIES:
        return per_slot
    return per_slot + int(math.ceil(UINT * width))


def estimate_memory(scene: Scene, backend: str = "cpu", fluid: int | None = None,
                    boundary: int | None = None) -> MemoryEstimate:
    """Bytes a Simulation of `scene` needs on `backend` ('cpu' or 'cuda'); `fluid`/`boundary` override
    the particle counts (a simulation made from given arrays)."""
    n = scene.estimated_particles() if fluid is None else int(fluid)
    slots = particle_slots(scene, n)
    nb = boundary_count(scene) if boundary is None else int(boundary)
    cells = cell_count(scene)
    per_slot = solver_bytes_per_slot(scene) + neighbor_list_bytes_per_slot(scene, slots, backend)
    device = slots * per_slot + nb * BYTES_PER_BOUNDARY + cells * BYTES_PER_CELL
    host = n * HOST_BYTES_PER_PARTICLE + nb * HOST_BYTES_PER_BOUNDARY
    return MemoryEstimate(n, slots, nb, cells, device, host)


def _cgroup_available() -> int | None:
    """Memory left under this process's cgroup (v2) limit, if there is one."""
    try:
        base = Path("/sys/fs/cgroup")
        limit = (base / "memory.max").read_text().strip()
        if limit == "max":
            return None
        return max(0, int(limit) - int((base / "memory.current").read_text().strip()))
    except (OSError, ValueError):
        return None


def cuda_memory_info() -> tuple[int, int] | None:
    """(free, total) bytes of CUDA device 0 (cudaMemGetInfo; (0, 0) without a device), or None when the
    compiled module cannot say (built without CUDA)."""
    try:
        from . import _core as core
        info = getattr(core, "cuda_memory_info", None)
        if info is None:
            return None
        free, total = info()
        return int(free), int(total)
    except Exception:  # noqa: BLE001  (no device information)
        return None


def cuda_memory_in_use() -> int | None:
    """Bytes in use on CUDA device 0, the context included (total - free); None without a device."""
    info = cuda_memory_info()
    return info[1] - info[0] if info is not None and info[1] else None


def available_memory(backend: str = "cpu") -> int | None:
    """Bytes available on `backend`'s device: host memory for 'cpu' (psutil, else sysconf, capped by a
    cgroup limit); for 'cuda' the free device memory when the compiled module reports it, else None."""
    if backend == "cuda":
        info = cuda_memory_info()                 # None: skip the device check
        return info[0] if info is not None else None
    try:
        import psutil
        host = int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001
        try:
            host = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
    cgroup = _cgroup_available()
    return min(host, cgroup) if cgroup is not None else host


def _gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**28 else f"{n / 2**20:.1f} MiB"


def check_memory(scene: Scene, backend: str = "cpu", fluid: int | None = None,
                 boundary: int | None = None) -> MemoryEstimate:
    """Raise SceneError when `scene` cannot fit on `backend`; returns the estimate otherwise."""
    est = estimate_memory(scene, backend, fluid, boundary)
    if est.slots > MAX_SLOTS:
        raise SceneError(f"{scene.name}: {est.fluid:,} particles ({est.slots:,} slots) exceed the solver's "
                         f"limit of {MAX_SLOTS:,} (uint32 ids); raise particles.spacing or lower adaptive.capacity")
    if est.cells > MAX_CELLS:
        raise SceneError(f"{scene.name}: {est.cells:,} grid cells exceed the solver's limit of {MAX_CELLS:,}; "
                         f"the domain is too large for the kernel radius (domain.size, particles.spacing)")
    host = available_memory("cpu")
    host_need = est.host_bytes + (est.device_bytes if backend == "cpu" else 0)
    if host is not None and host_need > SAFETY * host:
        raise SceneError(f"{scene.name}: {est.describe()} need about {_gib(host_need)} of host memory on the "
                         f"{backend} backend, {_gib(host)} available; lower the particle count (particles.spacing, "
                         f"--particles) or adaptive.capacity, or set pbf.neighbor_list = false")
    if backend == "cuda":
        device = available_memory("cuda")
        if device is not None and est.device_bytes > SAFETY * device:
            raise SceneError(f"{scene.name}: {est.describe()} need about {_gib(est.device_bytes)} of GPU memory, "
                             f"{_gib(device)} free; lower the particle count (particles.spacing, --particles) "
                             f"or adaptive.capacity, or set pbf.neighbor_list = false")
    return est
