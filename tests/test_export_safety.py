"""Exports that never destroy or escape: `cloudpbf export` against existing folders, its own run, earlier
exports, unfinished and damaged runs, too little memory, full and read-only disks, and fuzzed arguments
(hypothesis).  Runs are stored without the solver (a few dozen particles), so the module is quick."""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import subprocess
import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")
pytest.importorskip("zarr")
pytest.importorskip("pyvista")

from cloudpbf.cli import app  # noqa: E402
from cloudpbf.store.manifest import info_checksum, manifest  # noqa: E402
from cloudpbf_io.files import json_default  # noqa: E402
from pbf_cuda.scene import NAME_PATTERN, SceneError, load_scene, sanitize_name, scene_from_dict  # noqa: E402

runner = CliRunner()
FORMATS = ("vtp", "vtu", "bgeo", "netcdf", "zarr")


def _state(n, rng, step):
    return {"position": rng.uniform(0, 50, (n, 3)).astype(np.float32),
            "velocity": rng.normal(size=(n, 3)).astype(np.float32),
            "temperature": rng.uniform(280, 300, n).astype(np.float32),
            "vapor": rng.uniform(0, 0.01, n).astype(np.float32), "cloud": np.zeros(n, np.float32),
            "mass": np.full(n, 2.0, np.float32), "level": np.zeros(n, np.int32),
            "kernel_radius": np.full(n, 20.0, np.float32), "id": np.arange(n, dtype=np.uint32),
            "step": np.int64(step), "time_s": np.float64(step * 2.0)}


def stored_run(root: Path, tag: str = "0123456789abcdef", finished: bool = True, name: str = "growing") -> Path:
    """A small finished particle run as the cache holds it (config, snapshots, result.json with manifest)."""
    scene = load_scene("growing").with_particle_count(300).to_dict()
    scene["scene"] = {"name": name}
    run_dir = root / f"particles-growing-{tag}"
    (run_dir / "snapshots").mkdir(parents=True)
    key = tag * 4
    (run_dir / "config.json").write_text(json.dumps({"identity": {"solver": "particles", "scene": scene, "seed": 3},
                                                     "key": key}, default=json_default))
    rng = np.random.default_rng(int(tag[:4], 16))
    for step in (0, 5):
        np.savez(run_dir / "snapshots" / f"step_{step:06d}.npz", **_state(40, rng, step))
    if finished:
        info = {"key": key, "stable": True, "step": 5, "manifest": manifest(run_dir)}
        info["checksum"] = info_checksum(info)
        (run_dir / "result.json").write_text(json.dumps(info))
    return run_dir


def tree(root: Path) -> dict:
    """{relative path: sha256 or '<dir>' or '<link>'} of everything under root (links not followed)."""
    out = {}
    for base, dirs, files in os.walk(root):
        for name in dirs + files:
            p = Path(base) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "<link>"
            elif p.is_dir():
                out[rel] = "<dir>"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def export(*args):
    return runner.invoke(app, ["export", *map(str, args)])


def one_line_error(res, *needles):
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    text = " ".join(res.output.split())
    assert "Traceback" not in res.output
    for needle in needles:
        assert needle in text, text


def no_temp_files(root: Path) -> None:
    left = [p for p in root.rglob("*") if ".export-tmp" in p.name or ".export-old" in p.name or p.name.endswith(".tmp")]
    assert not left, left


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return stored_run(tmp_path_factory.mktemp("runs"))


