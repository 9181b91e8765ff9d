"""A parameter is declared once: the solver's C++ declaration (csrc/params.h, PBF_PARAMS) and the scene
schema (pbf_cuda/scene.py) must not drift apart.

* every C++ parameter is either copied from a scene field (the field exists, its type and length fit, and
  the C++ default is the schema's default) or computed from the scene (pbf_cuda.simulation.DERIVED);
* every scene field reaches the solver's parameters, through exactly the parameters that declare it (changing
  it changes nothing else), or is declared outside the solver (pbf_cuda.simulation.OUTSIDE_SOLVER).
"""
import dataclasses

import numpy as np
import pytest

from pbf_cuda.scene import SECTIONS, SceneError, load_scene

core = pytest.importorskip("pbf_cuda._core")
from pbf_cuda import simulation  # noqa: E402

CXX_TYPES = {"float": float, "int": int, "std::size_t": int, "bool": bool}


def schema_fields():
    """{"section.field": dataclasses.Field} of the whole scene schema."""
    return {f"{section}.{f.name}": f for section, cls in SECTIONS.items() for f in dataclasses.fields(cls)}


def schema_default(field):
    return field.default_factory() if field.default_factory is not dataclasses.MISSING else field.default


def declared():
    return {name: (ctype, length, source) for name, ctype, length, source in core.declared_params()}


def test_the_params_struct_is_the_declared_list():
    names = [name for name, *_ in core.declared_params()]
    assert len(names) == len(set(names))
    p = core.Params()
    attributes = {a for a in dir(p) if not a.startswith("_")}
    assert attributes == set(names)


def test_every_solver_parameter_is_copied_from_a_scene_field_with_its_default_or_derived():
    fields = schema_fields()
    defaults = core.Params()
    copied = {}
    for name, (ctype, length, source) in declared().items():
        if not source:
            assert name in simulation.DERIVED, f"{name}: no scene field in params.h and not in DERIVED"
            continue
        assert name not in simulation.DERIVED, f"{name}: both copied from {source} and DERIVED"
        assert source in fields, f"{name}: params.h names scene field {source}, which the schema lacks"
        copied[source] = name
        field = fields[source]
        want = schema_default(field)
        have = getattr(defaults, name)
        if length:
            assert isinstance(want, list) and field.metadata["length"] == length, (name, want)
            values = zip(have, want)
        else:
            assert not isinstance(want, list), name
            values = [(have, want)]
        for h, w in values:
            kind = CXX_TYPES[ctype]
            assert isinstance(w, kind) and not (kind is not bool and isinstance(w, bool)), (name, ctype, w)
            cast = np.float32 if ctype == "float" else kind
            assert cast(h) == cast(w), f"{name}: C++ default {h} != scene default {source} = {w}"
    assert len(copied) == len(set(copied.values()))
    derived_names = {n for n, (_, _, s) in declared().items() if not s}
    assert set(simulation.DERIVED) == derived_names
    for name, reads in simulation.DERIVED.items():
        for source in reads:
            assert source in fields or source in SECTIONS, f"DERIVED[{name}] reads unknown scene field {source}"
    assert set(simulation.OUTSIDE_SOLVER) <= set(fields)


def base_scene():
    """Every section present and every switch on, so each field can matter: adaptive with the look-ahead
    criterion, smoothing, velocity projection, a wave, an explicit fill box, the large-scale forcing."""
    return load_scene("growing_adaptive", **{
        "domain.size": [1200.0, 1600.0, 1200.0], "particles.spacing": 100.0,
        "particles.fill_min": [0.0, 0.0, 0.0], "particles.fill_max": [1200.0, 1600.0, 1200.0],
        "adaptive.criterion": "lookahead", "smoothing.fields": ["temperature"], "wave.amplitude": 0.5,
        "forcing.subsidence_values": [-1e-3, -1e-3, 0.0, 0.0], "forcing.radiative_values": [-1e-5, 0.0, 0.0, 0.0],
        "forcing.moisture_values": [-1e-8, 0.0, 0.0, 0.0]})


def params_of(scene, capacity=4096):
    p = simulation.build_params(scene, capacity)
    return {name: getattr(p, name) for name in declared()}


def other_values(value, meta):
    """A few valid-looking values different from `value` (the first that the schema accepts is used)."""
    lo, hi, choices, length = meta["lo"], meta["hi"], meta["choices"], meta["length"]
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, str):
        return [c for c in choices if c != value]
    if isinstance(value, list):
        if choices:
            flipped = [c for c in choices if c != value[0]]
            return [[flipped[0], *value[1:]], value + [c for c in choices if c not in value][:1]]
        return [[v, *value[1:]] for v in other_values(value[0], dict(meta, length=None))]
    candidates = [value + 1, value - 1] if isinstance(value, int) else [value * 1.25, value * 0.8, value + 0.1,
                                                                        (lo + hi) / 2 if None not in (lo, hi) else 1.0]
    return [c for c in candidates if c != value and (lo is None or c >= lo) and (hi is None or c <= hi)]


# Fields that matter under one setting of another field only, and that setting (the base scene uses another).
ONLY_WITH = {"adaptive.heating_time": {"adaptive.criterion": "heated"}}


def test_every_scene_field_reaches_exactly_the_parameters_that_declare_it():
    common = base_scene()
    data = common.to_dict()
    reads = {}                                      # scene field -> the parameters allowed to change with it
    for name, (_, _, source) in declared().items():
        if source:
            reads.setdefault(source, set()).add(name)
    for name, sources in simulation.DERIVED.items():
        for source in sources:
            reads.setdefault(source, set()).add(name)
    for dotted, field in schema_fields().items():
        scene = common.replace(**ONLY_WITH.get(dotted, {}))
        base = params_of(scene)
        section, key = dotted.split(".")
        value = data[section][key]
        changed = None
        for other in other_values(value, field.metadata):
            try:
                moved = scene.replace(**{dotted: other})
            except SceneError:
                continue
            changed = {k for k, v in params_of(moved).items() if not np.array_equal(v, base[k])}
            break
        assert changed is not None, f"{dotted}: no other valid value tried"
        allowed = reads.get(dotted, set())
        assert changed <= allowed, f"{dotted} changes {sorted(changed - allowed)}, which do not declare it"
        if dotted in simulation.OUTSIDE_SOLVER:
            assert not changed, f"{dotted} is declared outside the solver but changes {sorted(changed)}"
        else:
            assert changed, f"{dotted} reaches no solver parameter and is not in OUTSIDE_SOLVER"
    # A whole optional section: [atmosphere] switches the thermodynamics on.
    assert base["thermodynamics"] and not params_of(load_scene("dam_break"))["thermodynamics"]
