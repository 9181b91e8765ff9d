"""The run cache's last holes: deeply nested JSON, partial rows of another run, entries of the wrong kind
(folders, files, links, devices) where the cache expects others, a bounded quarantine, full and read-only
caches; and `cloudpbf runs` (list, show, prune), run-id prefixes, the end-of-run summary.  All on the toy
solver of test_harness_toy (milliseconds per run)."""
from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import uuid
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from cloudpbf import runs
from cloudpbf.cli import app
from cloudpbf.store import manifest
from cloudpbf.store.safe import StoreError, UnsafeFileError, read_json
from test_harness_toy import toy_solver  # noqa: F401  (fixture)
from test_reliability import Crash, assert_same, comparable, crash_at, toy_spec

runner = CliRunner()


@pytest.fixture
def reference(toy_solver, tmp_path_factory):  # noqa: F811
    spec = toy_spec()
    return spec, comparable(runs.execute(spec, tmp_path_factory.mktemp("ref"), quiet=True))


@pytest.fixture
def alarm():
    """Fail instead of hanging: SIGALRM after 20 s."""
    def hang(signum, frame):
        raise TimeoutError("hung")
    old = signal.signal(signal.SIGALRM, hang)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def _recomputed_equal(spec, root, expected):
    result = runs.execute(spec, root, quiet=True)
    assert not result.cached
    assert_same(comparable(result), expected)
    return result


# ---- JSON bounds ---------------------------------------------------------------------------------------
def test_read_json_bounds_size_and_nesting(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(UnsafeFileError, match="nests 100000 levels"):
        read_json(p)
    p.write_text('["[[[[", {"a": [1, 2]}]')
    assert read_json(p) == ["[[[[", {"a": [1, 2]}]
    p.write_text("1" * 100)
    with pytest.raises(UnsafeFileError, match="more than the 10 allowed"):
        read_json(p, limit=10)


@pytest.mark.parametrize("name", ["result.json", "progress.json", "partial/stats.json"])
def test_deeply_nested_json_is_damage_not_a_recursion_error(reference, tmp_path, name):
    spec, expected = reference
    if name == "result.json":
        runs.execute(spec, tmp_path, quiet=True)
    else:
        with pytest.raises(Crash):
            runs.execute(spec, tmp_path, quiet=True, on_step=crash_at(12))
    (spec.directory(tmp_path) / name).write_text("[" * 100_000)
    _recomputed_equal(spec, tmp_path, expected)


def test_partial_rows_of_another_run_are_not_resumed(reference, tmp_path):
    spec, expected = reference
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path, quiet=True, on_step=crash_at(12))
    d = spec.directory(tmp_path)
    (d / "partial" / "steps.json").write_text(json.dumps([{"step": 1, "bogus": 1e308}]))
    result = _recomputed_equal(spec, tmp_path, expected)
    assert result.resumed_from is None and "bogus" not in result.steps_table()
    assert "partial/steps.json does not match" in (d / "log.txt").read_text()


def test_resume_keeps_every_column(reference, tmp_path):
    spec, expected = reference
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path, quiet=True, on_step=crash_at(12))
    result = runs.execute(spec, tmp_path, quiet=True)
    assert result.resumed_from == 10
    assert_same(comparable(result), expected)


# ---- entries of the wrong kind ---------------------------------------------------------------------------
def _make_file(p: Path):
    p.write_text("not what the cache put here")


def _make_dir(p: Path):
    p.mkdir()


@pytest.mark.parametrize("where,make", [(".lock", _make_dir), ("snapshots", _make_file), ("config.json", _make_dir),
                                        ("partial", _make_file), ("log.txt", "link")])
def test_wrong_kinds_inside_a_run_are_quarantined(reference, tmp_path, where, make):
    spec, expected = reference
    d = spec.directory(tmp_path)
    d.mkdir(parents=True)
    outside = tmp_path / "outside.txt"
    outside.write_text("keep")
    if make == "link":
        (d / where).symlink_to(outside)
    else:
        make(d / where)
    _recomputed_equal(spec, tmp_path, expected)
    assert outside.read_text() == "keep"                                   # never written through a link
    assert list((tmp_path / runs.QUARANTINE).iterdir())


