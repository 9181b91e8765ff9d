"""Off-screen pyvista renders of the clouds (PNG files for the report).

* :func:`render_particles`: particles as Gaussian splats, coloured by cloud w (clear
  air transparent, opacity rising with w, as in the paper's Figure 1), by
  temperature, temperature anomaly, shape energy (eq. 20) or adaptive level;
* :func:`render_volume`: volume render of a gridded cloud field (deposited particles
  or the grid baseline);
* :func:`render_slab_comparison`: the paper's Figure 1, a quasi-2D slab seen from the
  front, without and with temperature smoothing, side by side;
* :func:`render_shape_energy`: the paper's Figure 3, shape energy E = k_p (1 - exp(-k_c w))
  beside the cloud density w it is computed from.

Rendering needs an OpenGL context without a display: VTK 9.5 wheels find one through
EGL (Debian/Ubuntu packages ``libegl1 libegl-mesa0 libgl1-mesa-dri``, Mesa's software
llvmpipe when no GPU) or OSMesa (``libosmesa6``).  :func:`rendering_status` probes,
once per process and in a subprocess (a missing GL library must not crash the
caller), which of them works.  Every render function raises :class:`RenderUnavailable`
with the reason when none does, and also when the image comes out blank; use
:func:`render_or_note` to turn that into a ``NAME.unavailable.txt`` note that the
report shows as "render unavailable: <reason>".

Lengths in m, temperatures in K, w in kg/kg.  y is up.
"""
from __future__ import annotations

import functools
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from cloudpbf_io.files import atomic_path

__all__ = [
    "RenderUnavailable",
    "COLOR_BY",
    "rendering_status",
    "require_rendering",
    "shape_energy",
    "render_particles",
    "render_volume",
    "render_slab_comparison",
    "render_shape_energy",
    "render_or_note",
    "note_path",
]

COLOR_BY = ("cloud", "cloud_density", "temperature", "temperature_anomaly", "shape_energy", "level")
CLOUD_THRESHOLD = 1e-5  # kg/kg, as in cloudpbf.statistics
SKY = "#9cc3e6"          # background: pale sky blue


def compact_particles(state: Mapping, threshold: float = CLOUD_THRESHOLD, clear_fraction: float = 0.1,
                      keys: Sequence[str] = ("position", "cloud", "level")) -> dict:
    """A particle state cut down for renders made elsewhere: every particle with cloud water above `threshold`
    (kg/kg) and `clear_fraction` of the clear ones (a fixed random draw, seed 0), only `keys` (those present)."""
    cloud = np.asarray(state["cloud"])
    keep = (cloud > threshold) | (np.random.default_rng(0).random(len(cloud)) < clear_fraction)
    return {k: np.asarray(state[k])[keep] for k in keys if k in state}


def _cloud_colormap():
    from matplotlib.colors import LinearSegmentedColormap  # harness extra (matplotlib)
    return LinearSegmentedColormap.from_list("cloud", ["#6e7780", "#c9d0d6", "#ffffff"])


_CLOUD_CMAP = _cloud_colormap()  # grey thin cloud, white dense cloud
# the shaded volume's colours (the lighting darkens them): light grey thin cloud, white dense cloud
_LIT_CLOUD_CMAP = __import__("matplotlib.colors", fromlist=["LinearSegmentedColormap"]).LinearSegmentedColormap \
    .from_list("lit_cloud", ["#c4ccd4", "#eef1f4", "#ffffff"])
_WINDOW_CLASSES = ("vtkEGLRenderWindow", "vtkOSOpenGLRenderWindow")
_PROBE = r"""
import sys
import pyvista as pv
pv.OFF_SCREEN = True
p = pv.Plotter(off_screen=True, window_size=(64, 48))
p.add_mesh(pv.Sphere(), color="white")
p.set_background("black")
img = p.screenshot(return_img=True)
name = p.ren_win.GetClassName()
p.close()
if img is None or float(img.std()) == 0.0:
    sys.exit("blank probe image from " + name)
print(name)
"""


