"""`recon compare` / `recon bench scenes` (recon.eval.compare): stock COLMAP vs the extra-affine pipeline."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon.eval.compare import GT_KEYS, compare_clouds, compare_scene, run_scenes, scene_rows

SIZE = (640, 480)  # facade-extreme at this size: ours registers 4/4 (stock default 0/4 with pycolmap 4.2.1)


@pytest.fixture()
def facade(facade_extreme_scene) -> Path:
    """facade-extreme at SIZE, alone in its parent folder, rendered once per session (conftest)."""
    return facade_extreme_scene


@pytest.mark.slow
def test_compare_via_cli_ours_registers_every_image_stock_recorded(facade, tmp_path, capsys):
    from recon.cli import main

    out = tmp_path / "cmp"
    assert main(["compare", str(facade), "--out", str(out), "--max-size", "640"]) == 0
    data = json.loads((out / "compare.json").read_text())
    stock, ours = data["stock"], data["extra_affine"]
    assert (out / "stock-default" / "report.json").is_file() and (out / "extra_affine" / "report.json").is_file()
    # stock's outcome is recorded, not asserted (a newer COLMAP may register this scene)
    stock_ok = stock["status"] == "ok"
    assert stock["status"] in ("ok", "no_model") and stock_ok == (stock["registered_images"] > 0)
    assert stock_ok or stock["message"]
    assert ours["status"] == "ok" and ours["registered_images"] == 4 == ours["num_images"]
    for key in ("num_images", "registered_images", "num_points3D", "mean_track_length", "mean_reprojection_error",
                "seconds_total", "peak_mb", "stages", "verified_pairs", "inliers_per_pair_mean"):
        assert key in stock and key in ours, key
    assert ours["num_points3D"] > 0 and ours["verified_pairs"] > 0 and "match" in ours["stages"]
    # the renderer's COLMAP-text GT: every GT key present for both methods
    assert data["gt"]["format"] == "colmap"
    for key in GT_KEYS:
        assert key in stock and key in ours, key
    assert stock_ok or stock["auc_5"] == 0.0
    assert ours["auc_5"] > 0.5 and ours["rel_rot_err_deg_median"] < 2.0
    # a rendered scene: the verified correspondences checked against the exact transfer
    assert 0.6 * ours["distinct_inliers_per_pair_mean"] < ours["correct_per_pair"] <= ours["distinct_inliers_per_pair_mean"]
    assert (stock["correct_per_pair"] is not None) == (stock["verified_pairs"] > 0)
    assert ours["correct_median_px"] < 0.5
    assert stock_ok or (data["clouds"]["status"] == "skipped" and "stock" in data["clouds"]["message"])
    text = capsys.readouterr().out
    assert "extra_affine" in text and "stock-default" in text and stock["status"] in text
    assert "correct (rendered truth)" in text and "their median error px" in text
    cols = _columns(out / "compare.rrd")  # the default sink: both runs in one recording
    assert "Points3D:positions" in cols["/world/extra_affine/points"]
    assert any(k.startswith("/world/stock-default/") for k in cols) == stock_ok  # stock logged iff it has a model
    assert "TextDocument:text" in cols["/summary"]
    from recon.cli.view import resolve_recording

    assert resolve_recording(out) == out / "compare.rrd"  # `recon view OUT` finds it


def _columns(rrd: Path) -> dict[str, set[str]]:
    from rerun.chunk import RrdReader

    cols: dict[str, set[str]] = {}
    for c in RrdReader(rrd).stream().to_chunks():
        cols.setdefault(str(c.entity_path), set()).update(c.to_record_batch().schema.names)
    return cols


def _logged_centres(rrd: Path, prefix: str) -> dict[str, np.ndarray]:
    """{image name: camera centre} of the cameras logged under `prefix`/cameras/<name>."""
    from rerun.chunk import RrdReader

    out = {}
    for c in RrdReader(rrd).stream().to_chunks():
        path = str(c.entity_path)
        names = c.to_record_batch().schema.names
        if path.startswith(f"{prefix}/cameras/") and path.count("/") == prefix.count("/") + 2 \
                and "Transform3D:translation" in names:
            b = c.to_record_batch()
            t = np.asarray(b.column("Transform3D:translation").to_pylist()[0], np.float64).reshape(3)
            R = np.asarray(b.column("Transform3D:mat3x3").to_pylist()[0], np.float64).reshape(3, 3).T  # column-major
            out[path.rsplit("/", 1)[1]] = -R.T @ t
    return out


@pytest.mark.slow
def test_compare_recording_aligns_every_model_to_the_ground_truth(facade, tmp_path):
    """--stock-preset high (which registers this scene) and ours, logged in the GT frame: each
    model's logged camera centres land on the GT centres."""
    from recon.cli import main
    from recon.eval.gt import find_gt

    out = tmp_path / "cmp-high"
    rrd = tmp_path / "c.rrd"
    assert main(["compare", str(facade), "--out", str(out), "--max-size", "640", "--stock-preset", "high",
                 "--rerun", f"save:{rrd}"]) == 0
    assert not (out / "compare.rrd").exists()  # the recording went where it was asked
    gt = find_gt(facade)
    gt_c = {n: -g.cam_from_world[:, :3].T @ g.cam_from_world[:, 3] for n, g in gt.items()}
    extent = max(np.linalg.norm(a - b) for a in gt_c.values() for b in gt_c.values())
    logged_gt = _logged_centres(rrd, "/world/gt")
    assert set(logged_gt) == set(gt_c)
    for n in gt_c:
        np.testing.assert_allclose(logged_gt[n], gt_c[n], atol=1e-6 * extent)
    for method in ("extra_affine", "stock-high"):
        centres = _logged_centres(rrd, f"/world/{method}")
        assert len(centres) == 4, method
        err = max(np.linalg.norm(centres[n] - gt_c[n]) for n in centres)
        assert err < 0.02 * extent, (method, err, extent)


