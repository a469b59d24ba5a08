"""`recon bench difficulty`: the azimuth-step sweep (rendered facade, stock vs ours)."""

from __future__ import annotations

import importlib.util
import json

import pytest

from recon.cli import main
from recon.eval.difficulty import step_deg


@pytest.mark.slow
def test_difficulty_sweep_rows_table_plot_and_reuse(tmp_path, capsys):
    """One wide step (4 views over +-80 deg: 53 deg apart): ours registers all four with a small
    GT rotation error, stock's row is recorded whatever it registers (none with pycolmap 4.2.1);
    a second call reuses the finished scene."""
    out = tmp_path / "d"
    args = ["bench", "difficulty", "--out", str(out), "--views", "4", "--max-azimuth", "80",
            "--stock-presets", "default", "--image-size", "640x480"]
    assert main(args) == 0
    data = json.loads((out / "difficulty.json").read_text())
    rows = {r["method"]: r for r in data["rows"]}
    assert set(rows) == {"stock-default", "ours"}
    assert all(abs(r["step_deg"] - step_deg(4, 80.0)) < 0.01 for r in rows.values())
    assert 0 <= rows["stock-default"]["registered"] <= rows["stock-default"]["images"] == 4  # recorded, not judged
    assert rows["ours"]["registered"] == rows["ours"]["images"] == 4
    assert rows["ours"]["rot_err_deg"] is not None and rows["ours"]["rot_err_deg"] < 1.0
    assert rows["ours"]["verified_pairs"] >= 3 and rows["ours"]["inliers_per_pair"] > 30
    text = capsys.readouterr()
    assert "Difficulty curve" in text.out and "53.3" in text.out
    if importlib.util.find_spec("matplotlib") is None:  # the bench extra (`make test` installs it)
        assert "plot: skipped" in text.out and not (out / "difficulty.png").exists()
    else:
        assert (out / "difficulty.png").stat().st_size > 10_000

    mtime = (out / "runs" / "facade-4x80" / "compare.json").stat().st_mtime_ns
    assert main(args) == 0
    assert "reusing" in capsys.readouterr().err
    assert (out / "runs" / "facade-4x80" / "compare.json").stat().st_mtime_ns == mtime
    assert json.loads((out / "difficulty.json").read_text())["rows"] == data["rows"]


def test_difficulty_bad_options_exit_2(tmp_path):
    assert main(["bench", "difficulty", "--out", str(tmp_path), "--views", "2"]) == 2
    assert main(["bench", "difficulty", "--out", str(tmp_path), "--views", "a,b"]) == 2
    assert main(["bench", "difficulty", "--out", str(tmp_path), "--image-size", "10x10"]) == 2
    assert not list(tmp_path.rglob("*.png"))
