"""COLMAP database round trip (recon.core.database): cameras, keypoints (+0.5), matches, atomic build;
and a scene from `pycolmap.synthesize_dataset` through our writer, COLMAP's verification and our mapper."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from recon.core.database import (
    build_database,
    database_is_sound,
    database_problem,
    estimate_database_bytes,
    import_scene_images,
    read_keypoints_opencv,
    read_verified,
    require_free_space,
    two_view_options,
    write_keypoints_and_matches,
)


def _write_images(d: Path, sizes) -> list[str]:
    d.mkdir(parents=True, exist_ok=True)
    names = []
    for i, (w, h) in enumerate(sizes):
        rng = np.random.default_rng(i)
        img = cv2.resize(rng.integers(0, 255, (h // 8, w // 8, 3), dtype=np.uint8), (w, h))
        name = f"im {i}.png"
        (d / name).write_bytes(cv2.imencode(".png", img)[1].tobytes())
        names.append(name)
    return names


def test_round_trip_keypoints_plus_half_and_matches(tmp_path):
    names = _write_images(tmp_path / "images", [(160, 120)] * 3)
    db_path = tmp_path / "database.db"
    ids, mode, missing = import_scene_images(db_path, tmp_path / "images", names, "auto")
    assert mode == "single" and not missing and sorted(ids) == sorted(names)
    rng = np.random.default_rng(0)
    kpts = {n: rng.uniform(0, 100, (50 + 10 * i, 2)).astype(np.float32) for i, n in enumerate(names)}
    pairs = [(names[0], names[1]), (names[2], names[1])]  # second pair: larger id first
    matches = [np.stack([np.arange(20), np.arange(20) + 5], 1).astype(np.uint32),
               np.stack([np.arange(30), np.arange(30)[::-1]], 1).astype(np.uint32)]
    write_keypoints_and_matches(db_path, ids, kpts, pairs, matches)

    db = pycolmap.Database.open(str(db_path))
    try:
        assert db.num_images() == 3 and db.num_cameras() == 1
        for n in names:
            k = db.read_keypoints(ids[n])
            assert k.shape[0] == len(kpts[n])
            np.testing.assert_allclose(k[:, :2], kpts[n] + 0.5, atol=1e-5)  # COLMAP pixel centres
        m01 = db.read_matches(ids[names[0]], ids[names[1]])
        np.testing.assert_array_equal(m01, matches[0])
        m21 = db.read_matches(ids[names[2]], ids[names[1]])  # read in the order written
        np.testing.assert_array_equal(m21, matches[1])
        cams = db.read_all_cameras()
        assert (cams[0].width, cams[0].height) == (160, 120)
    finally:
        db.close()
    np.testing.assert_allclose(read_keypoints_opencv(db_path, ids[names[1]]), kpts[names[1]], atol=1e-5)


def test_camera_modes(tmp_path):
    names = _write_images(tmp_path / "images", [(160, 120), (160, 120), (200, 120)])
    for mode, want_mode, want_cams in (("auto", "per-image", 3), ("per-image", "per-image", 3)):
        db_path = tmp_path / f"{mode}.db"
        ids, used, missing = import_scene_images(db_path, tmp_path / "images", names, mode)
        assert used == want_mode and not missing
        db = pycolmap.Database.open(str(db_path))
        assert db.num_cameras() == want_cams
        db.close()
    with pytest.raises(ValueError):
        import_scene_images(tmp_path / "x.db", tmp_path / "images", names, "bogus")


def test_build_is_atomic_and_verifies(tmp_path):
    names = _write_images(tmp_path / "images", [(320, 240)] * 2)
    # matches consistent with a real two-view geometry: random 3D points seen by two cameras
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(4, 6, 200)]
    K = np.array([[300, 0, 159.5], [0, 300, 119.5], [0, 0, 1.0]])
    R = cv2.Rodrigues(np.array([0, 0.15, 0.0]))[0]
    t = np.array([-0.8, 0, 0.1])
    p0 = (K @ X.T).T
    p1 = (K @ (R @ X.T + t[:, None])).T
    k0 = (p0[:, :2] / p0[:, 2:]).astype(np.float32)
    k1 = (p1[:, :2] / p1[:, 2:]).astype(np.float32)
    m = np.stack([np.arange(200), np.arange(200)], 1).astype(np.uint32)
    m[180:, 1] = rng.permutation(np.arange(180, 200))  # 20 wrong matches
    db_path = tmp_path / "database.db"
    db_path.write_bytes(b"old content")
    ids, used, missing = build_database(db_path, tmp_path / "images", names, "auto", {names[0]: k0, names[1]: k1},
                                        [(names[0], names[1])], [m], two_view_options(seed=0))
    assert not (tmp_path / "database.db.tmp").exists() and not missing
    verified = read_verified(db_path)
    (n_in, conf, inl), = verified.values()
    assert 170 <= n_in <= 185 and conf in ("CALIBRATED", "UNCALIBRATED")
    assert np.all(inl[inl[:, 0] < 180, 0] == inl[inl[:, 0] < 180, 1])
    assert np.count_nonzero(inl[:, 0] != inl[:, 1]) <= 4  # a wrong match may lie on its epipolar line
    assert np.count_nonzero(inl[:, 0] < 180) >= 175

    # a failing build leaves the existing database untouched and no temp file behind
    before = db_path.read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        build_database(db_path, tmp_path / "images", names, "auto", {}, [], [], two_view_options(),
                       on_stage=lambda s: (_ for _ in ()).throw(RuntimeError("boom")) if s == "write" else None)
    assert db_path.read_bytes() == before
    assert not (tmp_path / "database.db.tmp").exists()


# a synthesized scene through our database writer, COLMAP's verification and our mapper ---------------
def _synthetic_scene(root: Path, num_frames: int = 5, num_points3D: int = 150):
    """pycolmap.synthesize_dataset's truth (one 640 x 480 camera, f = 600 px) as recon hands it to
    the database: blank images of the right size, keypoints in OpenCV's convention (COLMAP's
    minus 0.5) and, per pair, the matches of the points both images see.
    Returns (truth, image dir, names, {name: keypoints}, pairs, matches)."""
    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, num_frames, num_points3D
    o.camera_width, o.camera_height = 640, 480
    o.camera_params = [600.0, 320.0, 240.0, 0.0]
    gt = pycolmap.synthesize_dataset(o)
    image_dir = root / "images"
    image_dir.mkdir(parents=True)
    images = sorted(gt.images.values(), key=lambda im: im.name)
    names = [im.name for im in images]
    kpts, point_ids = {}, {}
    for im in images:
        cv2.imwrite(str(image_dir / im.name), np.zeros((480, 640), np.uint8))
        kpts[im.name] = np.array([p.xy for p in im.points2D], np.float32) - 0.5
        point_ids[im.name] = {p.point3D_id: k for k, p in enumerate(im.points2D) if p.has_point3D()}
    pairs, matches = [], []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            common = sorted(set(point_ids[a]) & set(point_ids[b]))
            pairs.append((a, b))
            matches.append(np.array([(point_ids[a][q], point_ids[b][q]) for q in common], np.uint32))
    return gt, image_dir, names, kpts, pairs, matches


def test_synthetic_scene_through_our_database_and_mapper(tmp_path):
    """Exact keypoints and matches: every pair verified with every match, and the mapper gives
    back the truth. A half-pixel slip in the keypoint convention (no +0.5 on writing) fails
    here: measured 0.07 deg rotation and 0.006 px reprojection error instead of 1e-5."""
    from recon.core.sfm import mapping_options, model_stats, run_incremental

    gt, image_dir, names, kpts, pairs, matches = _synthetic_scene(tmp_path)
    db_path = tmp_path / "database.db"
    ids, used, missing = build_database(db_path, image_dir, names, "auto", kpts, pairs, matches,
                                        two_view_options(seed=0))
    assert used == "single" and not missing and sorted(ids) == names
    verified = read_verified(db_path)
    assert len(verified) == len(pairs) == 10
    for (a, b), m in zip(pairs, matches):
        n_in, _, inl = verified[(ids[a], ids[b])]
        assert n_in == len(m) == 150 and {tuple(r) for r in inl} == {tuple(r) for r in m}
    np.testing.assert_allclose(read_keypoints_opencv(db_path, ids[names[2]]), kpts[names[2]], atol=1e-4)

    res = run_incremental(db_path, image_dir, mapping_options(seed=0, num_threads=1))
    rec = res.reconstruction
    assert res.model_sizes == [5] and rec.num_points3D() == 150
    cmp = pycolmap.compare_reconstructions(rec, gt, alignment_error="proj_center", max_proj_center_error=0.1)
    assert max(e.rotation_error_deg for e in cmp["errors"]) < 1e-2
    assert model_stats(rec)["mean_reprojection_error"] < 1e-3
    (cam,) = rec.cameras.values()  # imported with f = 1.2 * 640 px, refined by bundle adjustment
    assert cam.params[0] == pytest.approx(600.0, rel=1e-3)


def test_verification_drops_wrong_matches(tmp_path):
    """A fifth of every pair's matches paired with the wrong keypoint: COLMAP's verification (with
    our options) keeps the right ones and few of the wrong ones."""
    _, image_dir, names, kpts, pairs, matches = _synthetic_scene(tmp_path)
    rng = np.random.default_rng(0)
    noisy, truth = [], []
    for m in matches:
        m = m.copy()
        truth.append({tuple(r) for r in m})
        wrong = rng.choice(len(m), 30, replace=False)
        m[wrong, 1] = m[np.roll(wrong, 1), 1]  # a derangement of the chosen rows' partners
        noisy.append(m)
    db_path = tmp_path / "database.db"
    ids, _, _ = build_database(db_path, image_dir, names, "auto", kpts, pairs, noisy, two_view_options(seed=0))
    verified = read_verified(db_path)
    kept_wrong = 0
    for (a, b), true_set in zip(pairs, truth):
        _, _, inl = verified[(ids[a], ids[b])]
        right = sum(tuple(r) in true_set for r in inl)
        assert right >= 115, (a, b, right)  # of the 120 right matches
        kept_wrong += len(inl) - right
    assert kept_wrong <= 30  # of 300 (measured 20): a wrong match that lies on its epipolar line stays



def test_soundness_check_finds_damage_a_fingerprint_cannot_see(tmp_path):
    import os
    import shutil

    names = _write_images(tmp_path / "images", [(160, 120)] * 2)
    good = tmp_path / "database.db"
    import_scene_images(good, tmp_path / "images", names, "auto")
    assert database_is_sound(good) and database_problem(good) is None
    before = good.read_bytes()
    assert database_problem(tmp_path / "none.db") == "missing"

    damaged = tmp_path / "damaged.db"  # pages overwritten, the SQLite header intact
    data = bytearray(before)
    data[len(data) // 2: len(data) // 2 + 4096] = os.urandom(4096)
    damaged.write_bytes(bytes(data))
    assert not database_is_sound(damaged)

    text = tmp_path / "text.db"
    text.write_text("not a database")
    assert not database_is_sound(text)

    truncated = tmp_path / "truncated.db"
    truncated.write_bytes(before[: len(before) // 3])
    assert not database_is_sound(truncated)

    other = tmp_path / "other.db"  # a valid SQLite file that is not a COLMAP database
    import sqlite3

    con = sqlite3.connect(other)
    con.execute("CREATE TABLE notes (x)")
    con.commit()
    con.close()
    assert "not a COLMAP database" in database_problem(other)

    empty = tmp_path / "empty.db"  # the schema, but no image
    shutil.copy(good, empty)
    con = sqlite3.connect(empty)
    con.execute("DELETE FROM images")
    con.commit()
    con.close()
    assert database_problem(empty) == "no images"
    assert good.read_bytes() == before  # checking never writes


def test_free_space_is_checked_before_colmap_writes(tmp_path, monkeypatch):
    import errno
    import shutil
    from collections import namedtuple

    assert estimate_database_bytes(100, 100_000, 500_000, 1000) > 3 * (24 * 100_000 + 16 * 500_000)
    require_free_space(tmp_path / "database.db", 1)  # plenty
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 << 20, 10 << 20, 4096))
    with pytest.raises(OSError) as e:
        require_free_space(tmp_path / "database.db", 1 << 20)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(tmp_path / "database.db")
    names = _write_images(tmp_path / "images", [(160, 120)] * 2)
    with pytest.raises(OSError):  # refused before pycolmap could abort the process
        import_scene_images(tmp_path / "database.db", tmp_path / "images", names, "auto")
    assert not (tmp_path / "database.db").exists()