class RenderUnavailable(RuntimeError):
    """Rendering cannot run here (no OpenGL context, pyvista missing, blank image)."""


# ------------------------------------------------------------------------------------------
# availability
# ------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def rendering_status() -> tuple[bool, str]:
    """``(True, window class)`` if an off-screen render works here, else ``(False, reason)``.

    Tries VTK's default window first when a DISPLAY exists, then EGL, then OSMesa,
    each in a subprocess; the first that works is kept for this process through
    ``VTK_DEFAULT_OPENGL_WINDOW``.  ``CLOUDPBF_NO_RENDER=1`` disables rendering.
    """
    if os.environ.get("CLOUDPBF_NO_RENDER", "") not in ("", "0"):
        return False, "disabled by CLOUDPBF_NO_RENDER"
    try:
        # viz extra (pyvista)
        import pyvista  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the install
        return False, f"pyvista is not installed ({exc}); pip install 'cloudpbf[viz]'"
    preset = os.environ.get("VTK_DEFAULT_OPENGL_WINDOW")
    candidates: list[str | None] = [preset] if preset else []
    if os.environ.get("DISPLAY") and not preset:
        candidates.append(None)
    candidates += [c for c in _WINDOW_CLASSES if c != preset]
    failures = []
    for window in candidates:
        env = dict(os.environ)
        if window:
            env["VTK_DEFAULT_OPENGL_WINDOW"] = window
        try:
            proc = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                                  text=True, timeout=120)
        except subprocess.TimeoutExpired:
            failures.append(f"{window or 'default window'}: timed out")
            continue
        if proc.returncode == 0:
            got = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else (window or "")
            if got.startswith("vtk") and got.endswith("RenderWindow"):  # VTK may fall back by itself
                os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = got
            elif window:
                os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = window
            return True, got or "default window"
        last = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
        failures.append(f"{window or 'default window'}: {last[:200]}")
    return False, ("no off-screen OpenGL context (install libegl1 libegl-mesa0 libgl1-mesa-dri, "
                   "or libosmesa6); tried " + "; ".join(failures))


def require_rendering() -> None:
    """Raise :class:`RenderUnavailable` with the reason unless rendering works here."""
    ok, why = rendering_status()
    if not ok:
        raise RenderUnavailable(why)


def _pyvista():
    require_rendering()
    import pyvista as pv  # viz extra (pyvista)
    pv.OFF_SCREEN = True
    return pv


# ------------------------------------------------------------------------------------------
# quantities shown
# ------------------------------------------------------------------------------------------
def shape_energy(cloud, k_p: float, k_c: float) -> np.ndarray:
    """Shape energy E = k_p (1 - exp(-k_c w)) of eq. 20 (w in kg/kg, k_c in 1/(kg/kg))."""
    return k_p * -np.expm1(-k_c * np.asarray(cloud, dtype=np.float64))


def _need(state: Mapping, *keys: str):
    missing = [k for k in keys if k not in state]
    if missing:
        raise KeyError(f"particle state lacks {', '.join(missing)} (has: {', '.join(sorted(state))})")


def _scalars(state: Mapping, scene, color_by: str) -> tuple[np.ndarray, str, str, tuple]:
    """(values, label, colormap, clim) of a colouring."""
    if color_by == "cloud":
        _need(state, "cloud")
        w = np.asarray(state["cloud"], dtype=np.float64)
        top = float(np.max(w)) if w.size else 0.0
        return w, "cloud w (kg/kg)", _CLOUD_CMAP, (0.0, max(top, 1e-12))
    if color_by == "cloud_density":
        _need(state, "cloud")
        w = np.asarray(state["cloud"], dtype=np.float64)
        return w, "w (kg/kg)", "viridis", (0.0, max(float(np.max(w)) if w.size else 0.0, 1e-12))
    if color_by == "temperature":
        _need(state, "temperature")
        t = np.asarray(state["temperature"], dtype=np.float64)
        return t, "temperature T (K)", "coolwarm", (float(t.min()), float(t.max()) + 1e-9)
    if color_by == "temperature_anomaly":
        _need(state, "temperature", "position")
        t = np.asarray(state["temperature"]) - scene.environment_temperature(np.asarray(state["position"])[:, 1])
        bound = max(float(np.max(np.abs(t))), 1e-6)
        return t, "T - T0(y) (K)", "coolwarm", (-bound, bound)
    if color_by == "shape_energy":
        _need(state, "cloud")
        a = scene.adaptive
        e = shape_energy(state["cloud"], a.k_p, a.k_c)
        return e, "E (eq. 20)", "viridis", (0.0, float(a.k_p))
    if color_by == "level":
        _need(state, "level")
        lv = np.asarray(state["level"], dtype=np.float64)
        return lv, "level l", "plasma", (0.0, max(float(lv.max()), 1.0))
    raise ValueError(f"color_by = {color_by!r}: allowed values are {', '.join(COLOR_BY)}")


