"""The grid's parameters against the scene schema (grid_baseline/parameters.py): every scene field is
copied, derived or ignored by the grid, decided once, and Params follows exactly the fields it says."""
import dataclasses
from pathlib import Path

import pytest

pytest.importorskip("jax")
pytest.importorskip("jax_cfd")
from grid_baseline.parameters import COPIED, DERIVED, IGNORED, Params, params_from_scene  # noqa: E402
from pbf_cuda.scene import SECTIONS, SceneError, load_scene  # noqa: E402

GRID = Path(__file__).resolve().parent.parent / "grid_baseline"
SCENE_FIELDS = {f"{section}.{f.name}": f for section, cls in SECTIONS.items() for f in dataclasses.fields(cls)}
COPIED_NAMES = {f"{section}.{name}" for section, names in COPIED.items() for name in names}
# the fields whose value Params depends on: the copied ones and those DERIVED into a Params field
SHAPE_PARAMS = COPIED_NAMES | {name for name, use in DERIVED.items() if use.startswith("Params.")}
SHAPE = (6, 5, 4)


def test_every_scene_field_is_copied_derived_or_ignored_once():
    decided = [COPIED_NAMES, set(DERIVED), set(IGNORED)]
    undecided = set(SCENE_FIELDS) - set().union(*decided)
    assert not undecided, (f"scene fields the grid has not decided about: {sorted(undecided)}; add each to "
                           f"grid_baseline/parameters.py's COPIED, DERIVED or IGNORED (with the reason)")
    assert set().union(*decided) <= set(SCENE_FIELDS), "the grid's tables name fields the scene no longer has"
    assert sum(len(d) for d in decided) == len(SCENE_FIELDS), "a field is in more than one of the tables"
    assert all(IGNORED.values()) and all(DERIVED.values())


def test_params_hold_the_copied_fields_under_the_scene_names():
    scene = load_scene("cycling")
    p = params_from_scene(scene, SHAPE)
    names = {f.name for f in dataclasses.fields(Params)}
    for section, fields in COPIED.items():
        for name in fields:
            assert name in names
            value = getattr(getattr(scene, section) or SECTIONS[section](), name)   # [forcing]: its defaults
            assert getattr(p, name) == (tuple(value) if isinstance(value, list) else value), name
    assert p.shape == SHAPE and p.size == tuple(scene.domain.size) and p.dt == scene.time.dt
    assert p.periodic == tuple(b == "periodic" for b in scene.domain.boundary)


def test_fields_the_simulation_reads_are_read_there():
    source = "".join(path.read_text() for path in GRID.glob("*.py") if path.name != "parameters.py")
    for dotted, use in DERIVED.items():
        if not use.startswith("Params."):
            assert f".{dotted.partition('.')[2]}" in source, f"{dotted}: DERIVED says '{use}', no grid module reads it"


def _other_values(meta, value):
    """Valid values of a field other than `value`, the likeliest to pass the scene's cross checks first."""
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, str):
        return [c for c in meta["choices"] if c != value]
    if isinstance(value, list) and meta["choices"]:   # the first entry changed (a fixed length kept)
        return [[c] + value[1:] if meta["length"] else [c] for c in meta["choices"] if c != value[0]]
    if isinstance(value, list):
        return [[w] * len(value) for w in _other_values(meta, sum(value) / len(value))] if value else []
    lo, hi = meta["lo"], meta["hi"]
    if isinstance(value, int):
        return [v for v in (value + 1, value - 1) if lo <= v <= hi]
    candidates = [value * 1.25 + 1e-3, value * 0.8, 0.5 * (value + hi), 0.5 * (value + lo), hi, lo]
    return [v for v in candidates if lo <= v <= hi and v != value]


@pytest.mark.parametrize("dotted", sorted(SCENE_FIELDS))
def test_params_follow_exactly_the_fields_that_shape_them(dotted):
    scene = load_scene("cycling")
    section, _, name = dotted.partition(".")
    if getattr(scene, section) is None:
        scene = scene.replace(**{f"{section}.{name}": getattr(SECTIONS[section](), name)})
    value = getattr(getattr(scene, section), name)
    if value is None:   # an optional corner (particles.fill_min/max): unset means the domain's
        others = [[f * s for s in scene.domain.size] for f in (0.25, 0.75)]
    else:
        others = _other_values(SCENE_FIELDS[dotted].metadata, value)
    base = params_from_scene(scene, SHAPE)
    for other in others:
        try:
            changed = scene.replace(**{dotted: other})
        except SceneError:
            continue   # refused by a cross check of the scene: try the next value
        assert (params_from_scene(changed, SHAPE) != base) == (dotted in SHAPE_PARAMS), \
            f"{dotted} = {other!r}: Params {'did not follow' if dotted in SHAPE_PARAMS else 'changed'}"
        return
    pytest.fail(f"{dotted}: no other value of this field passes the scene's checks; pick one here")
