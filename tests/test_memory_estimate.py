"""The memory estimate (pbf_cuda/memory.py) against what the CPU solver allocates: the bytes per particle
slot of the arrays SolverData::allocate makes, measured with glibc's allocator statistics as the slope of
the process's allocated bytes over the slot count (fixed domain, cells and walls; only the filled region
grows), must equal the estimate's per-slot bytes less the parts made during a step, within a quarter byte
per slot: one new array of the smallest type (a uint8 per slot) fails it."""
import ctypes
import gc

import pytest

from pbf_cuda import Simulation, load_scene
from pbf_cuda.memory import ADAPTIVE_STEP_BYTES, SORT_SCRATCH_BYTES, UINT, particle_slots, solver_bytes_per_slot


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


def _mallinfo2():
    try:
        fn = ctypes.CDLL(None).mallinfo2
    except (AttributeError, OSError):
        pytest.skip("needs glibc's mallinfo2 (glibc >= 2.33)")
    fn.restype = _MallInfo2
    return fn


def _allocated_bytes(mallinfo2) -> int:
    """Bytes the process's allocator has handed out and not taken back (heap chunks in use + mmapped)."""
    gc.collect()
    info = mallinfo2()
    return info.uordblks + info.hblkhd


def _bytes_of_simulation(mallinfo2, scene) -> tuple[int, int]:
    """(slots, bytes allocated by making a CPU Simulation of `scene` and kept while it lives)."""
    before = _allocated_bytes(mallinfo2)
    sim = Simulation(scene, backend="cpu", seed=0)
    held = _allocated_bytes(mallinfo2) - before
    slots = particle_slots(scene, sim.size)
    del sim
    return slots, held


def _allocated_per_slot(scene) -> int:
    """The estimate's per-slot bytes of the arrays made when the solver is built: solver_bytes_per_slot less
    the sort's scratch and the adaptive step's arrays (made during a step), plus the neighbour lists' count
    (neighbor_list_bytes_per_slot's first uint32 per slot on the CPU; the rows are sized at the first step)."""
    made_in_step = SORT_SCRATCH_BYTES + (ADAPTIVE_STEP_BYTES if scene.adaptive.enabled else 0)
    return solver_bytes_per_slot(scene) - made_in_step + (UINT if scene.pbf.neighbor_list else 0)


CASES = [
    ("growing", {}),
    ("growing", {"pbf.vorticity": 0.0, "pbf.neighbor_list": False}),
    ("growing", {"pbf.projection": "velocity", "pbf.gradient_correction": True, "pbf.shift_keeps_anomaly": True}),
    ("growing", {"smoothing.fields": ["temperature", "vapor", "cloud"]}),
    ("growing", {"smoothing.kappa": 0.0}),
    ("growing_adaptive", {}),
    ("dam_break", {}),      # no atmosphere: no thermodynamic arrays
]


@pytest.fixture(scope="module")
def mallinfo2():
    fn = _mallinfo2()
    _bytes_of_simulation(fn, load_scene("growing").with_particle_count(2_000))   # first-use allocations
    return fn


def _block(scene, layers: int):
    """`scene` with a 64 x `layers` x 64 block of particles (a spacing of a 64th of the narrower horizontal side):
    slot counts that are multiples of 4096, so every array fills whole pages and the allocator's rounding
    is the same at both sizes."""
    spacing = min(scene.domain.size[0], scene.domain.size[2]) / 64
    return scene.replace(**{"particles.spacing": spacing, "particles.fill_min": [0.0, 0.0, 0.0],
                            "particles.fill_max": [64 * spacing, layers * spacing, 64 * spacing]})


@pytest.mark.parametrize("name, overrides", CASES, ids=[f"{n}-{'-'.join(o) or 'default'}" for n, o in CASES])
def test_estimate_counts_the_bytes_the_solver_allocates_per_slot(mallinfo2, name, overrides):
    scene = load_scene(name, **overrides)
    small, large = _block(scene, 16), _block(scene, 32)
    _bytes_of_simulation(mallinfo2, small)   # a first run of each scene warms caches the slope must not see
    (slots_small, bytes_small), (slots_large, bytes_large) = (_bytes_of_simulation(mallinfo2, s) for s in (small, large))
    assert slots_small % 4096 == 0 and slots_large == 2 * slots_small
    measured = (bytes_large - bytes_small) / (slots_large - slots_small)
    assert measured == pytest.approx(_allocated_per_slot(scene), abs=0.25), \
        f"{name} {overrides}: the solver allocates {measured:.2f} bytes per slot; pbf_cuda/memory.py counts " \
        f"{_allocated_per_slot(scene)} (SolverData::allocate changed: update solver_bytes_per_slot)"
