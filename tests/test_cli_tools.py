"""One CLI and installs that behave: --version, clean help, study subcommands with one list syntax,
plain progress lines off a terminal, Simulation.step(progress=...), the run cache location, the
missing-extra message, portable locking and XLA_FLAGS."""
from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from cloudpbf.cli import app

runner = CliRunner()
REPO = Path(__file__).resolve().parent.parent


def invoke(*args):
    return runner.invoke(app, list(args), catch_exceptions=False)


def test_version_is_the_package_metadata():
    res = invoke("--version")
    assert res.exit_code == 0
    assert res.output.strip() == f"cloudpbf {importlib.metadata.version('cloudpbf')}"


def test_version_needs_no_extra(monkeypatch, capsys):
    """The console script answers --version before importing the harness (typer, pandas, ...)."""
    from cloudpbf import console
    for name in ("cloudpbf.cli", "typer", "pandas"):
        monkeypatch.setitem(sys.modules, name, None)      # importing any of them now fails
    assert console.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"cloudpbf {importlib.metadata.version('cloudpbf')}"


@pytest.mark.parametrize("command", ["run", "export", "adaptive-cost", "constant-gravity", "pbf-scaling",
                                     "grid-scaling", "demo", "scaling", "budgets", "cbl"])
def test_help_has_no_escaped_brackets(command):
    res = invoke(command, "--help")
    assert res.exit_code == 0
    assert "\\[" not in res.output
    assert "[default: " in res.output or "[required]" in res.output


def test_every_study_is_a_subcommand():
    names = {c.name or c.callback.__name__ for c in app.registered_commands}
    assert {"adaptive-cost", "constant-gravity", "pbf-scaling", "grid-scaling", "export", "table1", "compare",
            "sweep", "stress", "scaling", "demo", "budgets", "cbl"} <= names
    # no study keeps a command line of its own (argparse) beside the cloudpbf one
    for module in sorted((REPO / "cloudpbf" / "studies").glob("*.py")):
        assert "argparse" not in module.read_text(), module.name


@pytest.mark.parametrize("args,expected", [
    (["constant-gravity", "--gravity", "0.1,abc"], "expected comma-separated floats"),
    (["constant-gravity", "--gravity", "0.1,500"], "'500.0': allowed range"),
    (["adaptive-cost", "--scenes", "growing_adaptive,nosuch"], "'--scenes': unknown scene 'nosuch'"),
    (["budgets", "--scene", "nosuch"], "'--scene': unknown scene 'nosuch'"),
    (["budgets", "--every", "0"], "Invalid value for '--every'"),
    (["cbl", "--times", "200;400"], "'--times': '200;400': expected comma-separated floats"),
    (["cbl", "--from-csv", "--out", "/nonexistent/cbl.csv"], "no such CSV to draw"),
    (["adaptive-cost", "--steps", "1"], "Invalid value for '--steps'"),
    (["pbf-scaling", "--sizes", "250000;1000000"], "expected comma-separated integers"),
    (["grid-scaling", "--dtypes", "float16"], "'float16': allowed float32, float64"),
    (["export", "/nonexistent/run", "--resolution", "4,4"], "expected three cell counts"),
])
def test_study_arguments_are_checked(args, expected):
    res = invoke(*args)
    assert res.exit_code == 2, res.output
    assert expected in " ".join(res.output.split())


