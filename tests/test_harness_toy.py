"""A small deterministic stand-in for pbf_cuda.Simulation, so the harness's cache, resume and
instability handling are tested even where the compiled solver is absent.

It honours the simulation protocol the run loop uses (step, step_count, time, size, n_particles, backend,
scene, state, stats, timings, reset_timings, save, load) and counts every step it takes.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cloudpbf import solvers
from cloudpbf_io.files import atomic_path
from pbf_cuda.protocol import InstabilityError
from pbf_cuda.scene import load_scene


class ToySimulation:
    """Particles on the scene's lattice, pulled toward the domain centre by a spring (rate k = 1e-3 /s^2)
    plus a seeded random forcing and pbf.gravity; velocity blows up (x10 per step) when scene.time.dt > 100 s."""
    steps_taken = 0          # class-wide counter: the cache tests assert on it

    def __init__(self, scene, backend="cpu", seed=None, _state=None):
        self.scene, self.backend, self.seed = scene, "cpu", seed
        if _state is None:
            shape = scene.lattice_shape()
            d = scene.particles.spacing
            grid = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) * d for n in shape], indexing="ij"), -1)
            self.pos = grid.reshape(-1, 3).astype(np.float64)
            self.vel = np.zeros_like(self.pos)
            self.temperature = 300.0 - 0.0065 * self.pos[:, 1]
            self.step_count, self.time = 0, 0.0
        else:
            self.pos, self.vel, self.temperature = _state["pos"], _state["vel"], _state["temperature"]
            self.step_count, self.time = int(_state["step"]), float(_state["time"])
        self.ids = np.arange(len(self.pos), dtype=np.uint32)
        self._timings = {}

    @property
    def n_particles(self):
        return len(self.pos)

    @property
    def size(self):
        return self.n_particles

    def step(self, n=1):
        dt = self.scene.time.dt
        centre = np.asarray(self.scene.domain.size) / 2
        for _ in range(n):
            rng = np.random.default_rng([self.seed or 0, self.step_count])
            force = (-1e-3 * (self.pos - centre) + 1e-3 * rng.standard_normal(self.pos.shape)
                     + np.asarray(self.scene.pbf.gravity))
            self.vel = self.vel * (10.0 if dt > 100 else 1.0) + dt * force
            self.pos = self.pos + dt * self.vel
            self.step_count += 1
            self.time += dt
            ToySimulation.steps_taken += 1
            t = self._timings.setdefault("pbf", [0.0, 0])
            t[0] += 1.0
            t[1] += 1
            speed = np.linalg.norm(self.vel, axis=1)
            if speed.max() > self.scene.pbf.max_velocity:
                bad = self.ids[speed > self.scene.pbf.max_velocity]
                raise InstabilityError(self.step_count, "velocity above pbf.max_velocity", bad,
                                          self.step_count - 1)

    def state(self):
        return {"position": self.pos.astype(np.float32), "velocity": self.vel.astype(np.float32),
                "temperature": self.temperature.astype(np.float32), "id": self.ids.copy()}

    def stats(self):
        return {"step": self.step_count, "time": self.time, "n_particles": self.n_particles,
                "max_speed": float(np.linalg.norm(self.vel, axis=1).max()),
                "min_position": self.pos.min(axis=0).tolist(), "max_position": self.pos.max(axis=0).tolist(),
                "level_counts": [self.n_particles], "backend": "cpu"}

    def timings(self):
        return {k: {"total_ms": t, "count": c, "mean_ms": t / c} for k, (t, c) in self._timings.items() if c}

    def reset_timings(self):
        self._timings = {}

    def save(self, path):
        meta = json.dumps({"scene": self.scene.to_dict(), "step": self.step_count, "time": self.time,
                           "seed": self.seed})
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, pos=self.pos, vel=self.vel, temperature=self.temperature,
                         meta=np.frombuffer(meta.encode(), np.uint8))

    @classmethod
    def load(cls, path):
        from pbf_cuda.scene import scene_from_dict
        with np.load(path) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            state = {"pos": z["pos"], "vel": z["vel"], "temperature": z["temperature"],
                     "step": meta["step"], "time": meta["time"]}
        return cls(scene_from_dict(meta["scene"]), seed=meta["seed"], _state=state)


class ToyAdapter(solvers.ParticleAdapter):
    """The particle adapter with the toy solver and a small diagnostics function (mean height, profile)."""

    @staticmethod
    def resolve_backend(backend):
        return "cpu"

    @staticmethod
    def preflight(spec):
        from pbf_cuda.memory import check_memory
        check_memory(spec.scene, "cpu")

    @staticmethod
    def expected_scene(spec):
        return spec.scene            # the toy keeps the scene as given (no seeded noise offset)

    @staticmethod
    def create(spec):
        return ToySimulation(spec.scene, seed=spec.seed)

    @staticmethod
    def load(path, spec):
        return ToySimulation.load(path)

    @staticmethod
    def diagnostics(sim, spec, state):
        y = state["position"][:, 1].astype(np.float64)
        edges = np.linspace(0.0, sim.scene.domain.size[1], 5)
        counts = np.histogram(y, bins=edges)[0]
        return ({"mean_height": float(y.mean())},
                {"z": 0.5 * (edges[1:] + edges[:-1]), "fraction": counts / max(len(y), 1)})


@pytest.fixture
def toy_solver(monkeypatch):
    """Swap the particle solver for the toy; yields the ToySimulation class (its step counter reset)."""
    monkeypatch.setitem(solvers.ADAPTERS, "particles", ToyAdapter)
    ToySimulation.steps_taken = 0
    return ToySimulation


def toy_scene(**overrides):
    """A 6x5x6-particle box (walls on y) the toy runs in milliseconds."""
    base = {"domain.size": [600.0, 500.0, 600.0], "particles.spacing": 100.0, "time.steps": 20,
            "time.snapshot_every": 5, "time.dt": 2.0}
    base.update(overrides)
    return load_scene("growing", **base)


def test_toy_checkpoint_round_trip_is_exact(tmp_path):
    sim = ToySimulation(toy_scene(), seed=3)
    sim.step(4)
    sim.save(tmp_path / "c.npz")
    again = ToySimulation.load(tmp_path / "c.npz")
    sim.step(5)
    again.step(5)
    assert again.step_count == sim.step_count == 9
    np.testing.assert_array_equal(again.pos, sim.pos)


def test_toy_seeds_differ():
    a, b = ToySimulation(toy_scene(), seed=1), ToySimulation(toy_scene(), seed=2)
    a.step(3)
    b.step(3)
    assert not np.array_equal(a.pos, b.pos)