def test_a_file_where_the_run_directory_belongs(reference, tmp_path):
    spec, expected = reference
    d = spec.directory(tmp_path)
    d.parent.mkdir(parents=True, exist_ok=True)
    d.write_text("a file")
    _recomputed_equal(spec, tmp_path, expected)
    kept = list((tmp_path / runs.QUARANTINE).glob(f"{d.name}-*/{d.name}"))
    assert len(kept) == 1 and kept[0].read_text() == "a file"


def test_a_file_at_the_quarantine_is_one_clear_error(reference, tmp_path):
    spec, _ = reference
    first = runs.execute(spec, tmp_path, quiet=True)
    (tmp_path / runs.QUARANTINE).write_text("x")
    sound = toy_spec(seed=5)
    runs.execute(sound, tmp_path, quiet=True)
    assert runs.execute(sound, tmp_path, quiet=True).cached               # a sound run is still served
    (first.path / "timings.csv").write_text("damaged")
    with pytest.raises(StoreError, match="quarantine: is a file, not a folder"):
        runs.execute(spec, tmp_path, quiet=True)


def _device_or_fifo(path: Path) -> str:
    try:
        os.mknod(path, 0o600 | stat.S_IFCHR, os.makedev(1, 5))            # /dev/zero's numbers
        return "device"
    except (PermissionError, OSError):
        os.mkfifo(path)
        return "fifo"


@pytest.mark.parametrize("how", ["link to /dev/zero", "node"])
def test_a_snapshot_replaced_by_a_device_does_not_hang(reference, tmp_path, alarm, how):
    spec, expected = reference
    first = runs.execute(spec, tmp_path, quiet=True)
    snap = first.path / "snapshots" / "step_000020.npz"
    info = json.loads((first.path / "result.json").read_text())
    snap.unlink()
    if how == "node":
        _device_or_fifo(snap)
    else:
        snap.symlink_to("/dev/zero")
    info["manifest"]["snapshots/step_000020.npz"]["bytes"] = 0
    info["checksum"] = manifest.info_checksum(info)
    (first.path / "result.json").write_text(json.dumps(info))
    problems = runs.verify_run(first.path, spec.key())
    assert problems and "not a regular file" in problems[0]
    _recomputed_equal(spec, tmp_path, expected)


def test_quarantine_keeps_the_newest(reference, tmp_path, monkeypatch):
    spec, _ = reference
    monkeypatch.setattr(manifest, "QUARANTINE_KEEP", 2)
    result = runs.execute(spec, tmp_path, quiet=True)
    for i in range(4):
        (result.path / "timings.csv").write_text(f"damaged {i}")
        result = runs.execute(spec, tmp_path, quiet=True)
        assert not result.cached
    assert len(list((tmp_path / runs.QUARANTINE).iterdir())) == 2


# ---- read-only and full caches -----------------------------------------------------------------------------
def _mount(tmp_path: Path, size: str) -> Path | None:
    mount = tmp_path / f"fs-{uuid.uuid4().hex[:6]}"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)],
                                           capture_output=True).returncode:
        return None
    return mount


def test_read_only_cache_serves_what_it_holds_and_refuses_in_one_line(reference, tmp_path):
    spec, expected = reference
    disk = _mount(tmp_path, "4m")
    if disk is None:
        pytest.skip("no tmpfs can be mounted here (not root)")
    try:
        runs.execute(spec, disk, quiet=True)
        assert subprocess.run(["mount", "-o", "remount,ro", str(disk)]).returncode == 0
        served = runs.execute(spec, disk, quiet=True)
        assert served.cached
        assert_same(comparable(served), expected)
        res = runner.invoke(app, ["runs", "--runs-root", str(disk)])
        assert res.exit_code == 0 and "stable" in res.output
        with pytest.raises(StoreError, match="cannot write"):
            runs.execute(toy_spec(seed=7), disk, quiet=True)
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_full_cache_is_one_line_and_leaves_no_temp_files(reference, tmp_path):
    spec, _ = reference
    disk = _mount(tmp_path, "64k")
    if disk is None:
        pytest.skip("no tmpfs can be mounted here (not root)")
    try:
        (disk / "filler").write_bytes(b"x" * 56_000)
        with pytest.raises(StoreError, match="the disk is full"):
            runs.execute(spec, disk, quiet=True)
        assert not [p for p in disk.rglob("*") if p.name.endswith(".tmp")]
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_injected_disk_errors_are_one_line(reference, tmp_path, monkeypatch):
    import errno
    spec, _ = reference
    real = os.replace

    def full(src, dst, *a, **k):
        if str(dst).startswith(str(tmp_path)):
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real(src, dst, *a, **k)
    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(StoreError, match="the disk is full"):
        runs.execute(spec, tmp_path, quiet=True)
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


