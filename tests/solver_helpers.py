"""Helpers shared by the solver tests: backend parametrisation and small scenes."""
import numpy as np
import pytest

BACKENDS = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def by_id(state: dict) -> dict:
    """State arrays reordered by particle id (the solver re-sorts particles every step)."""
    order = np.argsort(state["id"], kind="stable")
    return {k: v[order] for k, v in state.items()}
