"""Scene validation: each value checked against its declaration (pbf_cuda/scene.py's ``_spec``: type,
range, choices, length), the checks between fields, and the error both raise.

Every failure is a :class:`SceneError` whose message names the field, the value (shortened: a message
never echoes a huge value whole) and what is allowed.
"""
from __future__ import annotations

import math
from dataclasses import fields
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["SceneError", "short", "short_text", "build_section", "cross_checks"]


class SceneError(ValueError):
    """A scene file or parameter set is invalid. The message names the field."""


SHORT_VALUE_CHARS = 60           # values are shortened to this in error messages


def short_text(text: str, limit: int = SHORT_VALUE_CHARS) -> str:
    """`text` cut to about `limit` characters, without quotes (for names and paths in messages)."""
    text = str(text)
    if len(text) <= limit:
        return text
    return f"{text[:limit - 20]}...{text[-8:]} ({len(text)} chars)"


def short(value: Any, limit: int = SHORT_VALUE_CHARS) -> str:
    """repr(value) cut to `limit` characters (error messages never echo a huge value whole)."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001  (a value whose repr fails still gets a message)
        text = f"<{type(value).__name__}>"
    if len(text) <= limit:
        return text
    return f"{text[:limit - 20]}...{text[-8:]} ({len(text)} chars)"


def _check_value(where: str, value: Any, meta: dict, default: Any):
    lo, hi, choices, length = meta["lo"], meta["hi"], meta["choices"], meta["length"]
    unit = f" {meta['unit']}" if meta["unit"] else ""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise SceneError(f"{where} = {short(value)}: expected true or false")
        return value
    if isinstance(default, str) or (choices and not isinstance(default, list)):
        if not isinstance(value, str) or (choices and value not in choices):
            raise SceneError(f"{where} = {short(value)}: allowed values are {', '.join(choices or ['any text'])}")
        return value
    if isinstance(default, list) or length is not None:
        if not isinstance(value, list) or (length is not None and len(value) != length):
            n = f"{length} " if length else ""
            raise SceneError(f"{where} = {short(value)}: expected a list of {n}values")
        if choices:
            for item in value:
                if item not in choices:
                    raise SceneError(f"{where} = {short(value)}: each entry must be one of {', '.join(choices)}")
            return list(value)
        return [_check_number(f"{where}[{i}]", v, lo, hi, unit, float) for i, v in enumerate(value)]
    kind = int if isinstance(default, int) else float
    return _check_number(where, value, lo, hi, unit, kind)


def _check_number(where, value, lo, hi, unit, kind):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(f"{where} = {short(value)}: expected a number in [{lo}, {hi}]{unit}")
    if isinstance(value, int) and abs(value) > 2**63:   # beyond float range or any field's
        raise SceneError(f"{where} = {short(value)} is out of range: allowed [{lo}, {hi}]{unit}")
    if kind is int and isinstance(value, float) and not value.is_integer():
        raise SceneError(f"{where} = {short(value)}: expected an integer in [{lo}, {hi}]")
    if kind is int and not math.isfinite(value):
        raise SceneError(f"{where} = {short(value)} is out of range: allowed [{lo}, {hi}]{unit}")
    value = kind(value)
    if not math.isfinite(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
        raise SceneError(f"{where} = {short(value)} is out of range: allowed [{lo}, {hi}]{unit}")
    return value


def build_section(name: str, cls, data: dict, source: str):
    """The section `name` of class `cls` from its table `data`: every field checked, unknown fields refused."""
    if not isinstance(data, dict):
        raise SceneError(f"{source}: [{name}] must be a table")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise SceneError(f"{source}: unknown field {name}.{short_text(unknown[0])}; known fields: {', '.join(known)}")
    obj = cls()
    for key, value in data.items():
        f = known[key]
        default = getattr(obj, key)
        if value is None:
            continue
        if default is None:  # optional list fields (fill_min/fill_max)
            default = [0.0, 0.0, 0.0]
        setattr(obj, key, _check_value(f"{source}: {name}.{key}", value, f.metadata, default))
    return obj


def cross_checks(scene: Scene, source: str):
    """Checks between fields: the domain against the kernel radius, the fill box, the adaptive thresholds,
    the environment profile within the saturation formula's range, the step control, the wave's walls."""
    d = scene.particles.spacing
    h = scene.kernel_radius
    size = scene.domain.size
    for axis, name in enumerate("xyz"):
        if scene.domain.boundary[axis] == "periodic" and size[axis] < 3.0 * h:
            raise SceneError(
                f"{source}: domain.size[{axis}] = {size[axis]} m with a periodic {name} axis must be >= 3 kernel radii "
                f"({3.0 * h:g} m = 3 * kernel_ratio * spacing)")
        if size[axis] < d:
            raise SceneError(f"{source}: domain.size[{axis}] = {size[axis]} m is smaller than particles.spacing = {d} m")
    lo, hi = scene.fill_box()
    for axis in range(3):
        if not (0.0 <= lo[axis] < hi[axis] <= size[axis] + 1e-9):
            raise SceneError(
                f"{source}: particles.fill_min/fill_max along axis {axis} = [{lo[axis]}, {hi[axis]}] must satisfy "
                f"0 <= fill_min < fill_max <= domain.size ({size[axis]} m)")
    if scene.estimated_particles() < 1:
        raise SceneError(f"{source}: the filled region holds no particle at spacing {d} m")
    if scene.adaptive.enabled:
        if scene.adaptive.merge_threshold >= scene.adaptive.split_threshold:
            raise SceneError(
                f"{source}: adaptive.merge_threshold = {scene.adaptive.merge_threshold} must be below "
                f"adaptive.split_threshold = {scene.adaptive.split_threshold}")
        if scene.atmosphere is None:
            raise SceneError(f"{source}: adaptive.enabled needs an [atmosphere] section (the shape energy uses cloud w)")
        criterion = scene.adaptive.criterion
        if criterion in ("thermal", "heated") and scene.atmosphere.latent_heat <= 0.0:
            raise SceneError(f"{source}: adaptive.criterion = '{criterion}' measures heat in units of "
                             f"atmosphere.latent_heat (Q), which must then be > 0 (got {scene.atmosphere.latent_heat})")
        if criterion == "heated" and not (scene.atmosphere.heating_rate > 0.0 and scene.adaptive.heating_time > 0.0):
            raise SceneError(f"{source}: adaptive.criterion = 'heated' refines above heated ground: it needs "
                             f"atmosphere.heating_rate > 0 (got {scene.atmosphere.heating_rate}) and "
                             f"adaptive.heating_time > 0 (got {scene.adaptive.heating_time})")
    if scene.atmosphere is not None:
        a = scene.atmosphere
        from .environment import EnvironmentProfile
        profile = EnvironmentProfile.of(a)
        for y in (0.0, size[1], *(k for k in profile.kinks if k < size[1])):
            t = float(profile.temperature(y))
            if t + a.saturation_c <= 0.0 or t < 100.0:
                what = f"atmosphere.lapse_rate = {a.lapse_rate} K/m"
                if profile.has_inversion and y > a.inversion_height:
                    what += (f", atmosphere.inversion_strength = {a.inversion_strength} K and "
                             f"atmosphere.lapse_rate_above = {a.lapse_rate_above} K/m")
                raise SceneError(
                    f"{source}: {what} give T0 = {t:.1f} K at y = {y} m, "
                    f"outside the saturation formula's range (T + C > 0, T >= 100 K)")
    if scene.pbf.gradient_correction and scene.pbf.projection != "velocity":
        raise SceneError(f"{source}: pbf.gradient_correction corrects the velocity projection's divergence; it needs "
                         f"pbf.projection = 'velocity' (got '{scene.pbf.projection}')")
    t = scene.time
    if t.cfl > 0.0 and not (t.dt_min <= t.dt <= t.dt_max):
        raise SceneError(f"{source}: time.dt = {t.dt} s must lie in [time.dt_min, time.dt_max] = [{t.dt_min}, {t.dt_max}] s "
                         f"when time.cfl > 0 (the controlled step starts at dt)")
    if scene.wave is not None and scene.domain.boundary[1] != "wall":
        raise SceneError(f"{source}: [wave] needs domain.boundary[1] = 'wall'")
    if scene.forcing is not None:
        if scene.atmosphere is None:
            raise SceneError(f"{source}: [forcing] acts on the temperature and vapor of an atmosphere; "
                             "it needs an [atmosphere] section")
        for kind in ("subsidence", "radiative", "moisture"):
            z = getattr(scene.forcing, kind + "_heights")
            if any(b < a for a, b in zip(z, z[1:])):
                raise SceneError(f"{source}: forcing.{kind}_heights = {short(z)} must be non-decreasing (m)")