@pytest.mark.slow
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
    assert data["extra_affine"]["correct_per_pair"] is None  # no readable poses, no exact transfer
    assert res["stock"]["status"] in ("ok", "no_model")  # recorded, whatever stock makes of this scene


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


@pytest.mark.slow
def test_bench_scenes_cli_and_errors(facade, tmp_path, capsys):
    from recon.cli import main

    root = facade.parent
    js = tmp_path / "scenes.json"
    assert main(["bench", "scenes", str(root), "--json", str(js), "--out", str(tmp_path / "o"),
                 "--max-size", "640", "--simulate", "needed"]) == 0
    data = json.loads(js.read_text())
    assert [Path(s["scene"]).name for s in data["scenes"]] == ["facade-extreme"]
    assert {r["method"] for r in data["rows"]} == {"stock-default", "extra_affine"}
    assert (tmp_path / "o" / "facade-extreme" / "compare.json").is_file()
    ours = json.loads((tmp_path / "o" / "facade-extreme" / "extra_affine" / "report.json").read_text())
    assert ours["config"]["match"]["simulate"] == "needed"  # --simulate reached our run
    assert ours["pairs_simulated"] >= 5 and ours["registered_images"] == 4  # grazing pairs: simulated where weak
    assert "facade-extreme" in capsys.readouterr().out
    # user errors: one line, exit 2
    assert main(["bench", "scenes", str(tmp_path / "nope")]) == 2
    assert main(["compare", str(facade), "--stock-preset", "bogus", "--out", str(tmp_path / "x")]) == 2
    assert main(["compare", str(tmp_path / "nope")]) == 2
    assert main(["compare", str(facade), "--simulate", "sometimes", "--out", str(tmp_path / "y")]) == 2
    assert not (tmp_path / "y").exists()  # refused before anything was created
    err = capsys.readouterr().err
    assert "no such folder" in err and "bogus" in err and "--simulate 'sometimes'" in err and "Traceback" not in err


def test_scene_rows_name_each_row_by_its_own_scene():
    """The JSON rows of a multi-scene benchmark: each method row carries its own scene's name
    (they all carried the last scene's before)."""
    results = [{"scene": "/data/scenes/fountain",
                "methods": {"stock-default": {"method": "stock-default", "points": 1},
                            "extra_affine": {"method": "extra_affine", "points": 2}}},
               {"scene": "/data/scenes/sacre", "methods": {"extra_affine": {"method": "extra_affine", "points": 3}}}]
    rows = scene_rows(results)
    assert [(r["scene"], r["method"], r["points"]) for r in rows] == [
        ("fountain", "stock-default", 1), ("fountain", "extra_affine", 2), ("sacre", "extra_affine", 3)]
    assert "scene" not in results[0]["methods"]["extra_affine"]  # the results themselves are not changed


@pytest.mark.slow
def test_run_scenes_unknown_scene(facade):
    from recon.errors import UserError

    with pytest.raises(UserError, match="no scene"):
        run_scenes(facade.parent, facade.parent / "o", ["missing"])


@pytest.mark.slow
def test_compare_scene_applies_settings_to_ours_and_mapping_settings_to_both(facade, tmp_path):
    """`settings` (`recon run --set` strings; bench_scenes' --set) reach our run's config and the
    comparison's record, and the `sfm.*` ones stock's too (both map the same way); a bad one is
    a UserError before anything runs."""
    from recon.errors import UserError

    with pytest.raises(UserError):
        compare_scene(facade, tmp_path / "bad", settings=["matcher.adaptive"])
    assert not (tmp_path / "bad" / "extra_affine").exists()
    settings = ["matcher.adaptive=true", "sfm.final_ba_loss=none"]
    res = compare_scene(facade, tmp_path / "o", max_size=SIZE[0], settings=settings)
    assert res["config"]["settings"] == settings
    ours = json.loads((tmp_path / "o" / "extra_affine" / "report.json").read_text())
    stock = json.loads((tmp_path / "o" / "stock-default" / "report.json").read_text())
    assert ours["config"]["match"]["matcher"] == {"adaptive": True}
    assert stock["config"]["match"]["matcher"] == {}
    off = {"loss": "none", "applied": False}
    assert ours["config"]["sfm"]["final_ba_loss"] == stock["config"]["sfm"]["final_ba_loss"] == "none"
    assert ours["final_ba"] == off and stock["final_ba"] == (off if stock["registered_images"] else {})
    assert {p["path"] for p in ours["pairs"]} <= {"originals", "targeted", "full"}
    assert not any(p["path_reason"].startswith("adaptive off") for p in ours["pairs"])