def test_module_entry_points_forward_to_the_cli():
    """`python -m cloudpbf.studies.constant_gravity ...` is `cloudpbf constant-gravity ...` (same list syntax)."""
    out = subprocess.run([sys.executable, "-m", "cloudpbf.studies.constant_gravity", "--gravity", "0.1,x"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "comma-separated floats" in out.stderr
    out = subprocess.run([sys.executable, "-m", "cloudpbf.studies.cbl", "--times", "200,x"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "'--times'" in out.stderr and "comma-separated floats" in out.stderr


def _compiled():
    try:
        from pbf_cuda import simulation
        simulation._core()
    except ImportError:
        pytest.skip("compiled solver not built")


def test_pbf_scaling_subcommand_writes_its_csv(tmp_path):
    _compiled()
    out = tmp_path / "pbf.csv"
    res = invoke("pbf-scaling", "--sizes", "300,600", "--steps", "1", "--backend", "cpu", "--out", str(out),
                 "--runs-root", str(tmp_path / "runs"), "--quiet")
    assert res.exit_code == 0, res.output
    frame = pd.read_csv(out)
    assert len(frame) == 2 and frame["particles"].iloc[0] < frame["particles"].iloc[1]
    assert (frame["step_ms"] > 0).all() and frame["backend"].eq("cpu").all()


def test_step_progress_callable_gives_the_same_bits():
    _compiled()
    from pbf_cuda import Simulation, load_scene
    scene = load_scene("growing").with_particle_count(1500)
    a, b = Simulation(scene, backend="cpu", seed=4), Simulation(scene, backend="cpu", seed=4)
    a.step(7)
    calls = []
    b.step(7, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (7, 7) and all(t == 7 for _, t in calls)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    sa, sb = a.state(), b.state()
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k])
    with pytest.raises(TypeError):
        b.step(1, progress="yes")


def test_step_progress_true_prints_plain_lines_off_a_terminal(capfd, monkeypatch):
    _compiled()
    from pbf_cuda import Simulation, load_scene
    monkeypatch.delenv("CLOUDPBF_PROGRESS", raising=False)
    monkeypatch.setenv("CLOUDPBF_PROGRESS_INTERVAL", "0")
    sim = Simulation(load_scene("growing").with_particle_count(1000), backend="cpu", seed=1)
    sim.step(4, progress=True)
    err = capfd.readouterr().err
    assert "growing (cpu): 4/4 step (100%)" in err
    assert "\r" not in err                                  # lines, not a redrawn bar


def test_plain_progress_is_periodic(capsys):
    from cloudpbf_io.progress import PlainProgress, progress_bar
    bar = PlainProgress(total=100, desc="runs", unit="run", interval=3600, file=sys.stdout)
    for _ in range(100):
        bar.update(1)
    bar.close()
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 and lines[0].startswith("runs: 100/100 run (100%)")
    assert isinstance(progress_bar(total=3, disable=True), PlainProgress)


def test_cli_run_prints_progress_lines_when_piped(tmp_path):
    """`cloudpbf run ... | tee log`: stderr is no terminal, progress still shows as lines."""
    _compiled()
    env = {**os.environ, "CLOUDPBF_PROGRESS_INTERVAL": "0", "CLOUDPBF_RUNS": str(tmp_path / "runs")}
    env.pop("CLOUDPBF_PROGRESS", None)
    out = subprocess.run([sys.executable, "-m", "cloudpbf.cli", "run", "growing", "--particles", "1000", "--steps", "20"],
                         cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    assert "particles growing: 20/20 step (100%)" in out.stderr


def test_missing_harness_extra_names_the_extra():
    code = ("import sys; sys.modules['click'] = None; sys.modules['typer'] = None\n"
            "from cloudpbf.console import main; sys.exit(main(['--help']))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 1
    assert 'pip install "cloudpbf[harness]"' in out.stderr and "Traceback" not in out.stderr


def test_console_script_points_at_the_wrapper():
    eps = importlib.metadata.entry_points(group="console_scripts", name="cloudpbf")
    assert [ep.value for ep in eps] == ["cloudpbf.console:main"]


def test_run_cache_location(monkeypatch, tmp_path):
    from cloudpbf.store import identity
    monkeypatch.delenv("CLOUDPBF_RUNS", raising=False)
    assert identity.is_checkout() and identity.default_root() == identity.REPO_ROOT / "runs"
    fake = tmp_path / "lib" / "python3.11" / "site-packages"
    fake.mkdir(parents=True)
    (fake / "pyproject.toml").write_text("")            # even with one: site-packages is no checkout
    monkeypatch.setattr(identity, "REPO_ROOT", fake)
    monkeypatch.setattr(identity.is_checkout, "__defaults__", (fake,))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    root = identity.default_root()
    assert "site-packages" not in root.parts
    assert root == tmp_path / "cache" / "cloudpbf" / "runs"
    monkeypatch.setenv("CLOUDPBF_RUNS", str(tmp_path / "mine"))
    assert identity.default_root() == tmp_path / "mine"


@pytest.mark.parametrize("with_filelock", [True, False])
def test_run_lock_is_portable_and_exclusive(tmp_path, monkeypatch, with_filelock):
    from cloudpbf.store.lock import locked
    if not with_filelock:
        monkeypatch.setitem(sys.modules, "filelock", None)      # a bare machine: the POSIX fallback
    assert "\nimport fcntl" not in (REPO / "cloudpbf" / "store" / "lock.py").read_text()   # not at import time (Windows)
    order = []

    def hold():
        with locked(tmp_path):
            order.append("a-in")
            time.sleep(0.3)
            order.append("a-out")

    t = threading.Thread(target=hold)
    t.start()
    time.sleep(0.1)
    with locked(tmp_path):
        order.append("b-in")
    t.join()
    assert order == ["a-in", "a-out", "b-in"]


def test_environment_reports_the_cloudpbf_version():
    from cloudpbf.environment import versions
    assert versions()["cloudpbf"] == importlib.metadata.version("cloudpbf")


def test_xla_flags_are_ones_xla_accepts():
    pytest.importorskip("jax")
    from cloudpbf.studies.context import xla_single_thread_flags
    flags = xla_single_thread_flags("--xla_dump_to=/tmp/x intra_op_parallelism_threads=1")
    assert flags.split() == ["--xla_dump_to=/tmp/x", "--xla_cpu_multi_thread_eigen=false"]
    assert xla_single_thread_flags(flags) == flags
    env = {**os.environ, "XLA_FLAGS": xla_single_thread_flags(None)}
    out = subprocess.run([sys.executable, "-c", "import jax.numpy as j; print(float(j.arange(4.0).sum()))"],
                         capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0 and out.stdout.strip() == "6.0", out.stderr


# ---- CUDA architectures -----------------------------------------------------------------------------
def test_architecture_rules():
    from pbf_cuda.cuda_arch import parse_architectures, supports
    default = parse_architectures("75-real,80-real,86-real,89-real,90-real,90-virtual")
    assert supports(86, default) and supports(87, default)          # sm_86 SASS; sm_80 SASS runs on 8.7
    assert supports(100, default) and supports(120, default)        # Blackwell through the compute_90 PTX
    assert not supports(70, default) and not supports(61, default)  # V100 / GTX 10: no image
    sm90_only = parse_architectures("90")                           # the old default: sm_90 + compute_90
    assert not supports(86, sm90_only) and not supports(80, sm90_only) and supports(120, sm90_only)
    assert not supports(89, parse_architectures("90-real")) and not supports(100, parse_architectures("90-real"))
    assert supports(86, parse_architectures("native")) is None


def test_missing_kernel_image_is_named(monkeypatch):
    _compiled()
    from pbf_cuda import cuda_arch, simulation

    class FakeCore:
        @staticmethod
        def cuda_built(): return True
        @staticmethod
        def cuda_device_count(): return 1
        @staticmethod
        def cuda_device_capability(): return 61
        @staticmethod
        def cuda_device_name(): return "NVIDIA GeForce GTX 1080"
        @staticmethod
        def cuda_architectures(): return "75-real,90-real,90-virtual"

    monkeypatch.setattr(cuda_arch, "_core", lambda: FakeCore)
    assert simulation.available_backends() == ["cpu"]
    with pytest.raises(RuntimeError) as err:
        simulation._resolve_backend("cuda")
    msg = str(err.value)
    assert "NVIDIA GeForce GTX 1080" in msg and "6.1 (sm_61)" in msg and "75-real,90-real,90-virtual" in msg
    monkeypatch.setattr(FakeCore, "cuda_device_capability", staticmethod(lambda: 86))
    monkeypatch.setattr(FakeCore, "cuda_architectures", staticmethod(lambda: "80-real,90-virtual"))
    assert simulation.available_backends() == ["cpu", "cuda"]


def test_the_module_reports_its_architectures():
    _compiled()
    from pbf_cuda import _core
    built = _core.cuda_architectures()
    assert _core.cuda_built() or built == ""
    assert (_core.cuda_device_capability() >= 30) == (_core.cuda_device_count() > 0)


# ---- dependency ranges and the lock ---------------------------------------------------------------
def _requirements():
    import tomllib
    from packaging.requirements import Requirement
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in project["optional-dependencies"].values():
        reqs += [Requirement(r) for r in extra if not r.startswith("cloudpbf")]
    return reqs


def test_the_lock_satisfies_the_ranges():
    from packaging.utils import canonicalize_name
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[canonicalize_name(name)] = version.strip()
    for req in _requirements():
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not pinned in constraints.txt"
        assert req.specifier.contains(pins[name], prereleases=True), f"{name}=={pins[name]} outside {req}"


def test_the_ranges_include_the_versions_of_the_gpu_results():
    import json
    from packaging.utils import canonicalize_name
    used = json.loads((REPO / "reports" / "gpu" / "data" / "environment.json").read_text())["versions"]
    ranges = {canonicalize_name(r.name): r.specifier for r in _requirements()}
    for name in ("numpy", "pandas", "jax", "jaxlib", "scipy", "pyarrow", "matplotlib", "typer", "tqdm", "dask"):
        if used.get(name):
            assert ranges[canonicalize_name(name)].contains(used[name]), f"{name} {used[name]} not in {ranges[name]}"


def test_environment_is_checked_against_the_lock(tmp_path):
    from cloudpbf.environment import environment, lock_check
    lock = tmp_path / "constraints.txt"
    lock.write_text(f"# comment\nnumpy=={np.__version__}\npandas==0.0.1\nno-such-package==1.0\n")
    got = lock_check(lock)
    assert got["matches"] is False
    assert got["differs"] == {"pandas": {"locked": "0.0.1", "installed": pd.__version__},
                              "no-such-package": {"locked": "1.0", "installed": None}}
    assert lock_check(tmp_path / "missing.txt") is None
    env = environment("cpu", "cpu")
    assert env["lock"]["file"] == "constraints.txt"
    assert env["lock"]["matches"] == (env["lock"]["differs"] == {})
    assert env["lock"]["differs"].get("numpy") is None     # this environment's numpy is the locked one
