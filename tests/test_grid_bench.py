"""cloudpbf/grid_scaling.py: CSV format, appending, and the commit column without git."""
import csv

import pytest

pytest.importorskip("jax")
pytest.importorskip("jax_cfd")

from cloudpbf import grid_scaling  # noqa: E402


def test_writes_then_appends_rows(tmp_path):
    out = tmp_path / "reports" / "grid_scaling.csv"
    args = ["--sizes", "6", "--steps", "2", "--warmup", "0", "--devices", "cpu", "--out", str(out)]
    assert grid_scaling.main(args) == 0                 # python -m cloudpbf.grid_scaling: the CLI's grid-scaling
    from cloudpbf.cli import main
    assert main(["grid-scaling", "--sizes", "8"] + args[2:] + ["--commit", "abc1234"]) == 0
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == grid_scaling.COLUMNS
    assert [r[0] for r in rows[1:]] == ["216", "512"]
    for r in rows[1:]:
        assert float(r[1]) > 0 and r[2] == "float64" and r[3] == "cpu"
    assert rows[-1][4] == "abc1234"
    assert rows[1][4] == grid_scaling.git_commit()


def test_commit_unknown_without_git(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))          # no git binary on the PATH
    assert grid_scaling.git_commit() == "unknown"
    monkeypatch.undo()
    assert grid_scaling.git_commit(cwd=tmp_path) in ("unknown",)   # not a repository


def test_refuses_a_file_with_other_columns(tmp_path):
    out = tmp_path / "x.csv"
    out.write_text("a,b\n1,2\n")
    # through the CLI: a usage error (exit code 2) naming the file, nothing appended
    assert grid_scaling.main(["--sizes", "6", "--steps", "1", "--devices", "cpu", "--out", str(out)]) == 2
    assert out.read_text() == "a,b\n1,2\n"
    with pytest.raises(ValueError, match="has columns"):
        grid_scaling.run_grid_scaling([6], steps=1, devices="cpu", out=out)