# ------------------------------------------------------------------------------------------
# plotting helpers
# ------------------------------------------------------------------------------------------
def _finish(plotter, out_png) -> Path:
    """Screenshot to `out_png`; raise RenderUnavailable if the picture is uniform."""
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    try:
        img = plotter.screenshot(str(out_png), return_img=True)
    finally:
        plotter.close()
    if img is None or float(np.asarray(img, dtype=np.float64).std()) == 0.0:
        out_png.unlink(missing_ok=True)
        raise RenderUnavailable(f"{out_png.name}: the rendered image is blank")
    return out_png


def _camera(plotter, size, view: str, aspect: float = 4.0 / 3.0, lo=(0.0, 0.0, 0.0)) -> None:
    """Point the camera at the box [lo, lo + size] (m).

    'iso': from the front, above and to the side, perspective; 'front': along -z with
    a parallel projection fitting x and y (the view of a quasi-2D slab).  ``aspect``
    is the viewport's width / height.
    """
    size = np.asarray(size, dtype=np.float64)
    centre = np.asarray(lo, dtype=np.float64) + size / 2.0
    if view == "front":
        plotter.camera_position = [tuple(centre + np.array([0.0, 0.0, 3.0 * size.max()])), tuple(centre), (0, 1, 0)]
        plotter.enable_parallel_projection()
        plotter.reset_camera()
        scale = 0.56 * max(size[1], 1.15 * size[0] / aspect)
        shift = np.array([0.06 * 2.0 * scale * aspect, 0.0, 0.0])  # room on the right for the colour bar
        plotter.camera.focal_point = tuple(centre + shift)
        plotter.camera.position = tuple(centre + shift + np.array([0.0, 0.0, 3.0 * size.max()]))
        plotter.camera.parallel_scale = scale
    elif view == "iso":
        eye = centre + np.array([0.9, 0.45, 1.7]) * size.max()
        plotter.camera_position = [tuple(eye), tuple(centre - np.array([0.0, 0.1 * size[1], 0.0])), (0, 1, 0)]
        plotter.reset_camera()
        plotter.camera.zoom(1.15)
    else:
        raise ValueError(f"view = {view!r}: allowed values are iso, front")


def _ground_and_box(pv, plotter, scene) -> None:
    size = np.asarray(scene.domain.size, dtype=np.float64)
    plotter.add_mesh(pv.Box(bounds=(0, size[0], 0, size[1], 0, size[2])).outline(), color="#4a5a6a", line_width=1)
    ground = pv.Plane(center=(size[0] / 2, 0.0, size[2] / 2), direction=(0, 1, 0), i_size=size[0], j_size=size[2])
    plotter.add_mesh(ground, color="#6f7f5f", opacity=1.0)


def _point_size(scene, window_size, view) -> float:
    """Splat size in pixels: about one initial particle spacing on screen."""
    size = np.asarray(scene.domain.size, dtype=np.float64)
    extent = max(size[0], size[1]) if view == "front" else float(np.linalg.norm(size))
    return float(np.clip(1.8 * scene.particles.spacing / extent * min(window_size), 2.0, 40.0))