@pytest.mark.parametrize("fmt", FORMATS)
def test_export_into_a_folder_of_other_files_touches_none_of_them(run_dir, tmp_path, fmt):
    victim = tmp_path / "victim"
    (victim / "sub").mkdir(parents=True)
    (victim / "sub" / "thesis.tex").write_text("work")
    before, run_before = tree(victim), tree(run_dir)
    res = export(run_dir, "--format", fmt, "--out", victim)
    assert res.exit_code == 0, res.output
    after = tree(victim)
    assert {k: v for k, v in after.items() if k in before} == before        # nothing changed or removed
    new = set(after) - set(before)
    assert new and all(k.startswith("particles-growing") for k in new), new
    assert tree(run_dir) == run_before
    again = export(run_dir, "--format", fmt, "--out", victim)                # the export exists now
    one_line_error(again, "exists (an earlier export of this run); --force replaces it")
    forced = export(run_dir, "--format", fmt, "--out", victim, "--force")
    assert forced.exit_code == 0, forced.output
    assert {k: v for k, v in tree(victim).items() if k in before} == before
    no_temp_files(victim)


def test_out_the_run_itself_keeps_the_run(run_dir, tmp_path):
    from cloudpbf.store.manifest import verify_run
    run = stored_run(tmp_path, "fedcba9876543210")
    for fmt in ("netcdf", "zarr", "vtp"):
        res = export(run, "--format", fmt, "--out", run)
        assert res.exit_code == 0, res.output
    assert verify_run(run, "fedcba9876543210" * 4) == []


def test_force_replaces_only_an_export_of_the_same_run(run_dir, tmp_path):
    other = stored_run(tmp_path / "runs", "aaaabbbbccccdddd")
    target = tmp_path / "out.nc"
    assert export(run_dir, "--format", "netcdf", "--out", target).exit_code == 0
    one_line_error(export(other, "--format", "netcdf", "--out", target, "--force"),
                   str(target), "is not an export of this run")
    plain = tmp_path / "data.nc"
    plain.write_text("mine")
    one_line_error(export(run_dir, "--format", "netcdf", "--out", plain, "--force"), "is not an export of this run")
    assert plain.read_text() == "mine"
    link = tmp_path / "link.nc"
    link.symlink_to(target)
    one_line_error(export(run_dir, "--format", "netcdf", "--out", link, "--force"), "is not an export of this run")
    folder = tmp_path / "series"
    assert export(run_dir, "--format", "vtp", "--out", folder).exit_code == 0
    assert export(run_dir, "--format", "vtp", "--out", folder, "--force").exit_code == 0
    (folder / "notes.txt").write_text("mine")          # put into an earlier export: the export is not replaced
    one_line_error(export(run_dir, "--format", "vtp", "--out", folder, "--force"),
                   "holds 1 file(s) the export did not write (notes.txt)")
    assert (folder / "notes.txt").read_text() == "mine"
    no_temp_files(tmp_path)


def test_a_killed_exports_temporary_copy_is_removed_by_the_next(run_dir, tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = tmp_path / f".out.nc.{dead.pid}.0123456789ab.export-tmp"
    stale.write_bytes(b"half")
    mine = tmp_path / ".out.nc.keep"
    mine.write_bytes(b"not a stage")
    assert export(run_dir, "--format", "netcdf", "--out", tmp_path / "out.nc").exit_code == 0
    assert not stale.exists() and mine.exists()


def test_names_come_from_the_run_and_stay_inside_out(tmp_path):
    run = stored_run(tmp_path / "runs", "1111222233334444", name="../../../../escape/pwn")
    out = tmp_path / "out"
    out.mkdir()
    for fmt in FORMATS:
        res = export(run, "--format", fmt, "--out", out)
        assert res.exit_code == 0, res.output
    names = sorted(p.name for p in out.iterdir())
    assert len(names) == 5 and all(n.startswith("particles-_.._.._.._escape_pwn") for n in names), names
    assert not (tmp_path / "escape").exists() and not list(tmp_path.parent.glob("escape*"))


def test_unfinished_damaged_and_extra_snapshots(tmp_path):
    run = stored_run(tmp_path / "runs", "5555666677778888", finished=False)
    one_line_error(export(run, "--format", "vtp", "--out", tmp_path / "a"), "has not finished", "--unverified")
    assert export(run, "--format", "vtp", "--out", tmp_path / "a", "--unverified").exit_code == 0
    done = stored_run(tmp_path / "runs", "9999aaaabbbbcccc")
    np.savez(done / "snapshots" / "step_000009.npz", **_state(5, np.random.default_rng(0), 9))   # not its own
    res = export(done, "--format", "vtp", "--out", tmp_path / "b")
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "b").glob("*.vtp")) == [
        "particles-growing_000000.vtp", "particles-growing_000005.vtp"]
    snap = done / "snapshots" / "step_000005.npz"
    snap.write_bytes(snap.read_bytes()[:-10] + b"0123456789")
    one_line_error(export(done, "--format", "vtp", "--out", tmp_path / "c"), "fails verification",
                   "step_000005.npz does not match its sha256")
    assert not (tmp_path / "c").exists()


