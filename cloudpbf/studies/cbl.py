"""Dry convective boundary layer: mixed-layer growth of both solvers against encroachment theory.

The `dry_cbl` scene heats the air below `heating_depth` at a constant rate S_e (eq. 5, a weak
simplex pattern only seeds the convection) under a stable layer whose potential temperature
theta = T + Gamma_d y rises with gamma = Gamma_d - lapse_rate (K/m).  No moisture, no clouds.

Kinematic surface heat flux (K m/s): the heated layer takes S_e * pattern(x, z) per unit time in
every mass element below heating_depth, so the column's heat input per unit area is

    H = S_e * D * mean_xz(pattern),   D = the depth of the discrete heated layer

where D = heating_depth: both solvers heat each particle layer (grid cell) by the part of it below
heating_depth, so the discrete heated column is exactly that deep at any spacing; the particle lattice
and the grid's cell centres sample the pattern at the same (x, z).

Encroachment (no entrainment): the heat H t fills a well-mixed layer of potential temperature
theta_m up to the height h where the initial profile reaches theta_m, so
int_0^h (theta_m - theta_init(z)) dz = gamma h^2 / 2 = H t, i.e. h^2 = 2 H t / gamma.

Measured h (`mixed_layer_depth`), from the horizontally (mass-) averaged profile theta_bar(z) in
bins of one spacing: theta_m is the mean of theta_bar over the mixed-layer core, the bins between
the top of the heated layer and half the height z0 where theta_bar first meets the initial profile
(the anomaly theta_bar - theta_init first falls to 0, interpolated linearly between bin centres);
then h = (theta_m - theta_ground) / gamma, the height where the initial profile meets the mixed
layer's potential temperature.  z0, the top of the warmed layer, includes the entrainment zone
(penetrating thermals) and sits about 10-20% above h; it is reported beside h.

    cloudpbf cbl --out reports/gpu/data/cbl_profiles.csv

writes both solvers' mean potential-temperature profiles side by side (one row per time and height)
and prints h, z0 and the encroachment depth (``python -m cloudpbf.studies.cbl ARGS`` is the same command).
Not part of the demo.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer

from cloudpbf import runs
from cloudpbf.cli_common import Backend, BackendOpt, QuietOpt, check_backend, parse_list, run_command, scene_arg
from cloudpbf.environment import commit as git_commit
from cloudpbf.studies.registry import Study, register
from pbf_cuda import Simulation
from pbf_cuda.initial_state import lattice_spacings
from pbf_cuda.scene import Scene, load_scene

PROFILE_COLUMNS = ("time_s", "z", "theta_particles", "theta_grid", "theta_initial", "h_theory", "h_particles",
                   "h_grid", "z0_particles", "z0_grid", "device", "commit")


def potential_temperature_lapse(scene: Scene) -> float:
    """gamma = Gamma_d - lapse_rate (K/m): d theta_init / dy of the environment."""
    a = scene.atmosphere
    return a.dry_lapse_rate - a.lapse_rate


def heated_depth(scene: Scene) -> float:
    """D (m): heating_depth. Both solvers heat each particle layer (grid cell) by the part of it below
    heating_depth, so the heated column is heating_depth deep at any spacing."""
    return float(scene.atmosphere.heating_depth)


def mean_heating_pattern(scene: Scene) -> float:
    """mean over the lattice columns (x, z) of max(0, 1 + amplitude * noise) (eq. 5)."""
    from grid_baseline.noise import heating_pattern  # grid extra (jax)
    a = scene.atmosphere
    ds = lattice_spacings(scene)
    xs = (np.arange(int(round(scene.domain.size[0] / ds[0]))) + 0.5) * ds[0]
    zs = (np.arange(int(round(scene.domain.size[2] / ds[2]))) + 0.5) * ds[2]
    X, Z = np.meshgrid(xs, zs, indexing="ij")
    return float(np.mean(np.asarray(heating_pattern(X, Z, a.noise_frequency, a.noise_amplitude,
                                                    tuple(a.noise_offset)), dtype=np.float64)))


def kinematic_heat_flux(scene: Scene) -> float:
    """H = S_e * D * mean pattern (K m/s), the ground heating as a surface flux (module docstring)."""
    return scene.atmosphere.heating_rate * heated_depth(scene) * mean_heating_pattern(scene)


def encroachment_depth(scene: Scene, t: float) -> float:
    """h = sqrt(2 H t / gamma) (m) at time t (s)."""
    return math.sqrt(2.0 * kinematic_heat_flux(scene) * t / potential_temperature_lapse(scene))


def bin_edges(scene: Scene) -> np.ndarray:
    """Height bins of one lattice spacing (the grid's cells), m."""
    d = float(lattice_spacings(scene)[1])
    return np.arange(int(round(scene.domain.size[1] / d)) + 1) * d


def particle_theta_profile(state: dict, scene: Scene, edges: np.ndarray) -> np.ndarray:
    """Mass-weighted mean theta = T + Gamma_d y (K) of the particles in each height bin."""
    y = state["position"][:, 1].astype(np.float64)
    theta = state["temperature"].astype(np.float64) + scene.atmosphere.dry_lapse_rate * y
    m = state["mass"].astype(np.float64)
    nb = len(edges) - 1
    idx = np.clip(np.searchsorted(edges, y, side="right") - 1, 0, nb - 1)
    mass = np.bincount(idx, m, nb)
    return np.bincount(idx, m * theta, nb) / np.where(mass > 0, mass, np.nan)


def grid_theta_profile(fields: dict) -> np.ndarray:
    """Horizontal mean of the grid's potential temperature (K) per cell layer."""
    return np.asarray(fields["potential_temperature"], dtype=np.float64).mean(axis=(0, 2))


def mixed_layer_depth(z: np.ndarray, theta: np.ndarray, scene: Scene) -> tuple[float, float]:
    """(h, z0) in m from a mean profile theta(z) at bin centres z (module docstring).

    z0: first height where theta - theta_init falls to 0 (linear between bins); h = (theta_m - T_ground) / gamma
    with theta_m the mean theta over the bins in [heated depth, z0 / 2] (at least the first bin above it)."""
    a = scene.atmosphere
    gamma = potential_temperature_lapse(scene)
    anomaly = theta - (a.ground_temperature + gamma * z)
    z0 = float(z[-1])
    for k in range(1, len(z)):
        if anomaly[k] <= 0.0 < anomaly[k - 1]:
            z0 = float(z[k - 1] + (z[k] - z[k - 1]) * anomaly[k - 1] / (anomaly[k - 1] - anomaly[k]))
            break
    D = heated_depth(scene)
    core = (z > D) & (z <= max(0.5 * z0, float(z[z > D][0]) if np.any(z > D) else 0.0))
    theta_m = float(np.mean(theta[core]))
    return (theta_m - a.ground_temperature) / gamma, z0


def run_profiles(scene: Scene | str = "dry_cbl", times=(200.0, 400.0, 600.0), seed: int = 0, backend: str = "cpu",
                 quiet: bool = False) -> "pandas.DataFrame":  # noqa: F821
    """Run both solvers to each time (s); one row per (time, height bin) with both mean profiles."""
    import pandas as pd  # harness extra (pandas)

    from grid_baseline import GridSimulation  # grid extra (jax)

    scene = load_scene(scene) if isinstance(scene, str) else scene
    edges = bin_edges(scene)
    z = 0.5 * (edges[1:] + edges[:-1])
    gamma = potential_temperature_lapse(scene)
    theta_init = scene.atmosphere.ground_temperature + gamma * z
    part = Simulation(scene, backend=backend, seed=seed)
    grid = GridSimulation(scene, seed=seed)
    if grid.shape[1] != len(z):
        raise ValueError(f"{scene.name}: grid has {grid.shape[1]} layers, expected {len(z)}")
    dt = scene.time.dt
    device = f"particles {part.backend}, grid {grid.stats()['device']}"
    commit = git_commit()
    frames = []
    for t in times:
        n = int(round(t / dt))
        part.step(n - part.step_count)
        grid.step(n - grid.step_count)
        tp = particle_theta_profile(part.state(), scene, edges)
        tg = grid_theta_profile(grid.fields())
        hp, z0p = mixed_layer_depth(z, tp, scene)
        hg, z0g = mixed_layer_depth(z, tg, scene)
        ht = encroachment_depth(scene, n * dt)
        if not quiet:
            print(f"t = {n * dt:.0f} s: h theory {ht:.0f} m, particles h {hp:.0f} m (z0 {z0p:.0f}), "
                  f"grid h {hg:.0f} m (z0 {z0g:.0f})", file=sys.stderr)
        frames.append(pd.DataFrame({"time_s": n * dt, "z": z, "theta_particles": tp, "theta_grid": tg,
                                    "theta_initial": theta_init, "h_theory": ht, "h_particles": hp, "h_grid": hg,
                                    "z0_particles": z0p, "z0_grid": z0g, "device": device, "commit": commit}))
    return pd.concat(frames, ignore_index=True)[list(PROFILE_COLUMNS)]


def plot_profiles(frame, path: str | Path) -> Path:
    """One panel per time: both solvers' mean theta(z), the initial profile, and h (theory, each solver)."""
    import matplotlib  # harness extra (matplotlib)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # harness extra (matplotlib)

    times = sorted(frame["time_s"].unique())
    fig, axes = plt.subplots(1, len(times), figsize=(3.2 * len(times), 4.2), sharey=True, squeeze=False)
    for ax, t in zip(axes[0], times):
        f = frame[frame["time_s"] == t]
        ax.plot(f["theta_initial"], f["z"], color="0.6", lw=1, label="initial")
        ax.plot(f["theta_particles"], f["z"], color="C0", marker=".", label="particles")
        ax.plot(f["theta_grid"], f["z"], color="C1", marker=".", label="grid")
        row = f.iloc[0]
        ax.axhline(row["h_theory"], color="k", ls="--", lw=1, label="h encroachment")
        ax.axhline(row["h_particles"], color="C0", ls=":", lw=1)
        ax.axhline(row["h_grid"], color="C1", ls=":", lw=1)
        lo = f["theta_initial"].min() - 0.2
        ax.set_xlim(lo, max(f["theta_particles"].max(), f["theta_grid"].max()) + 0.5)
        ax.set_ylim(0, 2.0 * row["h_theory"])
        ax.set_title(f"t = {t:.0f} s")
        ax.set_xlabel("mean theta (K)")
    axes[0][0].set_ylabel("height (m)")
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    from cloudpbf.report.plots import save_png  # harness extra (matplotlib, pandas)
    return save_png(fig, path)


def cbl_command(
    scene: Annotated[str, typer.Option(help="scene name")] = "dry_cbl",
    times: Annotated[str, typer.Option(help="simulated times, s, comma-separated")] = "200,400,600",
    seed: Annotated[int, typer.Option(min=0, help="random seed")] = 0,
    backend: BackendOpt = Backend.cpu,
    out: Annotated[Path, typer.Option("--out", help="CSV to write (or to read with --from-csv)")] = Path(
        "reports/latest/data/cbl_profiles.csv"),
    plot: Annotated[Optional[Path], typer.Option(help="also draw the profiles as a PNG here")] = None,
    from_csv: Annotated[bool, typer.Option("--from-csv", help="draw the existing --out CSV without running")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Dry convective boundary layer: both solvers' mixed-layer depth against encroachment (cbl_profiles.csv)."""
    if from_csv:
        import pandas as pd  # harness extra (pandas)
        if not out.is_file():
            raise typer.BadParameter(f"'{out}': no such CSV to draw", param_hint="'--out'")
        frame = pd.read_csv(out)
    else:
        scene_arg(scene, param="--scene")
        check_backend(backend)
        at = parse_list(times, "--times", float, 0.0, 1e7, example="200,400,600")
        frame = run_profiles(scene, at, seed, backend.value, quiet)
        runs.write_csv(frame, out)
        typer.echo(f"wrote {out}")
    if plot is not None:
        typer.echo(f"wrote {plot_profiles(frame, plot)}")


register(Study("cbl", order=92, outputs=("cbl_profiles.csv",), command=cbl_command))


def main(argv=None) -> int:
    """``python -m cloudpbf.studies.cbl ARGS`` is ``cloudpbf cbl ARGS``."""
    return run_command(cbl_command, "cbl", sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