def _add_particles(pv, plotter, state, scene, color_by, view, window_size, threshold, point_size,
                   scalar_bar=True, clim=None, fade=False) -> int:
    """Add the particle splats of one colouring; returns the number of points drawn.

    'cloud' draws only particles with w > threshold, opacity rising with w (clear air
    transparent, the paper's Figure 1); ``fade`` makes any other colouring's opacity
    rise from 0.12 to 1 over its colour range (so a slab seen from the front shows its
    depth).  ``clim`` overrides the colour range (shared between panels).
    """
    _need(state, "position")
    pos = np.asarray(state["position"], dtype=np.float64)
    values, label, cmap, auto_clim = _scalars(state, scene, color_by)
    lo, hi = clim if clim is not None else auto_clim
    keep = np.ones(len(pos), dtype=bool)
    opacity = None
    if color_by == "cloud":
        keep = values > threshold                   # clear air is fully transparent
        opacity = np.clip(values[keep] / max(hi, 1e-12), 0.08, 1.0) * 0.9
    elif color_by == "temperature_anomaly" and fade:
        bound = max(abs(lo), abs(hi), 1e-12)         # warm and cold parcels opaque, neutral air clear
        keep = np.abs(values) > 0.05 * bound
        opacity = np.clip(np.abs(values[keep]) / bound, 0.05, 1.0)
    elif fade:
        opacity = 0.12 + 0.88 * np.clip((values - lo) / max(hi - lo, 1e-300), 0.0, 1.0)
    if not keep.any():
        return 0
    cloud = pv.PolyData(pos[keep])
    cloud["value"] = values[keep]
    kwargs = dict(scalars="value", cmap=cmap, clim=(lo, hi), style="points",
                  point_size=point_size or _point_size(scene, window_size, view),
                  render_points_as_spheres=True, show_scalar_bar=scalar_bar,
                  scalar_bar_args=dict(title=label, color="black", vertical=True, fmt="%.3g",
                                       position_x=0.89, position_y=0.12, height=0.72, width=0.035))
    if opacity is not None:
        cloud["opacity"] = opacity
        kwargs["opacity"] = "opacity"
    plotter.add_mesh(cloud, **kwargs)
    return int(keep.sum())


# ------------------------------------------------------------------------------------------
# public renders
# ------------------------------------------------------------------------------------------
def render_particles(state: Mapping, scene, out_png, color_by: str = "cloud", view: str = "iso",
                     window_size: Sequence[int] = (1200, 900), threshold: float = CLOUD_THRESHOLD,
                     point_size: float | None = None, title: str | None = None, clim=None) -> Path:
    """Render particles of a ``Simulation.state()`` dict to a PNG.

    ``color_by``: 'cloud' (only particles with w > threshold, opacity rising with w),
    'cloud_density' (every particle coloured by w), 'temperature', 'temperature_anomaly'
    (T - T0(y)), 'shape_energy' (eq. 20, the scene's k_p and k_c) or 'level'.
    ``view``: 'iso' (perspective; low values of the last four fade out so the inside
    shows) or 'front' (parallel projection along -z, for slabs).  ``clim``: the colour range (lo, hi)
    (default: the state's own), shared by the frames of an animation.
    """
    if color_by not in COLOR_BY:
        raise ValueError(f"color_by = {color_by!r}: allowed values are {', '.join(COLOR_BY)}")
    pv = _pyvista()
    plotter = pv.Plotter(off_screen=True, window_size=tuple(window_size))
    plotter.set_background(SKY, top="#3d6fa8")
    _ground_and_box(pv, plotter, scene)
    # in a 3D view an opaque block of particles shows only its surface: let low values fade
    fade = view == "iso" and color_by in ("temperature_anomaly", "shape_energy", "cloud_density", "level")
    drawn = _add_particles(pv, plotter, state, scene, color_by, view, window_size, threshold, point_size,
                           clim=clim, fade=fade)
    n = len(state["position"])
    text = title or f"{scene.name}: {n:,} particles, coloured by {color_by}"
    if color_by == "cloud":
        text += f" ({drawn:,} cloudy, w > {threshold:g})" if drawn else f" (no cloud: w <= {threshold:g} everywhere)"
    plotter.add_text(text, position="upper_left", font_size=10, color="black")
    _camera(plotter, scene.domain.size, view, window_size[0] / window_size[1])
    return _finish(plotter, out_png)


