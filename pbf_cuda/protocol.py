"""What every solver of the project is, to the harness: the simulation protocol and its one error.

Both ``pbf_cuda.Simulation`` (particles) and ``grid_baseline.GridSimulation`` (cells) satisfy
:class:`SimulationProtocol`; both raise :class:`InstabilityError`, as does the harness when its own
checks find a run unstable.  Pure Python: the grid baseline imports it without the compiled core.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Protocol, runtime_checkable

import numpy as np

__all__ = ["InstabilityError", "SimulationProtocol"]


class InstabilityError(RuntimeError):
    """The run went unstable: NaN/Inf, a velocity or a density error over its bound, particles
    escaping through a wall.

    Attributes: ``step`` (the step that produced it), ``reason``, ``particles`` (ids of offending
    particles or cells, at most 16 shown; empty where none is singled out), ``last_good_step`` (the
    last step whose state passed the check; the caller's last checkpoint is at or before it).
    """

    def __init__(self, step: int, reason: str, particles: Iterable[int] = (), last_good_step: int = -1):
        self.step = int(step)
        self.reason = reason
        self.particles = [int(p) for p in particles]
        self.last_good_step = int(last_good_step)
        ids = ", ".join(map(str, self.particles[:16])) or "none identified"
        super().__init__(f"unstable at step {self.step}: {reason}; particles (ids): {ids}; "
                         f"last good step {self.last_good_step}")


@runtime_checkable
class SimulationProtocol(Protocol):
    """A solver as the harness drives it (units: SI; time in s)."""

    scene: object                     # the pbf_cuda.scene.Scene it runs

    @property
    def step_count(self) -> int:
        """Steps taken since the start (a restored checkpoint keeps its count)."""

    @property
    def time(self) -> float:
        """Simulated time in s."""

    @property
    def size(self) -> int:
        """Degrees of freedom: particles, or grid cells."""

    def step(self, n: int = 1) -> None:
        """Advance n steps; raises InstabilityError at the first step whose check fails."""

    def state(self) -> dict[str, np.ndarray]:
        """Host arrays of the current state (particles: position, velocity, ... per particle)."""

    def stats(self) -> dict:
        """Scalar statistics of the current state (and the step counters)."""

    def timings(self) -> dict[str, dict]:
        """Wall time per phase in ms: {phase: {total_ms, count, mean_ms}}."""

    def reset_timings(self) -> None:
        """Forget the timings so far (after warm-up steps)."""

    def save(self, path: str | Path) -> Path:
        """Write a checkpoint that load() restores bit-exactly, atomically."""
