"""How evenly a warp's rows fill it: the neighbour-list rows of a state, counted from its positions and radii.

    python3 benchmarks/row_balance.py cycling_adaptive --steps 601 --backend cuda
    python3 benchmarks/row_balance.py cycling_adaptive --state state.npz

A list pass's warp runs as long as its longest row (the candidate loop of its 32 particles, read four candidates a
round), so the pass's time follows the sum over warps of the longest row, not the mean row. This counts each
particle's candidates as the lists' build finds them (every j with |x_i - x_j| below the pair's support max(h_i, h_j)
plus the lists' skin of 0.1 h0, i itself included; the support alone for the rows narrowed after the density
iterations), takes the state's order as the sort's (Simulation.state() returns the particles as the solver holds
them, sorted by cell), and prints the rounds of four candidates the warps run against their rows' mean, overall and
for the warps with and without a particle finer than level 0, and what ordering each tile of 64, 128 or 256
particles by row length would leave (row_order.h: order_tiles_by_length orders tiles of 128 on the GPU).
A state file holds position (n x 3, m), level and kernel_radius (m), as Simulation.state() gives them.
"""
from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

SKIN = 0.1   # the lists' skin as a fraction of h0 (neighbor_list.h: kNeighborSkin)
BATCH = 4    # candidates a list pass reads per round (kernel_policy.h: kListBatch)


def row_lengths(position: np.ndarray, radius: np.ndarray, size, periodic) -> tuple[np.ndarray, np.ndarray]:
    """Each particle's candidates (support + skin) and pairs within support, itself included."""
    x = np.asarray(position, np.float64)
    h = np.asarray(radius, np.float64)
    h0 = h.max()
    shifted = x.copy()
    box = []
    for a in range(3):   # cKDTree wraps every axis of its box: wall axes get a box too large to wrap
        if periodic[a]:
            box.append(size[a])
        else:
            shifted[:, a] += 10.0 * size[a]
            box.append(30.0 * size[a])
    pairs = cKDTree(shifted, boxsize=box).query_pairs((1.0 + SKIN) * h0, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    d = x[i] - x[j]
    for a in range(3):
        if periodic[a]:
            d[:, a] -= size[a] * np.rint(d[:, a] / size[a])
    r = np.linalg.norm(d, axis=1)
    support = np.maximum(h[i], h[j])
    out = []
    for mask in (r < support + SKIN * h0, r < support):
        c = np.ones(len(x), np.int64)
        np.add.at(c, i[mask], 1)
        np.add.at(c, j[mask], 1)
        out.append(c)
    return out[0], out[1]


def warp_rounds(length: np.ndarray) -> np.ndarray:
    """Rounds of BATCH candidates each warp of 32 consecutive particles runs (its longest row)."""
    m = len(length) // 32 * 32
    return np.ceil(length[:m].reshape(-1, 32).max(1) / BATCH)


def report(length: np.ndarray, level: np.ndarray, label: str) -> None:
    m = len(length) // 32 * 32
    rounds = warp_rounds(length)
    mean = np.ceil(length[:m].reshape(-1, 32) / BATCH).mean(1)
    mixed = level[:m].reshape(-1, 32).max(1) > 0
    print(f"{label}: {len(length)} particles, rows {length.mean():.1f} on average, {length.min()}-{length.max()}")
    print(f"  warps' longest rows / mean rows: {rounds.sum() / mean.sum():.3f}"
          f" (warps with a fine particle {mixed.mean():.1%}: {rounds[mixed].sum() / max(mean[mixed].sum(), 1):.3f};"
          f" the others {rounds[~mixed].sum() / max(mean[~mixed].sum(), 1):.3f})")
    for tile in (64, 128, 256):
        t = len(length) // tile * tile
        ordered = -np.sort(-length[:t].reshape(-1, tile), axis=1).reshape(-1)
        print(f"  tiles of {tile} ordered by row length: {warp_rounds(ordered).sum() / rounds.sum():.3f} of the rounds")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", default="cycling_adaptive")
    ap.add_argument("--steps", type=int, default=601)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--state", help="an .npz with position, level, kernel_radius instead of a run")
    args = ap.parse_args(argv)
    from pbf_cuda import Simulation, load_scene
    scene = load_scene(args.scene)
    if args.state:
        state = dict(np.load(args.state))
    else:
        sim = Simulation(scene, backend=args.backend, seed=0)
        sim.step(args.steps)
        state = sim.state()
    periodic = [b == "periodic" for b in scene.domain.boundary]
    candidates, narrowed = row_lengths(state["position"], state["kernel_radius"], scene.domain.size, periodic)
    report(candidates, np.asarray(state["level"]), "candidates (the density iterations' rows)")
    report(narrowed, np.asarray(state["level"]), "pairs within support (the rows after the XSPH pass)")


if __name__ == "__main__":
    main()
