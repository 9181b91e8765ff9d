"""The small figures of the report's first screen (cloudpbf.report.glance): one per verdict card, drawn at the
size a card shows them (about 400 x 170 px), returned as PNG data URIs."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

from .plots import to_data_uri  # noqa: E402

CARD_SIZE = (4.0, 1.7)    # inches at plots.DPI: the card's figure slot
GREEN, ORANGE, RED, GREY, BLUE = "#2ca02c", "#ff9f1c", "#d62728", "#9aa7b4", "#1f77b4"


def _figure():
    fig, ax = plt.subplots(figsize=CARD_SIZE, layout="constrained")
    ax.tick_params(labelsize=7)
    return fig, ax


def bars(labels, values, reference=None, ylabel: str = "", log: bool = True, reference_label: str = "paper") -> str:
    """Measured values as bars, with the reference's (the paper's) beside them where given."""
    fig, ax = _figure()
    x = np.arange(len(labels))
    width = 0.4 if reference is not None else 0.7
    ax.bar(x - (width / 2 if reference is not None else 0), values, width, color=BLUE, label="measured")
    if reference is not None:
        ax.bar(x + width / 2, reference, width, color=GREY, label=reference_label)
        ax.legend(fontsize=6, loc="upper left", frameon=False)
    ax.set_xticks(x, labels, fontsize=6)
    if log:
        ax.set_yscale("log")
    ax.set_ylabel(ylabel, fontsize=7)
    return to_data_uri(fig)


def front(uniform_x, uniform_y, others_x, others_y, best=None, xlabel: str = "ms per step",
          ylabel: str = "error", uniform_label: str = "uniform", others_label: str = "adaptive") -> str:
    """Cost against error: the uniform runs as a line, the others as points, the best one starred."""
    fig, ax = _figure()
    order = np.argsort(uniform_x)
    ax.plot(np.asarray(uniform_x)[order], np.asarray(uniform_y)[order], "o-", color=BLUE, ms=3,
            label=uniform_label)
    ax.plot(others_x, others_y, "s", color=ORANGE, ms=3, label=others_label)
    if best is not None:
        ax.plot([best[0]], [best[1]], "*", color=RED, ms=10, label="best")
    ax.set_xlabel(xlabel, fontsize=7)
    ax.set_ylabel(ylabel, fontsize=7)
    if len(uniform_x) and min(list(uniform_x) + list(others_x)) > 0:
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.legend(fontsize=6, frameon=False)
    return to_data_uri(fig)


def intervals(labels, means, los, his, xlabel: str) -> str:
    """One row per group: its mean and 95% interval."""
    fig, ax = _figure()
    y = np.arange(len(labels))
    means, los, his = (np.asarray(v, dtype=float) for v in (means, los, his))
    ax.errorbar(means, y, xerr=[means - los, his - means], fmt="o", color=BLUE, capsize=3, ms=4)
    ax.set_yticks(y, labels, fontsize=7)
    ax.set_ylim(-0.6, len(labels) - 0.4)
    ax.set_xlabel(xlabel, fontsize=7)
    ax.grid(True, axis="x", alpha=0.3)
    return to_data_uri(fig)


def strip(values, states, xlabel: str = "time step dt (s)", stable_label: str = "stable, not usable") -> str:
    """One marker per tried value: green usable, orange stable but not usable (or not checked), red unstable."""
    fig, ax = _figure()
    colours = {"usable": GREEN, "stable": ORANGE, "unstable": RED}
    markers = {"usable": "o", "stable": "s", "unstable": "X"}
    labels = {"usable": "usable", "stable": stable_label, "unstable": "unstable"}
    values = np.asarray(values, dtype=float)
    for state in ("usable", "stable", "unstable"):
        mask = np.array([s == state for s in states], dtype=bool)
        if mask.any():
            ax.scatter(values[mask], np.zeros(mask.sum()), s=70, color=colours[state], marker=markers[state],
                       label=labels[state])
    if len(values) and (values > 0).all() and values.max() / values.min() > 20:
        ax.set_xscale("log")
    ax.set_yticks([])
    ax.set_ylim(-1, 1.4)
    ax.set_xlabel(xlabel, fontsize=7)
    ax.legend(fontsize=6, loc="upper left", ncol=3, frameon=False)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    return to_data_uri(fig)
