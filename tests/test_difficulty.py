"""`recon bench difficulty`: the azimuth-step sweep (rendered facade, stock vs ours)."""

from __future__ import annotations

import importlib.util
import json

import pytest

from recon.cli import main
from recon.eval.difficulty import _scene, baseline_table, by_baseline, step_deg


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
    # correct (within sqrt(3) px of the exact transfer through the rendered planes): most, not all
    assert 0.6 * rows["ours"]["distinct_per_pair"] < rows["ours"]["correct_per_pair"] <= rows["ours"]["distinct_per_pair"]
    assert rows["ours"]["correct_median_px"] < 0.5  # the right matches lie well inside the 1.7 px threshold
    seps = [b["separation_deg"] for b in rows["ours"]["by_baseline"]]  # 6 pairs: 3 neighbours, 2 at two steps, 1 at three
    assert seps == [round(k * step_deg(4, 80.0), 2) for k in (1, 2, 3)]
    assert [b["pairs"] for b in rows["ours"]["by_baseline"]] == [3, 2, 1]
    text = capsys.readouterr()
    assert "Difficulty curve" in text.out and "53.3" in text.out and "by azimuth separation" in text.out
    if importlib.util.find_spec("matplotlib") is None:  # the bench extra (`make test` installs it)
        assert "plot: skipped" in text.out and not (out / "difficulty.png").exists()
    else:
        assert (out / "difficulty.png").stat().st_size > 10_000

    mtime = (out / "runs" / "facade-4x80" / "compare.json").stat().st_mtime_ns
    assert main(args) == 0
    assert "reusing" in capsys.readouterr().err
    assert (out / "runs" / "facade-4x80" / "compare.json").stat().st_mtime_ns == mtime
    assert json.loads((out / "difficulty.json").read_text())["rows"] == data["rows"]


def test_scene_reuse_checks_textures(tmp_path):
    """A finished render is reused only for the same seed, size and textures: photo-textured and
    procedural renders of one preset under one name replace each other, and the images differ."""
    import cv2
    import numpy as np

    photo = tmp_path / "photo.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(photo), cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (0, 0), 1.5))
    size = (160, 120)
    d, made = _scene(tmp_path, "corner-wide", 0, size, lambda m: None, name="s")
    assert made
    procedural = cv2.imread(str(d / "images" / "view_00.png"))
    assert _scene(tmp_path, "corner-wide", 0, size, lambda m: None, name="s") == (d, False)
    assert _scene(tmp_path, "corner-wide", 0, size, lambda m: None, name="s", textures=[photo]) == (d, True)
    textured = cv2.imread(str(d / "images" / "view_00.png"))
    assert procedural.shape == textured.shape and np.abs(procedural.astype(int) - textured).mean() > 5
    assert _scene(tmp_path, "corner-wide", 0, size, lambda m: None, name="s", textures=[photo]) == (d, False)
    assert _scene(tmp_path, "corner-wide", 0, size, lambda m: None, name="s") == (d, True)


def test_difficulty_bad_options_exit_2(tmp_path):
    assert main(["bench", "difficulty", "--out", str(tmp_path), "--views", "2"]) == 2
    assert main(["bench", "difficulty", "--out", str(tmp_path), "--views", "a,b"]) == 2
    assert main(["bench", "difficulty", "--out", str(tmp_path), "--image-size", "10x10"]) == 2
    assert main(["bench", "difficulty", "--out", str(tmp_path / "t"), "--texture", str(tmp_path / "no.jpg")]) == 2
    assert not (tmp_path / "t").exists()
    assert not list(tmp_path.rglob("*.png"))


def test_by_baseline_groups_pairs_by_separation_and_skips_unverified_in_the_means():
    """Views named in azimuth order: (a, b) and (b, c) are neighbours, (a, c) two steps apart;
    an unverified neighbour pair counts in `pairs` but not in the means."""
    pairs = [{"image0": "view_00.png", "image1": "view_01.png", "verified_inliers": 300, "distinct_inliers": 250},
             {"image0": "view_02.png", "image1": "view_01.png", "verified_inliers": 100, "distinct_inliers": 90},
             {"image0": "view_00.png", "image1": "view_02.png", "verified_inliers": 40, "distinct_inliers": 40},
             {"image0": "view_02.png", "image1": "view_03.png", "verified_inliers": 0, "distinct_inliers": 0}]
    rows = by_baseline(pairs, 26.0)
    assert [r["separation_deg"] for r in rows] == [26.0, 52.0]
    assert (rows[0]["pairs"], rows[0]["verified_pairs"]) == (3, 2)
    assert rows[0]["inliers_per_pair"] == 200.0 and rows[0]["distinct_per_pair"] == 170.0
    assert (rows[1]["inliers_per_pair"], rows[1]["distinct_per_pair"]) == (40.0, 40.0)
    assert by_baseline([], 13.0) == []

    from rich.console import Console

    data = {"rows": [{"views": 4, "method": "ours", "by_baseline": rows},
                     {"views": 4, "method": "stock-high", "by_baseline": by_baseline(pairs[:1], 26.0)}]}
    console = Console(width=120, record=True)
    console.print(baseline_table(data))
    text = console.export_text()
    assert "200 (170)" in text and "300 (250)" in text and "40 (40)" in text
