"""The paper's Table 1 and the phases of a step it times: what the harness measures itself against.

PHASES: the paper's per-step phases, in its order: ``pbf`` (neighbour search, constraint iterations, velocity
update), ``smoothing``, ``cloud_dynamics``, ``splitting``, ``merging``; a timing column is ``<phase>_ms``
(ms per step).  PAPER_TABLE1: the paper's Table 1 (GeForce GTX 780 Ti), columns
``example,figure,mode,max_particles,<phase>_ms``.
"""
from __future__ import annotations

from pathlib import Path

import pandas as pd

PHASES = ("pbf", "smoothing", "cloud_dynamics", "splitting", "merging")
PAPER_TABLE1 = Path(__file__).resolve().parent / "data" / "paper_table1.csv"


def paper_table() -> pd.DataFrame:
    """The paper's Table 1 with ``total_ms``: the sum of the phases it lists, ms per step (NaN where it lists none)."""
    paper = pd.read_csv(PAPER_TABLE1)
    phase_cols = [f"{p}_ms" for p in PHASES if f"{p}_ms" in paper.columns]
    paper["total_ms"] = paper[phase_cols].sum(axis=1, min_count=1)
    return paper
