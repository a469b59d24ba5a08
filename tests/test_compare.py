"""`recon compare` / `recon bench scenes` (recon.compare): stock COLMAP vs the extra-affine pipeline."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon.compare import GT_KEYS, compare_clouds, compare_scene, run_scenes

SIZE = (640, 480)  # facade-extreme at this size: stock default registers 0/4, ours 4/4


@pytest.fixture(scope="module")
def facade(tmp_path_factory) -> Path:
    from scenes.render import render_scene

    d = tmp_path_factory.mktemp("fx") / "facade-extreme"
    render_scene(d, "facade-extreme", seed=0, image_size=SIZE)
    return d


def test_compare_stock_fails_ours_succeeds_via_cli(facade, tmp_path, capsys):
    from recon.cli import main

    out = tmp_path / "cmp"
    assert main(["compare", str(facade), "--out", str(out), "--max-size", "640"]) == 0
    data = json.loads((out / "compare.json").read_text())
    stock, ours = data["stock"], data["extra_affine"]
    assert (out / "stock-default" / "report.json").is_file() and (out / "extra_affine" / "report.json").is_file()
    assert stock["status"] == "no_model" and stock["registered_images"] == 0 and stock["message"]
    assert ours["status"] == "ok" and ours["registered_images"] == 4 == ours["num_images"]
    for key in ("num_images", "registered_images", "num_points3D", "mean_track_length", "mean_reprojection_error",
                "seconds_total", "peak_mb", "stages", "verified_pairs", "inliers_per_pair_mean"):
        assert key in stock and key in ours, key
    assert ours["num_points3D"] > 0 and ours["verified_pairs"] > 0 and "match" in ours["stages"]
    # the renderer's COLMAP-text GT: every GT key present for both methods
    assert data["gt"]["format"] == "colmap"
    for key in GT_KEYS:
        assert key in stock and key in ours, key
    assert stock["auc_5"] == 0.0 and ours["auc_5"] > 0.5 and ours["rel_rot_err_deg_median"] < 2.0
    assert data["clouds"]["status"] == "skipped" and "stock" in data["clouds"]["message"]
    text = capsys.readouterr().out
    assert "extra_affine" in text and "stock-default" in text and "no_model" in text


def test_malformed_gt_warns_and_completes(facade, tmp_path):
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(facade, scene)
    bad = scene / "gt" / "images.txt"
    bad.write_text("1 this is not a pose\n", encoding="utf-8")
    warnings: list[str] = []
    res = compare_scene(scene, tmp_path / "out", max_size=640, on_warning=warnings.append)
    gt_warn = [w for w in warnings if "ground truth" in w]
    assert len(gt_warn) == 1 and str(bad) in gt_warn[0] and "\n" not in gt_warn[0]
    data = json.loads((tmp_path / "out" / "compare.json").read_text())
    assert data["gt"] is None and any(str(bad) in w for w in data["warnings"])
    assert data["extra_affine"]["num_images"] == 4 and "num_points3D" in data["extra_affine"]
    assert "rel_rot_err_deg_median" not in data["extra_affine"]
    assert res["stock"]["status"] == "no_model"


def _similarity(s: float, deg: float, t) -> tuple[float, np.ndarray, np.ndarray]:
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    return s, R, np.asarray(t, float)


def test_cloud_alignment_by_name_not_order():
    rng = np.random.default_rng(0)
    stock_pts = rng.uniform(-5, 5, (2000, 3))
    names = ["a.png", "b.png", "c.png", "d.png", "e.png"]
    stock_c = {n: rng.uniform(-10, 10, 3) for n in names}
    s, R, t = _similarity(0.3, 40.0, [1.0, -2.0, 0.5])  # ours = s R stock + t
    ours_pts = (s * (R @ stock_pts[:1500].T)).T + t  # ours sees 3/4 of the scene
    # ours registered the images in another order (other ids), misses one, has one stock lacks
    ours_c = {n: s * R @ stock_c[n] + t for n in reversed(names[:4])}
    ours_c["z.png"] = np.zeros(3)
    c = compare_clouds(stock_c, stock_pts, ours_c, ours_pts)
    assert c["status"] == "ok" and c["common_images"] == names[:4]
    assert c["alignment"]["scale"] == pytest.approx(1 / 0.3, rel=1e-6)
    assert c["dist_ours_to_stock_median"] < 1e-6 and c["completeness_ours"] == pytest.approx(1.0)
    assert c["completeness_stock"] == pytest.approx(0.75, abs=0.03)  # the quarter ours lacks is far
    assert c["rel_dist_ours_to_stock_p90"] < 1e-6 and c["extent"] > 10

    # pairing by position instead of name would be wrong: a shuffled name mapping misaligns
    wrong = dict(zip(names[:4], [ours_c[n] for n in ["b.png", "c.png", "d.png", "a.png"]]))
    c2 = compare_clouds(stock_c, stock_pts, wrong, ours_pts)
    assert c2["status"] == "ok" and c2["dist_ours_to_stock_median"] > 1e-3


def test_cloud_alignment_needs_three_common_images():
    c = compare_clouds({"a": np.zeros(3), "b": np.ones(3)}, np.ones((5, 3)),
                       {"a": np.zeros(3), "b": np.ones(3)}, np.ones((5, 3)))
    assert c["status"] == "skipped" and "3 images" in c["message"]


def test_bench_scenes_cli_and_errors(facade, tmp_path, capsys):
    from recon.cli import main

    root = facade.parent
    js = tmp_path / "scenes.json"
    assert main(["bench", "scenes", str(root), "--json", str(js), "--out", str(tmp_path / "o"),
                 "--max-size", "640"]) == 0
    data = json.loads(js.read_text())
    assert [Path(s["scene"]).name for s in data["scenes"]] == ["facade-extreme"]
    assert {r["method"] for r in data["rows"]} == {"stock-default", "extra_affine"}
    assert (tmp_path / "o" / "facade-extreme" / "compare.json").is_file()
    assert "facade-extreme" in capsys.readouterr().out
    # user errors: one line, exit 2
    assert main(["bench", "scenes", str(tmp_path / "nope")]) == 2
    assert main(["compare", str(facade), "--stock-preset", "bogus", "--out", str(tmp_path / "x")]) == 2
    assert main(["compare", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "no such folder" in err and "bogus" in err and "Traceback" not in err


def test_run_scenes_unknown_scene(facade):
    from recon.cli import UserError

    with pytest.raises(UserError, match="no scene"):
        run_scenes(facade.parent, facade.parent / "o", ["missing"])
