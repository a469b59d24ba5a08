"""SIFT descriptors in the database (recon.core.descriptors): COLMAP's storage form, one row per
merged keypoint, and COLMAP's own matcher finding verified matches with them."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pycolmap

from recon.core.descriptors import colmap_sift_u8, sift_descriptors


def test_colmap_storage_form_is_l1_root_times_512():
    d = np.zeros((2, 128), np.float32)
    d[0, :4] = [4.0, 4.0, 4.0, 4.0]  # L1-root: sqrt(1/4) = 0.5 each -> 256 -> clipped to 255
    d[1, :] = 1.0  # sqrt(1/128) * 512 = 45.25 -> 45
    u8 = colmap_sift_u8(d)
    assert u8.dtype == np.uint8 and u8.shape == (2, 128)
    assert (u8[0, :4] == 255).all() and not u8[0, 4:].any() and (u8[1] == 45).all()


def test_descriptors_follow_the_keypoints_snapped_or_upright(corner_scene):
    """Keypoints on SIFT detections take those descriptors; others get upright ones; one row each."""
    gray = cv2.imread(str(sorted((corner_scene / "images").iterdir())[0]), cv2.IMREAD_GRAYSCALE)
    sift = cv2.SIFT_create()
    det, desc = sift.detectAndCompute(gray, None)
    on = np.array([d.pt for d in det[:50]], np.float32)
    off = np.array([[5.5, 7.25], [100.0, 100.0]], np.float32)  # probably no detection this close
    kpts = np.vstack([on, off])
    u8, stats = sift_descriptors(gray, kpts, (1.0, 1.0))
    assert u8.shape == (52, 128) and stats.snapped + stats.upright == 52 and stats.snapped >= 50
    # a snapped keypoint carries a detection's descriptor (the nearest, possibly a twin at the same point)
    same_point = [i for i, d in enumerate(det) if np.hypot(*(np.subtract(d.pt, det[0].pt))) < 1e-6]
    assert any((u8[0] == colmap_sift_u8(desc[i:i + 1])[0]).all() for i in same_point)
    assert u8[-1].any()  # the upright descriptor at (100, 100) is not empty
    empty, st = sift_descriptors(gray, np.zeros((0, 2), np.float32), (1.0, 1.0))
    assert empty.shape == (0, 128) and st.snapped == st.upright == 0


def test_descriptors_from_the_feature_stores_detections_are_the_same(corner_scene):
    """The database stage hands over the store's default-SIFT set of the original (the reference
    decision's) instead of detecting again: the same rows, at half resolution too."""
    from matching.features import DetectorConfig
    from matching.store import FeatureStore
    from matching.viewfeatures import original_features

    gray = cv2.imread(str(sorted((corner_scene / "images").iterdir())[1]), cv2.IMREAD_GRAYSCALE)
    store = FeatureStore()
    store.add_image("a", gray)
    det = original_features(store, "a", DetectorConfig("sift"))
    rng = np.random.default_rng(0)
    near = det.kpts[::5] + rng.normal(0.0, 0.8, (len(det.kpts[::5]), 2)).astype(np.float32)
    kpts_full = (np.vstack([near, rng.random((80, 2), np.float32) * gray.shape[::-1]]) + 0.5) * 2.0 - 0.5
    detected, s0 = sift_descriptors(gray, kpts_full, (0.5, 0.5))
    handed, s1 = sift_descriptors(gray, kpts_full, (0.5, 0.5), det)
    assert s0 == s1 and s0.snapped > 0 and s0.upright > 0
    np.testing.assert_array_equal(handed, detected)


def test_colmap_matches_the_database_with_its_own_matcher(corner_sift_run, tmp_path):
    """The run's database holds one SIFT descriptor per keypoint; with our matches removed,
    COLMAP's exhaustive matcher (its own descriptor matching and verification) finds verified
    matches again from those descriptors alone."""
    out, rep, _ = corner_sift_run
    db_path = tmp_path / "db.db"
    shutil.copyfile(out / "database.db", db_path)
    db = pycolmap.Database.open(str(db_path))
    try:
        for im in db.read_all_images():
            assert db.num_descriptors_for_image(im.image_id) == db.read_keypoints(im.image_id).shape[0] > 100
        db.clear_matches()
        db.clear_two_view_geometries()
    finally:
        db.close()
    pycolmap.match_exhaustive(str(db_path), device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(db_path))
    try:
        _, geoms = db.read_two_view_geometries()
    finally:
        db.close()
    inliers = sorted((len(g.inlier_matches) for g in geoms), reverse=True)
    assert len(inliers) >= 3 and inliers[0] >= 100, inliers
