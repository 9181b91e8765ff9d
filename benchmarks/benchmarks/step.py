"""The particle solver's step time at a few sizes, on the CPU and (where one exists) on a CUDA GPU.

One benchmark per (backend, scene, particles): the ``growing`` cloud scene (paper example 1,
non-adaptive) and its adaptive twin ``growing_adaptive`` (split and merge on), scaled to the given
particle count (fine-particle equivalents, as the harness scales them).  ``setup`` creates the
simulation and takes two warm-up steps (first-touch allocation, neighbour grid sizing); the timed
body is one step (``Simulation.step(1)``: PBF with its neighbour search, smoothing, cloud physics and,
when adaptive, splitting and merging).  Sizes that a backend does not run are skipped (asv prints
"n/a"): the CPU runs the small sizes, the GPU the large ones, so a run on either machine stays within
minutes.  ``CLOUDPBF_ASV_SIZES`` (comma-separated) narrows the sizes of a run, e.g. for a quick check.
"""
import os

BACKENDS = ("cpu", "cuda")
SCENES = ("growing", "growing_adaptive")
SIZES = (2_000, 16_000, 64_000, 250_000, 1_000_000)
RUNS_ON = {"cpu": (2_000, 16_000, 64_000), "cuda": (64_000, 250_000, 1_000_000)}


def _selected(particles: int) -> bool:
    chosen = os.environ.get("CLOUDPBF_ASV_SIZES")
    return not chosen or str(particles) in chosen.replace(" ", "").split(",")


def _scene(name: str, particles: int):
    from pbf_cuda import load_scene
    try:
        from cloudpbf.studies.scales import scale_scene
    except ImportError:      # a recorded commit from before the harness's package was named cloudpbf
        from bench.studies.scales import scale_scene
    return scale_scene(load_scene(name), particles)


class SolverStep:
    """Wall time of one solver step (s)."""
    params = (BACKENDS, SCENES, SIZES)
    param_names = ("backend", "scene", "particles")
    number = 1            # one step per sample: a step is milliseconds (GPU) to seconds (CPU, 64k)
    repeat = (3, 10, 20.0)
    warmup_time = 0.0
    timeout = 600

    def setup(self, backend, scene, particles):
        from pbf_cuda import Simulation, available_backends
        if backend not in available_backends() or particles not in RUNS_ON[backend] or not _selected(particles):
            raise NotImplementedError(f"{backend} does not run {particles} particles here")
        self.sim = Simulation(_scene(scene, particles), backend=backend, seed=0)
        self.sim.step(2)

    def time_step(self, backend, scene, particles):
        self.sim.step(1)

    def track_particles(self, backend, scene, particles):
        """Particles in the simulation after the warm-up (adaptive scenes: fewer than the uniform count)."""
        return int(self.sim.stats().get("n_particles", len(self.sim.state()["position"])))

    track_particles.unit = "particles"
