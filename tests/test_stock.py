"""`recon.eval.stock.run_stock`: COLMAP's own SIFT pipeline on a small real scene (4 photos of
fountain_P11 at 640 px, a few seconds), evaluated against the scene's Strecha ground truth."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from recon.eval.evaluate import evaluate_model
from recon.eval.gt import find_gt
from recon.eval.stock import run_stock
from shared_paths import SHARED_DATA as DATA

FOUNTAIN = DATA / "scenes" / "fountain_P11"
needs_fountain = pytest.mark.requires_shared("scenes/fountain_P11/images/0000.jpg", "scenes/fountain_P11/gt/cameras")
NAMES = ["0000.jpg", "0001.jpg", "0002.jpg", "0003.jpg"]
REPORT_KEYS = {"status", "message", "num_images", "registered_images", "num_points3D", "mean_track_length",
               "mean_reprojection_error", "seconds_total", "peak_mb", "stages", "pairs", "skipped", "tracks",
               "warnings", "config", "sfm_options", "verified_pairs", "inliers_per_pair_mean", "method", "preset"}


def small_fountain(root: Path, names=NAMES) -> Path:
    """A scene folder of symlinks to a few fountain photos, with their GT .camera files copied."""
    (root / "images").mkdir(parents=True)
    (root / "gt" / "cameras").mkdir(parents=True)
    for n in names:
        (root / "images" / n).symlink_to(FOUNTAIN / "images" / n)
        shutil.copy(FOUNTAIN / "gt" / "cameras" / f"{n}.camera", root / "gt" / "cameras")
    return root


@pytest.mark.slow
@needs_fountain
def test_stock_default_small_fountain(tmp_path):
    scene = small_fountain(tmp_path / "scene")
    out = tmp_path / "out"
    r = run_stock(scene, out, max_size=640, seed=0).to_dict()
    assert r["status"] == "ok", r["message"]
    assert REPORT_KEYS <= set(r)
    assert r["registered_images"] >= 3 and r["num_points3D"] > 100
    assert r["mean_track_length"] > 2.0 and r["mean_reprojection_error"] < 2.0
    assert len(r["pairs"]) == 6 and r["verified_pairs"] >= 3 and r["inliers_per_pair_mean"] > 50
    assert set(r["stages"]) >= {"load", "database", "features", "match", "sfm"}
    # COLMAP keeps two orientations of one point as two keypoints: some inliers repeat a correspondence
    verified = [p for p in r["pairs"] if p["verified_inliers"] > 0]
    assert all(0 < p["distinct_inliers"] <= p["verified_inliers"] for p in verified)
    assert sum(p["distinct_inliers"] for p in verified) < 0.97 * sum(p["verified_inliers"] for p in verified)
    assert r["distinct_inliers_per_pair_mean"] == pytest.approx(np.mean([p["distinct_inliers"] for p in verified]))
    assert r["peak_mb"] > 0 and r["colmap_options"]["extraction"]["max_image_size"] == 640
    # outputs, and report.json holds the same dict
    assert (out / "database.db").is_file() and (out / "sparse" / "0").is_dir()
    assert json.loads((out / "report.json").read_text())["registered_images"] == r["registered_images"]
    # one camera, one rig and one frame per image: extraction reused recon's imported images
    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        assert db.num_images() == 4 and db.num_frames() == 4 and db.num_cameras() == 1
        assert db.num_verified_image_pairs() == r["verified_pairs"]
    finally:
        db.close()
    # the model agrees with the GT (Strecha convention, matched by name)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    ev = evaluate_model(rec, find_gt(scene))
    assert ev["num_registered_with_gt"] == r["registered_images"]
    assert ev["rel_rot_err_deg_median"] < 2.0 and ev["auc_10"] > 0.5
    assert ev["center_err_rel_median"] < 0.05


@pytest.mark.slow
@needs_fountain
@pytest.mark.requires_shared("oxford/graf/img1.png")
def test_stock_pairs_file_and_no_model(tmp_path):
    """Explicit pairs go through COLMAP's imported pairs list (same pairs as recon run); a
    scene without any usable pair gives status no_model and never raises."""
    scene = small_fountain(tmp_path / "scene", NAMES[:3])
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("0000.jpg 0001.jpg\n# comment\n0001.jpg 0002.jpg\nmissing.jpg 0000.jpg\n")
    out = tmp_path / "out"
    r = run_stock(scene, out, pairs=str(pairs), max_size=480).to_dict()
    assert [(p["image0"], p["image1"]) for p in r["pairs"]] == [("0000.jpg", "0001.jpg"), ("0001.jpg", "0002.jpg")]
    assert any("missing.jpg" in w for w in r["warnings"])
    assert (out / "pairs.txt").read_text().split("\n")[:2] == ["0000.jpg 0001.jpg", "0001.jpg 0002.jpg"]
    assert r["status"] == "ok" and r["registered_images"] >= 3

    # only one usable pair, of unrelated images: no model, a report saying so
    other = tmp_path / "unrelated" / "images"
    other.mkdir(parents=True)
    (other / "a.jpg").symlink_to(FOUNTAIN / "images" / "0000.jpg")
    graf = DATA / "oxford" / "graf" / "img1.png"
    if not graf.is_file():
        pytest.skip("oxford/graf not found")
    (other / "b.png").symlink_to(graf)
    r2 = run_stock(other.parent, tmp_path / "out2", max_size=480).to_dict()
    assert r2["status"] == "no_model" and r2["registered_images"] == 0 and r2["message"]
    assert (tmp_path / "out2" / "report.json").is_file() and not (tmp_path / "out2" / "sparse").exists()


def test_stock_bad_arguments(tmp_path):
    """The same error contract as `recon run`: unusable input raises a user error (one line in
    the CLI), a scene without a model returns a report (see test_stock_pairs_file_and_no_model)."""
    from matching.errors import InputError
    from recon.errors import UserError

    with pytest.raises(UserError, match="preset"):
        run_stock(tmp_path, tmp_path / "o", preset="ultra")  # type: ignore[arg-type]
    with pytest.raises(InputError):
        run_stock(tmp_path / "nope", tmp_path / "o")
    # a folder with one image: a user error, as for recon run
    (tmp_path / "one").mkdir()
    img = np.full((100, 120), 128, np.uint8)
    import cv2

    cv2.imwrite(str(tmp_path / "one" / "a.png"), img)
    with pytest.raises(UserError, match="at least 2"):
        run_stock(tmp_path / "one", tmp_path / "o")