def render_volume(grid_w, cell_size, out_png, origin=(0.0, 0.0, 0.0), threshold: float = CLOUD_THRESHOLD,
                  window_size: Sequence[int] = (1200, 900), title: str | None = None, upsample: int = 2) -> Path:
    """Volume render of a cloud field w (kg/kg) on an (nx, ny, nz) grid of cell centres.

    ``cell_size`` (3,) m, ``origin`` (3,) m the grid corner.  Cells with
    w <= threshold are transparent; opacity and whiteness rise with w.  The field is
    interpolated (trilinear, ``upsample`` points per cell and axis, so no value leaves
    the cells' range) and lit by a sun from above (shaded ray casting): cloud tops
    bright, bases and the shadowed sides grey, as in the paper's Fig. 5.
    """
    w = np.asarray(grid_w, dtype=np.float64)
    if w.ndim != 3:
        raise ValueError(f"grid_w: expected an (nx, ny, nz) grid, got shape {w.shape}")
    dx = np.broadcast_to(np.asarray(cell_size, dtype=np.float64), (3,))
    org = np.broadcast_to(np.asarray(origin, dtype=np.float64), (3,))
    if np.any(dx <= 0):
        raise ValueError(f"cell_size = {cell_size!r}: every entry must be > 0 m")
    pv = _pyvista()
    size = dx * np.array(w.shape)
    shape = w.shape
    if upsample > 1 and w.max() > threshold:
        from scipy.ndimage import zoom  # harness extra (scipy)
        w = np.clip(zoom(w, upsample, order=1, grid_mode=True, mode="nearest"), 0.0, None)
        dx = dx * np.array(shape) / np.array(w.shape)
    grid = pv.ImageData(dimensions=w.shape, spacing=tuple(dx), origin=tuple(org + dx / 2))
    grid.point_data["cloud"] = w.ravel(order="F")
    top = float(w.max())
    plotter = pv.Plotter(off_screen=True, window_size=tuple(window_size))
    plotter.set_background(SKY, top="#3d6fa8")
    plotter.add_mesh(pv.Box(bounds=(org[0], org[0] + size[0], org[1], org[1] + size[1], org[2], org[2] + size[2]))
                     .outline(), color="#4a5a6a", line_width=1)
    plotter.add_mesh(pv.Plane(center=(org[0] + size[0] / 2, org[1], org[2] + size[2] / 2), direction=(0, 1, 0),
                              i_size=size[0], j_size=size[2]), color="#6f7f5f")
    if top > threshold:
        # opacity transfer over [0, top]; 64 samples (pyvista 0.46 drops a table of exactly n_colors)
        ramp = np.linspace(0.0, top, 64)
        opacity = np.where(ramp > threshold, 0.15 + 0.85 * np.sqrt(ramp / top), 0.0)
        volume = plotter.add_volume(grid, scalars="cloud", clim=(0.0, top), opacity=opacity,
                                    cmap=_LIT_CLOUD_CMAP, opacity_unit_distance=float(dx.max()),
                                    show_scalar_bar=True, shade=True, ambient=0.8, diffuse=0.55, specular=0.0,
                                    scalar_bar_args=dict(title="cloud w (kg/kg)", color="black", vertical=True,
                                                         position_x=0.88, position_y=0.15, height=0.7,
                                                         width=0.05))
        volume.mapper.SetSampleDistance(float(dx.min()) / 2)
        centre = org + size / 2       # a sun high above, on the camera's side, beside the default light kit
        plotter.add_light(pv.Light(position=tuple(centre + np.array([1.0, 4.0, 1.5]) * size.max()),
                                   focal_point=tuple(centre), intensity=0.6, light_type="scene light"))
        cloudy = int((np.asarray(grid_w) > threshold).sum())
        note = f"{cloudy:,} of {int(np.prod(shape)):,} cells cloudy"
    else:
        note = f"no cloud: w <= {threshold:g} everywhere"
    plotter.add_text(title or f"deposited cloud field {shape[0]}x{shape[1]}x{shape[2]}: {note}",
                     position="upper_left", font_size=10, color="black")
    _camera(plotter, size, "iso", window_size[0] / window_size[1], lo=org)
    return _finish(plotter, out_png)