# ---- cloudpbf runs, prefixes, the summary ----------------------------------------------------------------
def test_runs_list_show_prune_and_run_summary(toy_solver, tmp_path):  # noqa: F811
    root = tmp_path / "runs"
    res = runner.invoke(app, ["run", "growing", "--particles", "2000", "--steps", "6", "--runs-root", str(root),
                              "--quiet"])
    assert res.exit_code == 0, res.output
    assert "seed None" not in res.output and "physics: " in res.output and "largest speed" in res.output
    seed = next(line for line in res.output.splitlines() if ", seed " in line).split(", seed ")[1].split(",")[0]
    assert seed.isdigit()
    with pytest.raises(Crash):
        runs.execute(toy_spec(seed=4), root, quiet=True, on_step=crash_at(12))
    listing = runner.invoke(app, ["runs", "--runs-root", str(root)])
    assert listing.exit_code == 0, listing.output
    assert "2 run(s)" in listing.output and "unfinished" in listing.output and "stable" in listing.output
    folder = Path(next(line for line in res.output.splitlines() if line.startswith("run directory:")).split(": ")[1])
    shown = runner.invoke(app, ["runs", "show", folder.name[:22], "--runs-root", str(root)])
    assert shown.exit_code == 0, shown.output
    assert "verified yes" in shown.output and f"seed     {seed}" in shown.output
    ambiguous = runner.invoke(app, ["runs", "show", "particles-", "--runs-root", str(root)])
    assert ambiguous.exit_code == 2 and "fits 2 runs" in ambiguous.output
    asked = runner.invoke(app, ["runs", "prune", "--runs-root", str(root)], input="n\n")
    assert asked.exit_code == 1 and "nothing removed" in asked.output
    assert len([p for p in root.iterdir() if p.name != runs.QUARANTINE]) == 2
    pruned = runner.invoke(app, ["runs", "prune", "--yes", "--runs-root", str(root)])
    assert pruned.exit_code == 0 and "removed 1 folder(s)" in pruned.output, pruned.output
    assert [p.name for p in root.iterdir()] == [folder.name]
    bad = runner.invoke(app, ["runs", "prune", "--status", "all", "--runs-root", str(root)])
    assert bad.exit_code == 2 and "'--status'" in bad.output


def test_a_file_as_the_cache_folder_is_one_line(reference, tmp_path):
    spec, _ = reference
    (tmp_path / "file").write_text("x")
    with pytest.raises(StoreError, match="a folder on the way is a file"):
        runs.execute(spec, tmp_path / "file", quiet=True)


def test_strict_gpus_scheduler_and_scene_errors_of_study_commands(tmp_path):
    for args, needle in ((["demo", "--gpus", "\u00b2"], "'--gpus'"),
                         (["demo", "--scheduler", "tcp://h:8786\n"], "'--scheduler'"),
                         (["pbf-scaling", "--sizes", "3000000000"], "Error")):
        res = runner.invoke(app, [*args, "--out", str(tmp_path / "out")] if args[0] == "demo" else args)
        assert res.exit_code == 2, (args, res.output, res.exception)
        assert needle in res.output and "Traceback" not in res.output


# ---- fuzz: damaged cache files ------------------------------------------------------------------------------
def _nested(p: Path):
    p.write_text("[" * 50_000 + "]" * 50_000)


def _garbage(p: Path):
    p.write_bytes(os.urandom(64))


