"""Every shim that jax-cfd 0.2.1 needs under current jax, in one place (tested in tests/test_grid_compat.py).

jax-cfd 0.2.1 is the last release and is pinned by the project; two of its
problems matter to the grid baseline:

1. ``jax.tree_map`` / ``jax.tree_flatten`` / ``jax.tree_unflatten`` /
   ``jax.tree_leaves`` / ``jax.tree_structure`` were removed from the top-level
   ``jax`` namespace (jax 0.6).  jax-cfd calls them, e.g. in ``Grid.center``
   (and ``jax.named_call``, which the proxy below passes through should a jax
   drop it).
   Shim: the module-global name ``jax`` of the affected jax-cfd modules is
   replaced by a proxy module that forwards every attribute to the real jax
   and adds the missing aliases from ``jax.tree_util``.  The real ``jax``
   module itself is *not* modified (other libraries see it unchanged); on a jax
   that still has the aliases nothing is replaced.

2. ``boundaries.get_advection_flux_bc_from_velocity_and_scalar`` builds flux
   boundary conditions whose values are ``None`` on periodic axes.  As soon as
   one axis is a wall, padding that flux along a wall axis calls ``jnp.pad``
   with ``constant_values`` holding those ``None``s, which current jax rejects
   ("None is not a valid value for jnp.array").  Shim: the function is wrapped
   so that ``None`` values become ``0.0``; values on periodic axes are never
   read (periodic padding wraps), so results are otherwise unchanged.  The
   wrapper replaces the attribute on ``jax_cfd.base.boundaries`` (which is
   where ``advection.advect_van_leer`` looks it up), so it affects jax-cfd as a
   whole in this process; it only changes calls that would otherwise raise.

Other facts about jax-cfd 0.2.1 that the grid baseline works around in its own
code rather than by patching (see grid_baseline/projection.py and model.py):
only ``advect_van_leer`` supports walls; ``pressure.projection`` with
``solve_fast_diag`` falls back to a dense matrix on non-periodic axes and
``solve_cg`` is iterative (float32 leaves ~1e-5 relative divergence at walls),
so the projection is written directly in jax (FFT / DCT, exact).

:func:`apply` is idempotent and is called when grid_baseline imports its model.
"""
from __future__ import annotations

import functools
import importlib
import types

import jax

__all__ = ["apply", "status", "TREE_ALIASES", "PATCHED_MODULES"]

TREE_ALIASES = {
    "tree_map": "tree_map",
    "tree_flatten": "tree_flatten",
    "tree_unflatten": "tree_unflatten",
    "tree_leaves": "tree_leaves",
    "tree_structure": "tree_structure",
}
# jax-cfd modules (base package) that call a top-level jax function that newer jax may lack
# (jax.tree_* aliases; jax.named_call, kept as a pass-through if a jax drops it).
PATCHED_MODULES = (
    "jax_cfd.base.grids",
    "jax_cfd.base.array_utils",
    "jax_cfd.base.equations",
    "jax_cfd.base.subgrid_models",
    "jax_cfd.base.time_stepping",
)


def _named_call_passthrough(fun, *, name=None):
    return fun

_state = {"applied": False, "tree_proxy": False, "flux_bc": False}


class _JaxWithTreeAliases(types.ModuleType):
    """Stands in for ``jax`` inside jax-cfd modules: the real module plus the removed tree aliases."""

    def __init__(self, real):
        super().__init__("jax")
        object.__setattr__(self, "_real", real)
        for old, new in TREE_ALIASES.items():
            if not hasattr(real, old):
                object.__setattr__(self, old, getattr(real.tree_util, new))
        if not hasattr(real, "named_call"):
            object.__setattr__(self, "named_call", _named_call_passthrough)

    def __getattr__(self, name):  # only called for names not set on the proxy
        return getattr(object.__getattribute__(self, "_real"), name)


def _needs_tree_proxy() -> bool:
    return any(not hasattr(jax, name) for name in (*TREE_ALIASES, "named_call"))


def _fix_flux_bc_values(original):
    @functools.wraps(original)
    def get_advection_flux_bc_from_velocity_and_scalar(u, c, flux_direction):
        bc = original(u, c, flux_direction)
        values = tuple(tuple(0.0 if v is None else v for v in axis_values) for axis_values in bc.bc_values)
        if values == tuple(tuple(axis_values) for axis_values in bc.bc_values):
            return bc
        from jax_cfd.base import boundaries
        return boundaries.ConstantBoundaryConditions(bc.types, values)

    get_advection_flux_bc_from_velocity_and_scalar._grid_baseline_shim = True
    return get_advection_flux_bc_from_velocity_and_scalar


def apply() -> dict:
    """Install the shims (idempotent). Returns :func:`status`."""
    if _state["applied"]:
        return status()
    if _needs_tree_proxy():
        proxy = _JaxWithTreeAliases(jax)
        for name in PATCHED_MODULES:
            mod = importlib.import_module(name)
            if not isinstance(getattr(mod, "jax", None), _JaxWithTreeAliases):
                mod.jax = proxy
        _state["tree_proxy"] = True
    from jax_cfd.base import boundaries
    fn = boundaries.get_advection_flux_bc_from_velocity_and_scalar
    if not getattr(fn, "_grid_baseline_shim", False):
        boundaries.get_advection_flux_bc_from_velocity_and_scalar = _fix_flux_bc_values(fn)
    _state["flux_bc"] = True
    _state["applied"] = True
    return status()


def status() -> dict:
    """Which shims are active, and the versions they were applied against."""
    try:
        import jax_cfd
        cfd_version = getattr(jax_cfd, "__version__", "0.2.1?")
    except Exception:  # pragma: no cover
        cfd_version = None
    return {"jax": jax.__version__, "jax_cfd": cfd_version, **_state}
