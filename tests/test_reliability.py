"""Nothing bad gets through: every bad scene, cache file and command-line argument ends in a clear
error or a correct result, and nothing computed is lost.

Plays, on the CPU: mutated scene files (hypothesis), refused sizes, corrupted files of every kind in
the run cache, kill -9 during a run and during writes (subprocesses), and bad CLI arguments.  The run
cache cases use the toy solver of test_harness_toy (milliseconds per run), so the module takes well
under two minutes on 2 cores.
"""
from __future__ import annotations

import copy
import json
import math
import os
import signal
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from cloudpbf import runs
from cloudpbf.cli import app
from cloudpbf.store import manifest
from cloudpbf.store.files import sha256_file
from cloudpbf_io import files
from pbf_cuda import initial_state
from pbf_cuda.memory import boundary_count, check_memory, estimate_memory
from pbf_cuda.scene import MAX_SCENE_BYTES, SCENE_DIR, Scene, SceneError, list_scenes, load_scene, scene_from_dict
from test_harness_toy import ToySimulation, toy_scene, toy_solver  # noqa: F401  (fixture)

ROOT = Path(__file__).resolve().parent.parent
TESTS = Path(__file__).resolve().parent


def _core_built() -> bool:
    try:
        import pbf_cuda._core  # noqa: F401
        return True
    except ImportError:
        return False