def _truncate(p: Path):
    p.write_bytes(p.read_bytes()[: max(0, p.stat().st_size // 2)])


def _as_dir(p: Path):
    p.unlink()
    p.mkdir()
    (p / "inside").write_text("x")


def _link_outside(p: Path):
    p.unlink()
    p.symlink_to(p.parents[2] / "outside.txt")


def _link_zero(p: Path):
    p.unlink()
    p.symlink_to("/dev/zero")


def _fifo(p: Path):
    p.unlink()
    os.mkfifo(p)


def _device(p: Path):
    p.unlink()
    _device_or_fifo(p)            # a character device where the machine lets us make one (root), else a FIFO


DAMAGES = {"nested": _nested, "garbage": _garbage, "truncate": _truncate, "dir": _as_dir,
           "link_outside": _link_outside, "link_dev_zero": _link_zero, "fifo": _fifo, "device": _device}
FINISHED_FILES = ["result.json", "config.json", "timings.csv", "steps.csv", "stats.parquet", "profiles.parquet",
                  "snapshots/step_000020.npz", "checkpoint.npz"]
UNFINISHED_FILES = ["progress.json", "checkpoint.npz", "partial/stats.json", "partial/steps.json",
                    "partial/profiles.json", "config.json", "snapshots/step_000000.npz"]


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(finished=st.booleans(), data=st.data(), damage=st.sampled_from(sorted(DAMAGES)))
def test_fuzzed_damaged_cache_files_give_the_right_result(reference, tmp_path_factory, alarm, finished, data, damage):
    spec, expected = reference
    root = tmp_path_factory.mktemp("fuzzcache")
    (root / "outside.txt").write_text("keep")
    if finished:
        runs.execute(spec, root / "runs", quiet=True)
        name = data.draw(st.sampled_from(FINISHED_FILES))
    else:
        with pytest.raises(Crash):
            runs.execute(spec, root / "runs", quiet=True, on_step=crash_at(12))
        name = data.draw(st.sampled_from(UNFINISHED_FILES))
    target = spec.directory(root / "runs") / name
    DAMAGES[damage](target)
    signal.alarm(20)
    result = runs.execute(spec, root / "runs", quiet=True)
    assert_same(comparable(result), expected)
    assert (root / "outside.txt").read_text() == "keep"
    assert runs.verify_run(result.path, spec.key(), memo=False) == []


def test_real_solver_resume_matches_in_every_column(tmp_path):
    pytest.importorskip("pbf_cuda._core")
    from pbf_cuda.scene import load_scene
    scene = load_scene("dam_break").with_particle_count(1000)
    spec = runs.RunSpec("particles", scene, backend="cpu", steps=60, snapshot_every=10, checkpoint_every=20,
                        record_steps=True)
    with pytest.raises(Crash):
        runs.execute(spec, tmp_path / "a", quiet=True, on_step=crash_at(25))
    resumed = runs.execute(spec, tmp_path / "a", quiet=True)
    straight = runs.execute(spec, tmp_path / "b", quiet=True)
    assert resumed.resumed_from == 20
    for name in ("stats", "steps_table"):
        a, b = getattr(resumed, name)(), getattr(straight, name)()
        assert [c for c in a.columns if c != "wall_ms" and not a[c].equals(b[c])] == [], name   # wall_ms: measured


def test_a_peer_sending_a_huge_frame_is_one_line(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    import socket
    import struct
    import threading
    from cloudpbf.studies import context
    from cloudpbf.studies.scales import resolve_scale
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            with conn:
                conn.sendall(struct.pack("<Q", 1 << 62) + b"x" * 64)     # "4 EiB follow"
                conn.recv(1024)
    threading.Thread(target=serve, daemon=True).start()
    monkeypatch.setattr(context, "SCHEDULER_TIMEOUT_S", 5.0)
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    ctx = context.StudyContext(out=tmp_path / "out", scale=resolve_scale("smoke"), scheduler=address)
    try:
        with pytest.raises(context.SchedulerError, match="does not answer as a dask scheduler") as err:
            ctx.client()
        assert "\n" not in str(err.value)
    finally:
        server.close()