def test_memory_is_checked_before_anything_is_allocated(run_dir, tmp_path):
    res = export(run_dir, "--format", "netcdf", "--out", tmp_path / "big.nc", "--resolution", "4096,4096,4096")
    one_line_error(res, "--resolution 4096,4096,4096: needs about", "GiB of memory")
    assert not (tmp_path / "big.nc").exists()


def test_run_id_prefixes(tmp_path):
    root = tmp_path / "runs"
    stored_run(root, "abcd000011112222")
    stored_run(root, "abcd999911112222")
    one_line_error(export("abcd", "--runs-root", root, "--out", tmp_path / "o1"), "fits 2 runs",
                   "particles-growing-abcd0000")
    assert export("abcd9", "--runs-root", root, "--out", tmp_path / "o2").exit_code == 0
    assert export("particles-growing-abcd0", "--runs-root", root, "--out", tmp_path / "o3").exit_code == 0
    one_line_error(export("ffff", "--runs-root", root), "no run in")


# ---- full and read-only disks ---------------------------------------------------------------------------
@contextlib.contextmanager
def small_disk(tmp_path: Path, size: str = "64k"):
    """A tmpfs of `size` where this machine lets the tests mount one (root), else None."""
    mount = tmp_path / f"fs-{uuid.uuid4().hex[:6]}"
    mount.mkdir()
    ok = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)],
                                              capture_output=True).returncode == 0
    try:
        yield mount if ok else None
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(mount)], capture_output=True)


@contextlib.contextmanager
def failing_writes(monkeypatch, under: Path, code: int):
    """Every file or folder made under `under` fails with OSError(code) (where no tmpfs can be mounted)."""
    real_open, real_mkdir, real_os_open = open, os.mkdir, os.open
    import builtins

    def guarded(path):
        try:
            return Path(os.fspath(path)).resolve().is_relative_to(under.resolve())
        except (TypeError, ValueError):
            return False

    def fake_open(file, mode="r", *a, **k):
        if any(c in mode for c in "wxa") and guarded(file):
            raise OSError(code, os.strerror(code), str(file))
        return real_open(file, mode, *a, **k)

    def fake_mkdir(path, *a, **k):
        if guarded(path):
            raise OSError(code, os.strerror(code), str(path))
        return real_mkdir(path, *a, **k)

    def fake_os_open(path, flags, *a, **k):
        if flags & os.O_CREAT and guarded(path):
            raise OSError(code, os.strerror(code), str(path))
        return real_os_open(path, flags, *a, **k)

    with monkeypatch.context() as m:
        m.setattr(builtins, "open", fake_open)
        m.setattr(os, "mkdir", fake_mkdir)
        m.setattr(os, "open", fake_os_open)
        yield