def render_slab_comparison(state_unsmoothed: Mapping, state_smoothed: Mapping, scene, out_png,
                           color_by: str = "cloud", labels: Sequence[str] | None = None,
                           window_size: Sequence[int] = (1600, 800), threshold: float = CLOUD_THRESHOLD,
                           point_size: float | None = None) -> Path:
    """The paper's Figure 1: a quasi-2D slab seen from the front, without and with smoothing.

    Both states come from the same scene (e.g. ``smoothing_slab``) run with
    ``smoothing.kappa = 0`` and with the scene's kappa; ``scene`` supplies the domain.
    Both panels share one colour range.
    """
    if labels is None:
        labels = ("(a) without smoothing (kappa = 0)", f"(b) with smoothing (kappa = {scene.smoothing.kappa:g})")
    ranges = [_scalars(st, scene, color_by)[3] for st in (state_unsmoothed, state_smoothed)]
    clim = (min(r[0] for r in ranges), max(r[1] for r in ranges))
    panels = [(state_unsmoothed, color_by, labels[0], clim, False),
              (state_smoothed, color_by, labels[1], clim, True)]
    return _side_by_side(panels, scene, out_png, window_size, threshold, point_size, fade=color_by != "cloud")


def render_shape_energy(state: Mapping, scene, out_png, window_size: Sequence[int] = (1600, 800),
                        point_size: float | None = None) -> Path:
    """The paper's Figure 3: shape energy E = k_p (1 - exp(-k_c w)) (eq. 20) beside w itself.

    Front view of every particle, opacity rising with the value shown; high E marks
    split candidates (E > alpha), low E merge candidates (E < beta).
    """
    a = scene.adaptive
    _need(state, "cloud")
    w_max = float(np.max(state["cloud"])) if len(state["cloud"]) else 0.0
    clear = "" if w_max > CLOUD_THRESHOLD else f" (no cloud in this state: max w = {w_max:.2g})"
    panels = [(state, "shape_energy", f"(a) shape energy E, k_p = {a.k_p:g}, k_c = {a.k_c:g} "
                                      f"(split E > {a.split_threshold:g}, merge E < {a.merge_threshold:g}){clear}",
               None, True),
              (state, "cloud_density", f"(b) cloud density w used directly{clear}", None, True)]
    return _side_by_side(panels, scene, out_png, window_size, CLOUD_THRESHOLD, point_size, fade=True)