# ==== scene files ===================================================================================
def toml_value(value) -> str:
    """A TOML literal for a value (inline tables for dicts)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


def to_toml(data: dict) -> str:
    lines = []
    for key, value in data.items():
        if not isinstance(value, dict):
            lines.append(f"{json.dumps(key)} = {toml_value(value)}")
    for key, value in data.items():
        if isinstance(value, dict):
            lines.append(f"[{json.dumps(key)}]")
            lines += [f"{json.dumps(k)} = {toml_value(v)}" for k, v in value.items()]
    return "\n".join(lines) + "\n"


def raw_scene(name: str) -> dict:
    import tomllib
    return tomllib.loads((SCENE_DIR / f"{name}.toml").read_text())


leaf = st.one_of(
    st.integers(min_value=-2**70, max_value=2**70), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.text(max_size=20), st.just("x" * 5000), st.just(10**400),
    st.lists(st.floats(-1e7, 1e7), max_size=4), st.lists(st.sampled_from(["wall", "periodic", "open"]), max_size=4),
    st.just(["wall", "wall", "wall"]), st.just({"a": 1}), st.just([]),
).map(copy.deepcopy)       # a fresh object per draw: a drawn table may be mutated further
EXTENDS = ["growing", "dam_break", "", ".", "..", "/dev/zero", "/proc/self/environ", "../../../etc/passwd",
           "self.toml", "other.toml", "./other.toml", "sub/../self.toml", "missing.toml", "x" * 5000, "a\nb"]


@st.composite
def mutated_scene(draw):
    """(TOML text or bytes, the other file's text): a shipped scene's table with random mutations."""
    data = raw_scene(draw(st.sampled_from(list_scenes())))
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["value", "delete", "section", "unknown", "extends", "name"]))
        sections = [k for k, v in data.items() if isinstance(v, dict)] or ["scene"]
        section = draw(st.sampled_from(sections + ["pbf", "domain", "particles", "atmosphere", "adaptive"]))
        table = data.setdefault(section, {}) if isinstance(data.get(section, {}), dict) else None
        if kind == "value" and table is not None:
            fields = {"domain": ["size", "boundary"], "particles": ["spacing", "fill_min", "kernel_ratio", "seed"],
                      "time": ["dt", "steps", "check_every"], "pbf": ["iterations", "gravity", "unilateral"],
                      "adaptive": ["enabled", "capacity", "max_level"],
                      "atmosphere": ["saturation_a", "lapse_rate", "vapor_profile"]}.get(section, list(table) or ["x"])
            table[draw(st.sampled_from(fields))] = draw(leaf)
        elif kind == "delete" and table:
            table.pop(draw(st.sampled_from(sorted(table))))
        elif kind == "section":
            data[section] = draw(leaf)
        elif kind == "unknown" and table is not None:
            table[draw(st.text(min_size=1, max_size=8))] = draw(leaf)
        elif kind == "extends":
            data.setdefault("scene", {}) if isinstance(data.get("scene", {}), dict) else None
            if isinstance(data.get("scene"), dict):
                data["scene"]["extends"] = draw(st.one_of(st.sampled_from(EXTENDS), leaf))
        elif kind == "name" and isinstance(data.get("scene", {}), dict):
            data.setdefault("scene", {})["name"] = draw(leaf)
    text = to_toml(data)
    damage = draw(st.sampled_from(["none", "none", "truncate", "bytes"]))
    if damage == "truncate":
        return text[:draw(st.integers(0, len(text)))].encode()
    if damage == "bytes":
        raw = bytearray(text.encode())
        for _ in range(draw(st.integers(1, 5))):
            raw.insert(draw(st.integers(0, len(raw))), draw(st.integers(0, 255)))
        return bytes(raw)
    return text.encode()


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                   HealthCheck.too_slow])
@given(content=mutated_scene(), other=st.sampled_from(["self", "growing", "cycle", "outside"]))
def test_fuzzed_scene_files_load_or_raise_scene_error(tmp_path_factory, content, other):
    """Every mutated scene file is either a valid Scene or a SceneError naming the file; a valid one is
    sized before anything is allocated (its memory check passes or is a SceneError)."""
    folder = tmp_path_factory.mktemp("fuzz")
    path = folder / "self.toml"
    path.write_bytes(content)
    (folder / "other.toml").write_text({"self": '[pbf]\niterations = 3\n', "growing": '[scene]\nextends = "growing"\n',
                                        "cycle": '[scene]\nextends = "self.toml"\n',
                                        "outside": '[scene]\nextends = "../x.toml"\n'}[other])
    try:
        scene = load_scene(path)
    except SceneError as exc:
        message = str(exc)
        assert len(message) < 1500, message[:200]                      # values are shortened
        assert "self.toml" in message or "other.toml" in message or "scene '" in message, message
        return
    assert isinstance(scene, Scene)
    assert isinstance(scene.name, str) and scene.time.check_every <= 64
    try:
        check_memory(scene, "cpu")
    except SceneError as exc:
        assert "particles" in str(exc) or "cells" in str(exc)


@settings(max_examples=150, deadline=None)
@given(data=st.dictionaries(st.sampled_from(["scene", "pbf", "domain", "time", "wave", "x"]),
                            st.one_of(leaf, st.dictionaries(st.text(max_size=12), leaf, max_size=3)), max_size=4))
def test_scene_from_arbitrary_dicts_is_a_scene_or_scene_error(data):
    try:
        assert isinstance(scene_from_dict(data, source="fuzz"), Scene)
    except SceneError as exc:
        assert str(exc).startswith("fuzz")


@pytest.mark.parametrize("text, expect", [
    ("scene = 3\n", "[scene] = 3 must be a table"),
    ("pbf = 3\n", "[pbf] must be a table"),
    ("[pbf]\niterations = 99999999999999999999999999999999999\n", "pbf.iterations = 99999"),
    ("[scene]\nname = 3\n", "scene.name = 3: expected 1 to 64 characters, each a letter"),
    ("[scene]\nname = \"../../x/pwn\"\n", "no spaces, slashes or other symbols"),
    ('[scene]\nextends = "."\n', "is not a regular file"),
    ('[scene]\nextends = ""\n', "scene.extends = '': allowed: a shipped scene"),
    ('[scene]\nextends = "/dev/zero"\n', "outside the including file's folder"),
    ('[scene]\nextends = "../../../etc/passwd"\n', "outside the including file's folder"),
    ('[scene]\nextends = "/proc/self/environ"\n', "outside the including file's folder"),
    ('[scene]\nextends = "bad.toml"\n', "scene.extends forms a cycle: bad.toml -> bad.toml"),
    ('[scene]\nextends = "./sub/../bad.toml"\n', "scene.extends forms a cycle"),
    ('[scene]\nextends = "' + "x" * 100_000 + '"\n', "(100002 chars)"),
    ('[pbf]\niterations = "' + "y" * 100_000 + '"\n', "(100002 chars): expected a number in [1, 200]"),
    ("[time]\ncheck_every = 1000\n", "time.check_every = 1000 is out of range: allowed [1, 64]"),
])
def test_bad_scene_files_name_file_field_and_allowed(tmp_path, text, expect):
    (tmp_path / "sub").mkdir()
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError) as err:
        load_scene(path)
    message = str(err.value)
    assert expect in message and "bad.toml" in message, message
    assert len(message) < 1000


def test_binary_huge_and_special_files_are_refused(tmp_path):
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00\x01garbage")
    with pytest.raises(SceneError, match=r"binary\.toml: not UTF-8"):
        load_scene(binary)
    huge = tmp_path / "huge.toml"
    huge.write_text("# " + "a" * MAX_SCENE_BYTES + "\n")
    with pytest.raises(SceneError, match=r"at most"):
        load_scene(huge)
    with pytest.raises(SceneError, match="not a regular file"):
        load_scene(Path("/dev/zero"))
    with pytest.raises(SceneError, match="not a regular file"):
        load_scene(tmp_path)


def test_extends_cycle_through_two_files_and_allowed_extends(tmp_path):
    (tmp_path / "a.toml").write_text('[scene]\nextends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('[scene]\nextends = "./a.toml"\n')
    with pytest.raises(SceneError, match=r"cycle: a\.toml -> b\.toml -> a\.toml"):
        load_scene(tmp_path / "a.toml")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "base.toml").write_text('[scene]\nextends = "growing"\n[pbf]\niterations = 7\n')
    (tmp_path / "top.toml").write_text('[scene]\nname = "top"\nextends = "sub/base.toml"\n[time]\nsteps = 9\n')
    scene = load_scene(tmp_path / "top.toml")
    assert (scene.name, scene.pbf.iterations, scene.time.steps) == ("top", 7, 9)
    assert scene.particles.spacing == load_scene("growing").particles.spacing
    # a symbolic link inside the folder that leads outside it is refused
    (tmp_path / "link.toml").symlink_to(SCENE_DIR / "growing.toml")
    (tmp_path / "via_link.toml").write_text('[scene]\nextends = "link.toml"\n')
    with pytest.raises(SceneError, match="outside the including file's folder"):
        load_scene(tmp_path / "via_link.toml")


# ==== sizes and memory ===============================================================================
def test_sizes_that_cannot_fit_are_refused_before_allocation(monkeypatch):
    # The same answer on every machine: 24 GiB of host memory and 1 GiB of GPU memory available.
    import pbf_cuda.memory as memory
    monkeypatch.setattr(memory, "available_memory",
                        lambda backend: (1 if backend == "cuda" else 24) * 2**30)
    with pytest.raises(SceneError, match=r"GiB of GPU memory, 1\.00 GiB free"):
        check_memory(load_scene("growing").with_particle_count(50_000_000), "cuda")
    with pytest.raises(SceneError, match=r"1,000,000,000 fluid particles.*GiB of host memory"):
        check_memory(load_scene("rest_box").with_particle_count(10**9), "cpu")
    with pytest.raises(SceneError, match=r"125,000,000,000 particles .* exceed the solver's limit"):
        check_memory(load_scene("rest_box", **{"particles.spacing": 1e-4}), "cpu")
    big = load_scene("rest_box", **{"domain.size": [1000.0, 1000.0, 1000.0], "particles.spacing": 0.5,
                                    "particles.fill_max": [5.0, 5.0, 5.0],
                                    "domain.boundary": ["wall", "wall", "wall"]})
    assert big.estimated_particles() == 1000
    with pytest.raises(SceneError, match="1,000 fluid particles"):
        check_memory(big, "cpu")
    est = estimate_memory(load_scene("growing_adaptive"), "cpu")
    assert est.slots == math.ceil(est.fluid * load_scene("growing_adaptive").adaptive.capacity)


def _boundary_by_whole_lattice(scene):
    """The former construction: the whole extended lattice, filtered to what lies beyond a wall."""
    h, ds = scene.kernel_radius, initial_state.lattice_spacings(scene)
    counts = initial_state.lattice_counts(scene)
    walls = [b == "wall" for b in scene.domain.boundary]
    axes = [(np.arange(-(e := (math.ceil(h / ds[a]) if walls[a] else 0)), counts[a] + e) + 0.5) * ds[a]
            for a in range(3)]
    g = np.meshgrid(*axes, indexing="ij")
    pos = np.stack([x.ravel() for x in g], axis=1)
    out = np.zeros(len(pos), bool)
    for a in range(3):
        if walls[a]:
            out |= (pos[:, a] < 0) | (pos[:, a] > scene.domain.size[a])
    return pos[out].astype(np.float32)


@pytest.mark.parametrize("name,boundary", [("dam_break", None), ("growing", None), ("rest_box", ["wall"] * 3),
                                           ("growing", ["periodic", "wall", "wall"])])
def test_boundary_shell_equals_the_whole_lattice_construction(name, boundary):
    scene = load_scene(name, **({"domain.boundary": boundary} if boundary else {})).with_particle_count(2000)
    shell = initial_state.boundary_particles(scene)
    np.testing.assert_array_equal(shell["position"], _boundary_by_whole_lattice(scene))
    assert len(shell["position"]) == boundary_count(scene)


def test_boundary_shell_of_a_large_walled_box_is_cheap():
    scene = load_scene("rest_box", **{"domain.size": [400.0, 400.0, 400.0], "particles.spacing": 1.0,
                                      "particles.fill_max": [5.0, 5.0, 5.0],
                                      "domain.boundary": ["wall", "wall", "wall"]})
    t0 = time.perf_counter()
    shell = initial_state.boundary_particles(scene)   # the whole lattice would be 404^3 = 66M sites
    assert len(shell["position"]) == boundary_count(scene) < 3_000_000
    assert time.perf_counter() - t0 < 20


@pytest.mark.skipif(not _core_built(), reason="the particle solver is not built")
def test_from_arrays_refuses_duplicate_ids():
    from pbf_cuda import Simulation
    sim = Simulation(load_scene("rest_box").with_particle_count(300), backend="cpu")
    st_ = sim.state()
    st_["id"][5] = st_["id"][6]
    with pytest.raises(ValueError, match=r"1 duplicated id\(s\) \(" + str(int(st_["id"][6])) + r"\)"):
        Simulation.from_arrays(sim.scene, st_, backend="cpu")
    with pytest.raises(SceneError, match="fluid particles"):
        Simulation(load_scene("rest_box").with_particle_count(10**9), backend="cpu")


@pytest.mark.skipif(not _core_built(), reason="the particle solver is not built")
def test_from_arrays_checks_the_projection_impulse():
    """projection_impulse warm-starts the velocity projection: refused for a scene without one, and its length is
    checked like every other array's."""
    from pbf_cuda import Simulation
    sim = Simulation(load_scene("dam_break").with_particle_count(300), backend="cpu")
    st_ = sim.state()
    st_["projection_impulse"] = np.zeros(len(st_["mass"]), np.float32)
    with pytest.raises(ValueError, match=r"projection_impulse.*pbf.projection = 'position'.*'velocity' only"):
        Simulation.from_arrays(sim.scene, st_, backend="cpu")
    cloud = Simulation(load_scene("growing").with_particle_count(300), backend="cpu")
    st_ = cloud.state()
    st_["projection_impulse"] = np.zeros(len(st_["mass"]) - 1, np.float32)
    with pytest.raises(ValueError, match=r"fluid\['projection_impulse'\] has \d+ rows, position has \d+"):
        Simulation.from_arrays(cloud.scene, st_, backend="cpu")


# ==== compiled core against its sources =============================================================
@pytest.mark.skipif(not _core_built(), reason="the particle solver is not built")
def test_compiled_core_matches_its_sources_and_a_mismatch_is_refused(tmp_path):
    import shutil

    import pbf_cuda._core as core
    from pbf_cuda.buildinfo import CSRC, StaleBuildError, check_core, csrc_hash
    assert core.source_hash() == csrc_hash()
    check_core(core)
    copy = tmp_path / "csrc"
    shutil.copytree(CSRC, copy)
    with open(copy / "params.h", "a") as fh:
        fh.write("// edited\n")
    edited = csrc_hash(copy)
    assert edited != csrc_hash()
    with pytest.raises(StaleBuildError, match="built from other sources.*rebuild"):
        check_core(core, expected=edited)


# ==== the run cache ==================================================================================
def toy_spec(**changes):
    base = dict(solver="particles", scene=toy_scene(), seed=1, checkpoint_every=5, record_steps=True,
                keep_snapshots=2)
    base.update(changes)
    return runs.RunSpec(**base)


def comparable(result) -> dict:
    """What must be identical between a recomputed run and the original."""
    info = {k: v for k, v in result.info.items()
            if k not in ("wall_s", "step_wall_s", "step_ms", "finished", "resumed_from")}
    steps = result.steps_table().drop(columns=["wall_ms"], errors="ignore")   # a measurement, not a result
    return {"info": info, "stats": result.stats(), "profiles": result.profiles(), "steps": steps,
            "timings": {k: v["count"] for k, v in result.timings().items()},
            "snapshot": result.snapshot()["position"]}


def assert_same(a: dict, b: dict) -> None:
    assert a["info"] == b["info"]
    for name in ("stats", "profiles", "steps"):
        pd.testing.assert_frame_equal(a[name], b[name])
    assert a["timings"] == b["timings"]
    np.testing.assert_array_equal(a["snapshot"], b["snapshot"])


def _truncate(p: Path):
    p.write_bytes(p.read_bytes()[: max(1, p.stat().st_size // 3)])


def _empty(p: Path):
    p.write_bytes(b"")


def _garble(p: Path):
    raw = bytearray(p.read_bytes())
    for i in range(0, len(raw), max(1, len(raw) // 7)):
        raw[i] ^= 0x5A
    p.write_bytes(bytes(raw))


def _drop_rows(p: Path):               # a CSV cut at a line boundary: still parses, fewer rows
    lines = p.read_text().splitlines(keepends=True)
    p.write_text("".join(lines[: len(lines) // 4]))


def _edit_value(p: Path):              # valid JSON with a changed value
    info = json.loads(p.read_text())
    info["stable"] = not info["stable"]
    p.write_text(json.dumps(info))


FINISHED_DAMAGE = [
    ("result.json", _truncate), ("result.json", _empty), ("result.json", _garble), ("result.json", _edit_value),
    ("timings.csv", _truncate), ("timings.csv", _empty), ("steps.csv", _drop_rows), ("steps.csv", _garble),
    ("stats.parquet", _truncate), ("stats.parquet", _garble), ("profiles.parquet", _empty),
    ("snapshots/step_000020.npz", _truncate), ("snapshots/step_000020.npz", _garble), ("config.json", _garble),
    ("checkpoint.npz", _garble), ("snapshots/step_000020.npz", lambda p: p.unlink()),
]


@pytest.fixture
def reference(toy_solver, tmp_path_factory):
    spec = toy_spec()
    return spec, comparable(runs.execute(spec, tmp_path_factory.mktemp("ref"), quiet=True))


@pytest.mark.parametrize("name,damage", FINISHED_DAMAGE, ids=[f"{n}-{d.__name__}" for n, d in FINISHED_DAMAGE])
def test_damaged_finished_run_is_quarantined_and_recomputed(reference, toy_solver, tmp_path, name, damage):
    spec, expected = reference
    first = runs.execute(spec, tmp_path, quiet=True)
    d = first.path
    damage(d / name)
    assert runs.verify_run(d, spec.key())                            # detected on read
    assert runs.cached_result(spec, tmp_path) is None                # never served
    toy_solver.steps_taken = 0
    again = runs.execute(spec, tmp_path, quiet=True)
    assert not again.cached and toy_solver.steps_taken == spec.total_steps   # recomputed
    assert_same(comparable(again), expected)                         # correct
    assert runs.verify_run(d, spec.key()) == []
    kept = list((tmp_path / runs.QUARANTINE).glob(f"{d.name}-*"))    # the damaged files are kept
    assert len(kept) == 1 and (kept[0] / "result.json").exists()
    if (d / name).exists() and name != "result.json" and (kept[0] / name).exists():
        assert (kept[0] / name).read_bytes() != (d / name).read_bytes()
    assert "quarantined" in (d / "log.txt").read_text()
    third = runs.execute(spec, tmp_path, quiet=True)
    assert third.cached and toy_solver.steps_taken == spec.total_steps


def test_tampered_manifest_is_refused_without_reading_outside_the_run(toy_solver, tmp_path):
    spec = toy_spec()
    first = runs.execute(spec, tmp_path, quiet=True)
    info = json.loads((first.path / "result.json").read_text())
    info["manifest"]["../../outside.txt"] = {"bytes": 1, "sha256": "0" * 64}
    info["manifest"]["stats.parquet"] = "not an entry"
    info["checksum"] = manifest.info_checksum(info)                # a consistent-looking forgery
    (first.path / "result.json").write_text(json.dumps(info))
    problems = runs.verify_run(first.path, spec.key())
    assert sum("malformed" in p for p in problems) == 2, problems
    again = runs.execute(spec, tmp_path, quiet=True)
    assert not again.cached and runs.verify_run(again.path, spec.key()) == []


class Crash(Exception):
    pass


def crash_at(step):
    def hook(s):
        if s >= step:
            raise Crash(f"crash at {s}")
    return hook


UNFINISHED_DAMAGE = [
    ("progress.json", _truncate), ("progress.json", _empty), ("progress.json", _garble),
    ("partial/stats.json", _truncate), ("partial/steps.json", _garble), ("partial/profiles.json", _empty),
    ("checkpoint.npz", _truncate), ("checkpoint.npz", _garble), ("checkpoint.npz", lambda p: p.unlink()),
    ("progress.json", lambda p: p.unlink()),
]


@pytest.mark.parametrize("name,damage", UNFINISHED_DAMAGE, ids=[f"{n}-{d.__name__}" for n, d in UNFINISHED_DAMAGE])
def test_damaged_unfinished_run_restarts_and_gives_the_right_result(reference, toy_solver, tmp_path, name, damage):
    spec, expected = reference
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path, quiet=True, on_step=crash_at(12))
    d = spec.directory(tmp_path)
    damage(d / name)
    toy_solver.steps_taken = 0
    result = runs.execute(spec, tmp_path, quiet=True)
    assert result.resumed_from is None and toy_solver.steps_taken == spec.total_steps
    assert_same(comparable(result), expected)
    kept = list((tmp_path / runs.QUARANTINE).glob(f"{d.name}-*"))
    assert len(kept) == 1, "the unusable attempt is kept aside"
    assert "quarantined" in (d / "log.txt").read_text()


def test_checkpoint_of_another_run_or_scene_is_not_resumed(reference, toy_solver, tmp_path):
    spec, expected = reference
    other = toy_spec(seed=2)
    for s in (spec, other):
        with pytest.raises(Crash):
            runs.execute(s, tmp_path, quiet=True, on_step=crash_at(12))
    d, o = spec.directory(tmp_path), other.directory(tmp_path)
    for name in ("checkpoint.npz", "progress.json"):               # another run's pair copied in
        (d / name).write_bytes((o / name).read_bytes())
    toy_solver.steps_taken = 0
    result = runs.execute(spec, tmp_path, quiet=True)
    assert result.resumed_from is None and toy_solver.steps_taken == spec.total_steps
    assert_same(comparable(result), expected)
    assert "belongs to another run" in (d / "log.txt").read_text()
    # a checkpoint of a different scene, with a progress.json that vouches for it
    with pytest.raises(Crash):
        runs.execute(other, tmp_path, quiet=True, on_step=crash_at(12))
    sim = ToySimulation(toy_scene(**{"pbf.iterations": 9}), seed=2)
    sim.step(10)
    sim.save(o / "checkpoint.npz")
    prog = json.loads((o / "progress.json").read_text())
    runs.atomic_write_json(o / "progress.json", {**prog, "checkpoint_sha256": sha256_file(o / "checkpoint.npz")})
    res = runs.execute(other, tmp_path, quiet=True)
    assert res.resumed_from is None
    assert "the checkpoint's scene differs from the run's" in (o / "log.txt").read_text()


def test_stale_temp_files_are_removed_and_files_have_one_mode(toy_solver, tmp_path):
    spec = toy_spec()
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path, quiet=True, on_step=crash_at(12))
    d = spec.directory(tmp_path)
    stale = [d / ".stats.parquet.4194303.0123456789ab.tmp", d / "snapshots" / ".step_000010.npz.1.abcdefabcdef.tmp"]
    for p in stale:
        p.write_bytes(b"half")
    runs.execute(spec, tmp_path, quiet=True)
    assert not any(p.exists() for p in stale)
    assert not list(d.rglob("*.tmp"))
    umask = os.umask(0)
    os.umask(umask)
    want = files.FILE_MODE & ~umask
    modes = {p.relative_to(d).as_posix(): stat.S_IMODE(p.stat().st_mode) for p in d.rglob("*")
             if p.is_file() and p.name not in ("log.txt", ".lock")}
    assert modes and all(m == want for m in modes.values()), modes
    # the same helper (and mode) for checkpoints, study frames and the report
    from cloudpbf.store.files import save_frame
    files.atomic_savez(tmp_path / "c.npz", {"a": 1}, x=np.arange(3))
    save_frame(pd.DataFrame({"a": [1]}), tmp_path / "f.csv")
    for p in (tmp_path / "c.npz", tmp_path / "f.csv"):
        assert stat.S_IMODE(p.stat().st_mode) == want
    # a temp file of a writer that is still alive is left alone (outside a locked run directory)
    live = tmp_path / f".x.json.{os.getpid()}.0123456789ab.tmp"
    live.write_text("writing")
    dead = tmp_path / ".y.json.4194303.0123456789ab.tmp"
    dead.write_text("orphan")
    assert files.remove_stale_temps(tmp_path) == [dead] and live.exists()


@pytest.mark.skipif(not _core_built(), reason="the particle solver is not built")
def test_refused_run_leaves_nothing_in_the_cache(tmp_path):
    spec = runs.RunSpec("particles", load_scene("rest_box").with_particle_count(10**9), backend="cpu", steps=2)
    with pytest.raises(SceneError, match="1,000,000,000 fluid particles"):
        runs.execute(spec, tmp_path, quiet=True)
    assert not tmp_path.exists() or not any(tmp_path.iterdir())


# ==== kill -9 ===========================================================================================
RUNNER = textwrap.dedent("""
    import sys, time
    sys.path[:0] = [{tests!r}, {root!r}]
    from cloudpbf import runs, solvers
    import test_harness_toy as toy
    solvers.ADAPTERS["particles"] = toy.ToyAdapter
    spec = runs.RunSpec("particles", toy.toy_scene(**{{"time.steps": 40}}), seed=1, checkpoint_every=5,
                        record_steps=True, keep_snapshots=2)
    def slow(step):
        print(step, flush=True)
        time.sleep(0.05)
    runs.execute(spec, {out!r}, quiet=True, on_step=slow)
    print("done", flush=True)
""")


def _kill_when(proc, predicate, timeout=60.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if predicate():
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.01)
    proc.kill()
    return False


@pytest.mark.parametrize("when", ["after_checkpoint", "at_start"])
def test_kill_9_during_a_run_loses_nothing(toy_solver, tmp_path, when):
    script = tmp_path / "runner.py"
    out = tmp_path / "runs"
    script.write_text(RUNNER.format(tests=str(TESTS), root=str(ROOT), out=str(out)))
    spec = runs.RunSpec("particles", toy_scene(**{"time.steps": 40}), seed=1, checkpoint_every=5,
                        record_steps=True, keep_snapshots=2)
    d = spec.directory(out)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    if when == "at_start":
        ok = _kill_when(proc, lambda: (d / "log.txt").exists())
    else:
        ok = _kill_when(proc, lambda: (d / "progress.json").exists()
                        and json.loads((d / "progress.json").read_text() or "{}").get("step", 0) >= 15)
    assert ok, proc.stderr.read().decode()[-2000:]
    toy_solver.steps_taken = 0
    resumed = runs.execute(spec, out, quiet=True)
    straight = runs.execute(spec, tmp_path / "straight", quiet=True)
    assert_same(comparable(resumed), comparable(straight))
    if when == "after_checkpoint":
        assert resumed.resumed_from >= 15 and toy_solver.steps_taken < 40 + 40   # only the rest was computed
    assert runs.verify_run(d, spec.key()) == []


WRITER = textwrap.dedent("""
    import sys
    sys.path[:0] = [{root!r}]
    from cloudpbf_io import files
    i = 0
    while True:
        i += 1
        files.atomic_write_bytes({target!r}, (str(i) + ":").encode() * 200000 + b"END")
        print(i, flush=True)
""")


def test_kill_9_during_writes_leaves_old_or_new_file_never_a_partial_one(tmp_path):
    target = tmp_path / "big.bin"
    script = tmp_path / "writer.py"
    script.write_text(WRITER.format(root=str(ROOT), target=str(target)))
    for delay in (0.3, 0.55, 0.8):
        proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        proc.stdout.readline()                      # at least one complete write
        time.sleep(delay)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        data = target.read_bytes()
        head = data.split(b":", 1)[0]
        assert data == (head + b":") * 200000 + b"END"                  # one whole version
        files.remove_stale_temps(tmp_path)                               # the dead writer's temp is gone
        assert not list(tmp_path.glob(".*.tmp"))


# ==== the command line ====================================================================================
runner = CliRunner()


def cli(*args):
    result = runner.invoke(app, [str(a) for a in args], catch_exceptions=False)
    return result.exit_code, " ".join(result.output.split())


def test_cli_misuse_exits_2_naming_the_argument_and_leaves_no_run(tmp_path, monkeypatch):
    from cloudpbf.studies import context
    monkeypatch.setattr(context, "SCHEDULER_TIMEOUT_S", 1.0)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    root = tmp_path / "runs"
    bad_scene = tmp_path / "bad.toml"
    bad_scene.write_bytes(b"\x00\xff binary")
    escaping = tmp_path / "escape.toml"
    escaping.write_text('[scene]\nextends = "../../etc/passwd"\n')
    cases = [
        (["run", "rest_box", "--runs-root", a_file], "'--runs-root': '" + str(a_file) + "' is a file"),
        (["run", "rest_box", "--runs-root", a_file / "sub"], "'--runs-root'"),
        (["table1", "--out", a_file, "--scale", "smoke"], "'--out': '" + str(a_file) + "' is a file"),
        (["compare", "--scheduler", "nonsense", "--out", tmp_path / "o"], "'--scheduler': 'nonsense': expected"),
        (["sweep", "--scheduler", "tcp://host:99999", "--out", tmp_path / "o"], "'--scheduler'"),
        (["stress", "--scheduler", "tcp://127.0.0.1:9", "--out", tmp_path / "o", "--runs-root", root],
         "no dask scheduler answered at tcp://127.0.0.1:9"),
        (["run", "rest_box", "--particles", 10**9, "--runs-root", root],
         "--particles 1000000000: rest_box: 1,000,000,000 fluid particles"),
        (["run", "rest_box", "--set", "particles.spacing=1e-4", "--runs-root", root], "exceed the solver's limit"),
        (["run", bad_scene, "--runs-root", root], "bad.toml: not UTF-8"),
        (["run", escaping, "--runs-root", root], "outside the including file's folder"),
        (["run", "x" * 5000, "--runs-root", root], "unknown scene 'xxxx"),
        (["run", "rest_box", "--set", "time.check_every=1000000", "--runs-root", root],
         "time.check_every = 1000000 is out of range: allowed [1, 64]"),
    ]
    if not _core_built() or "cuda" not in __import__("pbf_cuda").available_backends():
        cases.append((["run", "rest_box", "--backend", "cuda", "--runs-root", root],
                      "Invalid value for '--backend': 'cuda' is not available here"))
    for args, expect in cases:
        code, output = cli(*args)
        assert code == 2, (args, output)
        assert expect in output, (args, output)
        assert "Traceback" not in output and len(output) < 1200, output
        assert not root.exists() or not any(root.iterdir()), f"{args} left {list(root.iterdir())}"