@pytest.mark.parametrize("fmt", FORMATS)
def test_full_disk_is_one_line_and_leaves_nothing(run_dir, tmp_path, monkeypatch, fmt):
    with small_disk(tmp_path) as disk:
        if disk is not None:
            (disk / "filler").write_bytes(b"x" * 60_000)
            before = tree(disk)
            res = export(run_dir, "--format", fmt, "--out", disk)
            one_line_error(res, str(disk), "nothing was written")
            # past the free-space check: the writer itself meets the full disk
            monkeypatch.setattr("cloudpbf.export.check_free_space", lambda folder, need: None)
            res = export(run_dir, "--format", fmt, "--out", disk)
            one_line_error(res, "the disk is full", "nothing was written")
            assert tree(disk) == before
            return
        out = tmp_path / "full"
        out.mkdir()
        with failing_writes(monkeypatch, out, errno.ENOSPC):
            res = export(run_dir, "--format", fmt, "--out", out)
        one_line_error(res, "the disk is full")
        assert list(out.iterdir()) == []


@pytest.mark.parametrize("fmt", ["netcdf", "vtp"])
def test_read_only_folder_is_one_line(run_dir, tmp_path, monkeypatch, fmt):
    with small_disk(tmp_path, "1m") as disk:
        if disk is not None and subprocess.run(["mount", "-o", "remount,ro", str(disk)]).returncode == 0:
            res = export(run_dir, "--format", fmt, "--out", disk)
            one_line_error(res, str(disk), "read-only")
            return
    out = tmp_path / "ro"
    out.mkdir()
    with failing_writes(monkeypatch, out, errno.EROFS):
        res = export(run_dir, "--format", fmt, "--out", out)
    one_line_error(res, "read-only")


# ---- fuzz ------------------------------------------------------------------------------------------------
_names = st.one_of(st.sampled_from(["..", ".", "../../x", "a/b", "victim", "new", "x.nc", "x.zarr", "link",
                                    "file", "\u202eevil", "sp ace", "-", "~"]),
                   st.text(min_size=1, max_size=12).filter(lambda t: "\0" not in t))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(fmt=st.sampled_from(FORMATS), out=_names, force=st.booleans(), unverified=st.booleans(),
       resolution=st.sampled_from([None, "2,2,2", "0,1,1", "a,b", "1,2", "4096,4096,4096", "3,3,3,3"]))
def test_fuzzed_export_arguments(run_dir, tmp_path_factory, fmt, out, force, unverified, resolution):
    sandbox = tmp_path_factory.mktemp("fuzz")
    inner = sandbox / "a" / "b"
    (inner / "victim").mkdir(parents=True)
    (inner / "victim" / "keep.txt").write_text("keep")
    (inner / "file").write_text("file")
    (inner / "link").symlink_to(inner / "victim")
    before, run_before = tree(sandbox), tree(run_dir)
    args = [run_dir, "--format", fmt, "--out", inner / out]
    args += ["--force"] * force + ["--unverified"] * unverified + (["--resolution", resolution] if resolution else [])
    cwd = os.getcwd()
    try:
        os.chdir(inner)
        res = export(*args)
    finally:
        os.chdir(cwd)
    assert res.exit_code in (0, 2), res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    after = tree(sandbox)
    assert {k: v for k, v in after.items() if k in before} == before          # nothing lost or changed
    for rel in set(after) - set(before):                                      # new files only inside --out
        assert (sandbox / rel).resolve().is_relative_to(sandbox.resolve()), rel
    assert tree(run_dir) == run_before
    no_temp_files(sandbox)


@settings(max_examples=300, deadline=None)
@given(name=st.text(max_size=80))
def test_fuzzed_scene_names_are_valid_or_a_scene_error(name):
    try:
        scene = scene_from_dict({"scene": {"name": name}})
    except SceneError as exc:
        assert "scene.name" in str(exc) and "\n" not in str(exc).replace("\\n", "")
    else:
        assert NAME_PATTERN.fullmatch(scene.name) and scene.name not in (".", "..")
    clean = sanitize_name(name)
    assert scene_from_dict({"scene": {"name": clean}}).name == clean
    assert "/" not in clean and not clean.startswith(".")