def _side_by_side(panels, scene, out_png, window_size, threshold, point_size, fade) -> Path:
    """Front views of several (state, colouring, label, clim, scalar bar) panels in one row."""
    pv = _pyvista()
    plotter = pv.Plotter(off_screen=True, shape=(1, len(panels)), window_size=tuple(window_size), border=False)
    panel_size = (window_size[0] // len(panels), window_size[1])
    size = scene.domain.size
    for i, (state, color_by, label, clim, bar) in enumerate(panels):
        plotter.subplot(0, i)
        plotter.set_background(SKY, top="#3d6fa8")
        _add_particles(pv, plotter, state, scene, color_by, "front", panel_size, threshold, point_size,
                       scalar_bar=bar, clim=clim, fade=fade)
        plotter.add_mesh(pv.Box(bounds=(0, size[0], 0, size[1], 0, size[2])).outline(), color="#4a5a6a")
        plotter.add_text(label, position="upper_left", font_size=9, color="black")
        _camera(plotter, size, "front", panel_size[0] / panel_size[1])
    return _finish(plotter, out_png)


def render_animation(frames: Sequence[tuple[float, Mapping]], scene, out_gif, out_strip=None,
                     window_size: Sequence[int] = (800, 600), strip_width: int = 360,
                     frame_ms: int = 700, threshold: float = CLOUD_THRESHOLD) -> Path:
    """The clouds developing: one particle render per (time s, state) frame, written as a looping GIF
    (`frame_ms` per frame, the last held three times as long) and, with `out_strip`, as one PNG strip
    of the frames side by side, each `strip_width` px wide, labelled with its time."""
    from PIL import Image  # harness extra (PIL)
    if not frames:
        raise RenderUnavailable("no stored states to animate")
    out_gif = Path(out_gif)
    images = []
    top = max(float(np.max(state["cloud"])) if len(state["cloud"]) else 0.0 for _, state in frames)
    clim = (0.0, max(top, 1e-12))              # one colour scale for every frame: the growth shows
    with tempfile.TemporaryDirectory() as tmp:
        for i, (time_s, state) in enumerate(frames):
            png = Path(tmp) / f"frame_{i:03d}.png"
            render_particles(state, scene, png, color_by="cloud", window_size=window_size, threshold=threshold,
                             title=f"{scene.name}, t = {time_s:g} s", clim=clim)
            with Image.open(png) as im:
                images.append(im.convert("RGB"))
    out_gif.parent.mkdir(parents=True, exist_ok=True)
    palette = [im.quantize(colors=128, method=Image.Quantize.MEDIANCUT) for im in images]
    durations = [frame_ms] * (len(palette) - 1) + [3 * frame_ms]
    with atomic_path(out_gif) as tmp_gif:
        palette[0].save(tmp_gif, format="GIF", save_all=True, append_images=palette[1:], duration=durations,
                        loop=0)
    if out_strip is not None:
        height = int(round(strip_width * images[0].height / images[0].width))
        strip = Image.new("RGB", (strip_width * len(images), height), "white")
        for i, im in enumerate(images):
            strip.paste(im.resize((strip_width, height), Image.Resampling.LANCZOS), (i * strip_width, 0))
        with atomic_path(Path(out_strip)) as tmp_png:
            strip.save(tmp_png, format="PNG")
    return out_gif


# ------------------------------------------------------------------------------------------
# report glue
# ------------------------------------------------------------------------------------------
def note_path(out_png) -> Path:
    """Where the "render unavailable" reason for `out_png` is written: NAME.unavailable.txt."""
    out_png = Path(out_png)
    return out_png.with_name(out_png.stem + ".unavailable.txt")


def render_or_note(render: Callable[..., Path], out_png, *args, **kwargs) -> Path | None:
    """Call ``render(..., out_png, ...)``; on failure write the reason next to the PNG.

    ``render_or_note(render_particles, out_png, state, scene)`` calls
    ``render_particles(state, scene, out_png)`` (the PNG path goes in the position
    each render function expects, or as ``out_png=`` for any other callable).
    Returns the PNG path, or None after writing ``NAME.unavailable.txt``, which the
    report shows as "render unavailable: <reason>".  A stale note is removed on success.
    """
    out_png = Path(out_png)
    note = note_path(out_png)
    try:
        if render in _PNG_POSITION:
            pos = _PNG_POSITION[render]
            call_args = list(args[:pos]) + [out_png] + list(args[pos:])
            path = render(*call_args, **kwargs)
        else:
            path = render(*args, out_png=out_png, **kwargs)
    except (RenderUnavailable, RuntimeError, OSError, ImportError) as exc:
        note.parent.mkdir(parents=True, exist_ok=True)
        note.write_text(f"{type(exc).__name__}: {exc}\n")
        out_png.unlink(missing_ok=True)
        return None
    note.unlink(missing_ok=True)
    return Path(path)


_PNG_POSITION = {render_particles: 2, render_volume: 2, render_slab_comparison: 3, render_shape_energy: 2,
                 render_animation: 2}
