"""Incremental SfM (recon.core.sfm) on databases that `pycolmap.synthesize_dataset` writes into
tmp_path: no images at all and an exactly known truth (as pycolmap's own
python/examples/custom_incremental_pipeline_test.py), so the mapper options, the growth hook,
the choice of the largest model and the model writers are checked in well under a second each.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap, see tests/conftest.py)
import numpy as np
import pycolmap
import pytest

from recon.core.sfm import (
    PP_SIGMA_MAX,
    RETRY_MAX_IMAGES,
    FinalBaConfig,
    GrowthStep,
    SfmResult,
    connected_images,
    final_bundle_adjustment,
    global_bundle_adjustment,
    map_with_retries,
    mapping_options,
    model_stats,
    options_summary,
    registered_names,
    run_incremental,
    write_model_atomic,
    write_points_ply,
)
from recon.eval.evaluate import evaluate_model, poses_from_estimate


def synthesize(db_path: Path, num_frames: int = 6, num_points3D: int = 200, keypoint_noise_px: float = 0.0
               ) -> pycolmap.Reconstruction:
    """One camera, `num_frames` images seeing `num_points3D` points, every pair matched and
    verified; with noise, the database's keypoints move by a Gaussian of that sigma (px).
    Appends to an existing database (a second call gives a second, unconnected scene)."""
    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs = 1
    o.num_cameras_per_rig = 1
    o.num_frames_per_rig = num_frames
    o.num_points3D = num_points3D
    with pycolmap.Database.open(str(db_path)) as db:
        gt = pycolmap.synthesize_dataset(o, db)
        if keypoint_noise_px:
            noise = pycolmap.SyntheticNoiseOptions()
            noise.point2D_stddev = keypoint_noise_px
            pycolmap.synthesize_noise(noise, gt, db)
    return gt


def pose_errors(rec: pycolmap.Reconstruction, gt: pycolmap.Reconstruction) -> tuple[float, float]:
    """(max rotation error in degrees, max camera-centre error in GT units) after aligning `rec` to `gt`."""
    cmp = pycolmap.compare_reconstructions(rec, gt, alignment_error="proj_center", max_proj_center_error=0.1)
    assert cmp is not None, "the model could not be aligned to the synthetic truth"
    errors = cmp["errors"]
    assert len(errors) == gt.num_reg_images()
    return max(e.rotation_error_deg for e in errors), max(e.proj_center_error for e in errors)


def _map(db_path: Path, on_step=None):
    return run_incremental(db_path, db_path.parent / "images", mapping_options(seed=0, num_threads=1), on_step)


def test_noise_free_database_gives_the_synthetic_model(tmp_path):
    db = tmp_path / "database.db"
    gt = synthesize(db)
    res = _map(db)
    rec = res.reconstruction
    assert res.num_models == 1 and res.model_sizes == [6] and res.hook_error is None
    assert rec.num_reg_images() == 6 and rec.num_points3D() == 200
    rot_deg, centre = pose_errors(rec, gt)
    assert rot_deg < 1e-2 and centre < 1e-4
    stats = model_stats(rec)
    assert stats["registered_images"] == 6 and stats["mean_track_length"] == pytest.approx(6.0)
    assert stats["mean_reprojection_error"] < 1e-3
    assert registered_names(rec) == sorted(im.name for im in gt.images.values())


def test_noisy_keypoints_still_give_every_image_and_small_errors(tmp_path):
    db = tmp_path / "database.db"
    gt = synthesize(db, keypoint_noise_px=0.5)
    res = _map(db)
    rec = res.reconstruction
    assert rec.num_reg_images() == 6 and rec.num_points3D() >= 190
    rot_deg, centre = pose_errors(rec, gt)
    assert rot_deg < 0.1 and centre < 0.05
    assert 0.2 < model_stats(rec)["mean_reprojection_error"] < 1.0  # the noise is seen, and absorbed


def test_growth_steps_follow_the_live_model(tmp_path):
    db = tmp_path / "database.db"
    synthesize(db)
    seen: list[tuple[GrowthStep, int, int]] = []
    res = _map(db, on_step=lambda step, live: seen.append((step, live.num_reg_images(), live.num_points3D())))
    steps = [s for s, _, _ in seen]
    assert res.growth == [s.to_dict() for s in steps]
    assert [s.step for s in steps] == list(range(5)) and all(s.model == 0 for s in steps)
    assert [s.registered_images for s in steps] == [2, 3, 4, 5, 6]
    assert all(s.registered_images == n_live and s.num_points3D == p_live for s, n_live, p_live in seen)
    assert len(steps[0].images) == 2 and steps[0].image == steps[0].images[1]  # the initial pair
    for prev, cur in zip(steps, steps[1:]):  # one new image per step, in registration order
        assert cur.images[:-1] == prev.images and cur.image == cur.images[-1]
    assert sorted(steps[-1].images) == registered_names(res.reconstruction)


def test_a_failing_hook_is_reported_once_and_mapping_finishes(tmp_path):
    db = tmp_path / "database.db"
    synthesize(db)
    calls = []

    def broken(step, live):
        calls.append(step.step)
        raise RuntimeError("sink gone")

    res = _map(db, on_step=broken)
    assert calls == [0] and res.hook_error == "RuntimeError: sink gone"
    assert res.reconstruction.num_reg_images() == 6 and len(res.growth) == 5


def test_two_unconnected_scenes_give_two_models_largest_first(tmp_path):
    db = tmp_path / "database.db"
    big = synthesize(db, num_frames=5, num_points3D=100)
    small = synthesize(db, num_frames=4, num_points3D=100)  # shares no match with the first
    res = _map(db)
    assert res.num_models == 2 and res.model_sizes == [5, 4]
    assert res.reconstruction.num_reg_images() == 5
    assert pose_errors(res.reconstruction, big)[0] < 1e-2
    assert {g["model"] for g in res.growth} == {0, 1}
    assert len(res.growth) == (5 - 1) + (4 - 1)  # an initial pair, then one step per image, per model
    assert small.num_reg_images() == 4


def test_connected_images_counts_the_largest_component_of_verified_pairs(tmp_path):
    db = tmp_path / "database.db"
    synthesize(db, num_frames=5, num_points3D=100)
    synthesize(db, num_frames=4, num_points3D=100)  # a second scene, no match with the first
    assert connected_images(db, 15) == 5
    assert connected_images(db, 10**6) == 0  # no pair that strong: no component


class _Model:
    """The two counts `map_with_retries` ranks models by."""

    def __init__(self, images: int) -> None:
        self.images = images

    def num_reg_images(self) -> int:
        return self.images

    def num_points3D(self) -> int:
        return 100 * self.images


def _fake_mapping(registered_by_seed: dict[int, int], calls: list[int]):
    """A stand-in for `run_incremental`: seed -> a model of that many images (0 = none)."""
    def fake(db_path, image_dir, options, on_step=None):
        calls.append(options.random_seed)
        n = registered_by_seed[options.random_seed]
        return SfmResult(_Model(n) if n else None, 1 if n else 0, [n] if n else [])
    return fake


@pytest.mark.parametrize("registered_by_seed, retries, want_calls, want_seed", [
    ({7: 10}, 2, [7], 7),                  # every connected image registered: no retry
    ({7: 9, 8: 10}, 2, [7, 8], 8),         # one image out: the next seed registers it, stop
    ({7: 9, 8: 8, 9: 9}, 2, [7, 8, 9], 7),  # no better model: the first (tie -> the earlier seed)
    ({7: 0, 8: 3, 9: 6}, 2, [7, 8, 9], 9),  # no model at first: the best of the retries
    ({7: 9}, 0, [7], 7),                    # retries off
])
def test_mapping_is_retried_with_the_next_seeds_while_images_stay_out(
        tmp_path, monkeypatch, registered_by_seed, retries, want_calls, want_seed):
    import recon.core.sfm as sfm_mod

    calls: list[int] = []
    monkeypatch.setattr(sfm_mod, "run_incremental", _fake_mapping(registered_by_seed, calls))
    monkeypatch.setattr(sfm_mod, "connected_images", lambda db_path, min_num_matches: 10)
    res, attempts = map_with_retries(tmp_path / "database.db", tmp_path, lambda seed: mapping_options(seed), 7, retries)
    assert calls == want_calls and [a["seed"] for a in attempts] == want_calls
    assert [a["seed"] for a in attempts if a["chosen"]] == [want_seed]
    assert _registered_of(res) == registered_by_seed[want_seed]


def test_a_large_scene_is_not_retried(tmp_path, monkeypatch):
    import recon.core.sfm as sfm_mod

    calls: list[int] = []
    monkeypatch.setattr(sfm_mod, "run_incremental", _fake_mapping({0: 5, 1: 200}, calls))
    monkeypatch.setattr(sfm_mod, "connected_images", lambda db_path, min_num_matches: RETRY_MAX_IMAGES + 1)
    map_with_retries(tmp_path / "database.db", tmp_path, lambda seed: mapping_options(seed), 0, 2)
    assert calls == [0]


def _registered_of(res: SfmResult) -> int:
    return 0 if res.reconstruction is None else res.reconstruction.num_reg_images()


def test_mapping_options_scale_pixel_thresholds_and_seed_every_stage():
    base = mapping_options(seed=5)
    assert base.mapper.init_max_error == 4.0 and base.mapper.abs_pose_max_error == 12.0
    for px_scale, factor in ((0.5, 1.0), (2.0, 2.0), (10.0, 3.0)):  # working-to-full-res factor, in [1, 3]
        o = mapping_options(px_scale=px_scale)
        assert o.mapper.init_max_error == pytest.approx(4.0 * factor)
        assert o.mapper.abs_pose_max_error == pytest.approx(12.0 * factor)
        assert o.mapper.filter_max_reproj_error == pytest.approx(4.0 * factor)
        assert o.triangulation.merge_max_reproj_error == pytest.approx(4.0 * factor)
        assert o.triangulation.complete_max_reproj_error == pytest.approx(4.0 * factor)
    assert base.random_seed == base.mapper.random_seed == base.triangulation.random_seed == 5
    assert base.min_model_size == 3 and base.multiple_models and not base.ba_refine_principal_point
    assert not base.structure_less_registration_fallback  # docs/decisions.md, "Structure-less registration off"
    assert mapping_options(structure_less_fallback=True).structure_less_registration_fallback
    summary = options_summary(mapping_options(px_scale=2.0))
    assert summary["init_max_error"] == pytest.approx(8.0) and summary["init_min_tri_angle"] == 8.0
    assert summary["min_num_matches"] == 15


def _row_capture(db_path: Path, yaws_deg: tuple[float, ...], narrow_matches_all: bool = True,
                 num_points: int = 600, shared: float = 0.4, noise_px: float = 0.3) -> list[str]:
    """A database of cameras on one arc (10 units from a 4 x 3 x 1 block of `num_points` points,
    yaw `yaws_deg`, focal 1500 px, 1024 x 768), keypoints projected with Gaussian noise of
    `noise_px` px. The first two images match on every point, every other pair on a random
    `shared` fraction of them (all verified, uncalibrated), so the first two are the mapper's
    best-matched pair. Returns the image names in id order."""
    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, len(yaws_deg), 50
    o.camera_params = [1500.0, 512.0, 384.0, 0.0]
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-2.0, -1.5, -0.5], [2.0, 1.5, 0.5], (num_points, 3))
    with pycolmap.Database.open(str(db_path)) as db:
        rec = pycolmap.synthesize_dataset(o, db)
        cam = next(iter(rec.cameras.values()))
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        for im, yaw in zip(images, np.deg2rad(yaws_deg)):
            c, s = np.cos(yaw), np.sin(yaw)
            cam_from_world_R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
            centre_in_world = np.array([10.0 * s, 0.0, -10.0 * c])
            uv = np.asarray(cam.img_from_cam((xyz - centre_in_world) @ cam_from_world_R.T))
            db.update_keypoints(im.image_id, (uv + rng.normal(0.0, noise_px, uv.shape)).astype(np.float32))
        first_two = {images[0].image_id, images[1].image_id}
        for a, b in itertools.combinations(images, 2):
            db.delete_matches(a.image_id, b.image_id)
            if db.exists_two_view_geometry(a.image_id, b.image_id):
                db.delete_two_view_geometry(a.image_id, b.image_id)
            every = narrow_matches_all and {a.image_id, b.image_id} == first_two
            idx = np.arange(num_points) if every else np.flatnonzero(rng.random(num_points) < shared)
            matches = np.stack([idx, idx], axis=1).astype(np.uint32)
            db.write_matches(a.image_id, b.image_id, matches)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            geometry.inlier_matches = matches
            db.write_two_view_geometry(a.image_id, b.image_id, geometry)
    return [im.name for im in images]


def test_a_wide_pair_starts_the_model_before_a_narrow_one_with_more_matches(tmp_path):
    """sacre_coeur's failure, reduced: the best-matched pair is 6 deg apart (above the 4 deg the
    mapper used to accept), two wider pairs have fewer matches. At 8 deg the model starts from
    a wide pair (docs/decisions.md, "Initial pair at 8 deg")."""
    names = _row_capture(tmp_path / "database.db", (-3.0, 3.0, -20.0, 20.0))
    res = run_incremental(tmp_path / "database.db", tmp_path, mapping_options(seed=0, num_threads=1))
    initial = [set(s["initial_pair"]) for s in res.growth if s["initial_pair"]]
    assert res.model_sizes == [4]
    assert initial[0] != set(names[:2]) and initial[0] & {names[2], names[3]}


def test_a_capture_of_only_narrow_pairs_still_initialises(tmp_path):
    """No pair reaches 8 deg (cameras 3-6 deg apart): COLMAP's pipeline relaxes its initial-pair
    thresholds by itself (inliers, then angle, halved twice) and maps every image."""
    _row_capture(tmp_path / "database.db", (-3.0, 3.0, 0.0), narrow_matches_all=False, shared=0.8)
    res = run_incremental(tmp_path / "database.db", tmp_path, mapping_options(seed=0, num_threads=1))
    assert res.model_sizes == [3]


def test_write_model_atomic_replaces_the_model_and_leaves_no_temporary_folder(tmp_path):
    db1, db2 = tmp_path / "a" / "database.db", tmp_path / "b" / "database.db"
    db1.parent.mkdir()
    db2.parent.mkdir()
    synthesize(db1, num_frames=6)
    synthesize(db2, num_frames=4, num_points3D=80)
    model_dir = tmp_path / "out" / "sparse" / "0"
    write_model_atomic(_map(db1).reconstruction, model_dir)
    assert pycolmap.Reconstruction(str(model_dir)).num_reg_images() == 6
    write_model_atomic(_map(db2).reconstruction, model_dir)  # replaces the first
    again = pycolmap.Reconstruction(str(model_dir))
    assert again.num_reg_images() == 4 and again.num_points3D() == 80
    assert sorted(p.name for p in model_dir.parent.iterdir()) == ["0"]


def test_point_cloud_and_stats_of_no_model(tmp_path):
    db = tmp_path / "database.db"
    synthesize(db)
    rec = _map(db).reconstruction
    ply = tmp_path / "points.ply"
    assert write_points_ply(rec, ply) == rec.num_points3D() == 200
    import open3d as o3d

    xyz = np.asarray(o3d.io.read_point_cloud(str(ply)).points)
    np.testing.assert_allclose(np.sort(xyz[:, 0]), np.sort([p.xyz[0] for p in rec.points3D.values()]), atol=1e-9)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["database.db", "points.ply"]
    assert model_stats(None) == dict(registered_images=0, num_points3D=0, mean_track_length=0.0,
                                     mean_reprojection_error=None, mean_observations_per_image=0.0)
    assert registered_names(None) == []


def test_point_cloud_of_a_model_read_back_is_the_same_bytes(tmp_path):
    """A rerun reads its model back from disk, whose point map iterates in another order:
    points.ply is written in point id order, so it does not change between identical runs."""
    db = tmp_path / "database.db"
    synthesize(db)
    rec = _map(db).reconstruction
    # as a mapper does: many points made and half of them dropped again (the hash map grows)
    made = [rec.add_point3D(np.array([k, 0.0, 5.0]), pycolmap.Track(), np.array([1, 2, 3], np.uint8))
            for k in range(5000)]
    for pid in made[::2]:
        rec.delete_point3D(pid)
    model_dir = tmp_path / "sparse" / "0"
    write_model_atomic(rec, model_dir)
    assert list(rec.points3D.keys()) != list(pycolmap.Reconstruction(str(model_dir)).points3D.keys())
    fresh, again = tmp_path / "fresh.ply", tmp_path / "again.ply"
    write_points_ply(rec, fresh)
    write_points_ply(pycolmap.Reconstruction(str(model_dir)), again)
    assert fresh.read_bytes() == again.read_bytes()


def test_the_pipeline_maps_with_colmaps_full_resolution_thresholds_unless_asked_to_scale():
    """Photos matched at half size (px_scale 2): the mapper keeps COLMAP's 4 px reprojection
    filter, as stock does; `sfm.scale_thresholds` doubles it."""
    from recon.config import build_run_config
    from recon.core.stages.sfm import mapping_options as stage_options

    plain = stage_options(build_run_config(), px_scale=2.0)
    scaled = stage_options(build_run_config(settings=["sfm.scale_thresholds=true"]), px_scale=2.0)
    assert plain.mapper.filter_max_reproj_error == pytest.approx(4.0)
    assert plain.triangulation.complete_max_reproj_error == pytest.approx(4.0)
    assert scaled.mapper.filter_max_reproj_error == pytest.approx(8.0)
    assert scaled.mapper.abs_pose_max_error == pytest.approx(24.0)
    fallback = stage_options(build_run_config(settings=["sfm.structure_less_fallback=true"]), px_scale=2.0)
    assert fallback.structure_less_registration_fallback and not plain.structure_less_registration_fallback


def _copy_model(rec: pycolmap.Reconstruction, folder: Path) -> pycolmap.Reconstruction:
    folder.mkdir()
    rec.write(str(folder))
    return pycolmap.Reconstruction(str(folder))


def test_final_robust_adjustment_resists_observations_a_few_px_off(tmp_path):
    """10 % of the observations moved 3 px (inside the mapper's 4 px filter, as chance matches
    on repeated texture are): a squared-loss adjustment follows them, the final Cauchy one keeps
    the poses of the clean observations."""
    db = tmp_path / "database.db"
    gt = synthesize(db, num_frames=8, num_points3D=300, keypoint_noise_px=0.3)
    rec = _map(db).reconstruction
    clean_rot, _ = pose_errors(rec, gt)
    rng = np.random.default_rng(0)
    moved = 0
    for image_id in sorted(rec.reg_image_ids()):
        for p in rec.image(image_id).points2D:
            if p.has_point3D() and rng.random() < 0.1:
                p.xy = p.xy + np.array([3.0, 0.0])
                moved += 1
    assert moved > 150
    squared, robust = _copy_model(rec, tmp_path / "squared"), _copy_model(rec, tmp_path / "robust")
    o = pycolmap.BundleAdjustmentOptions()
    o.refine_principal_point = False
    pycolmap.bundle_adjustment(squared, o)
    # the loss is the subject: the principal point held as the squared run holds it (freed, it
    # absorbs part of a shift every moved observation shares, here all +3 px in x)
    summary = final_bundle_adjustment(robust, FinalBaConfig(principal_point="fixed"))
    assert summary["applied"] and summary["loss"] == "cauchy" and summary["observations_dropped"] >= 0
    squared_rot, _ = pose_errors(squared, gt)
    robust_rot, _ = pose_errors(robust, gt)
    assert squared_rot > 2 * clean_rot  # the moved observations do pull a squared loss
    assert robust_rot < 0.5 * squared_rot and robust_rot < 1.5 * clean_rot


def test_global_bundle_adjustment_is_colmaps_to_the_bit_and_keeps_colmap_quiet(tmp_path, capfd):
    """Our copy of `pycolmap.bundle_adjustment` (which builds an OptionManager, and that resets
    glog's level: its heading and timer reached stderr under `quiet_colmap`) gives the same
    poses, points, intrinsics and point errors to the bit, prints nothing and leaves the log
    level where it was."""
    db = tmp_path / "database.db"
    synthesize(db, num_frames=6, num_points3D=200, keypoint_noise_px=0.5)
    rec = _map(db).reconstruction
    for pid, p in rec.points3D.items():  # start off the optimum, so the adjustment has work
        p.xyz = p.xyz + 0.01 * np.sin(pid)
    theirs, ours = _copy_model(rec, tmp_path / "theirs"), _copy_model(rec, tmp_path / "ours")

    def options() -> pycolmap.BundleAdjustmentOptions:
        o = pycolmap.BundleAdjustmentOptions()
        o.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        o.ceres.solver_options.num_threads = 1
        o.print_summary = False
        return o

    old = pycolmap.logging.minloglevel
    try:
        pycolmap.logging.minloglevel = 3
        capfd.readouterr()
        global_bundle_adjustment(ours, options())
        printed = capfd.readouterr()
        assert pycolmap.logging.minloglevel == 3
        assert "bundle adjustment" not in printed.err + printed.out
        pycolmap.bundle_adjustment(theirs, options())
    finally:
        pycolmap.logging.minloglevel = old
    assert sorted(ours.points3D) == sorted(theirs.points3D)
    for pid in theirs.points3D:
        assert np.array_equal(ours.points3D[pid].xyz, theirs.points3D[pid].xyz)
        assert ours.points3D[pid].error == theirs.points3D[pid].error
    for image_id in theirs.images:
        assert np.array_equal(ours.images[image_id].cam_from_world().matrix(),
                              theirs.images[image_id].cam_from_world().matrix())
    for camera_id in theirs.cameras:
        assert np.array_equal(ours.cameras[camera_id].params, theirs.cameras[camera_id].params)
    moved = max(np.abs(ours.points3D[pid].xyz - rec.points3D[pid].xyz).max() for pid in rec.points3D)
    assert moved > 1e-3  # it did adjust


def test_outlier_pass_drops_the_observations_the_loss_discounts_and_keeps_the_rest(tmp_path):
    """The same 3 px moves on 5 % of the observations (noise 0.3 px: about 4 loss scales off):
    one pass keeps them all under the 4 px filter, the outlier pass drops nearly all of them and
    little else, at a lower reprojection error and no worse poses."""
    db = tmp_path / "database.db"
    gt = synthesize(db, num_frames=8, num_points3D=300, keypoint_noise_px=0.3)
    rec = _map(db).reconstruction
    rng = np.random.default_rng(1)
    moved: set[tuple[int, int]] = set()
    for image_id in sorted(rec.reg_image_ids()):
        for idx, p in enumerate(rec.image(image_id).points2D):
            if p.has_point3D() and rng.random() < 0.05:
                p.xy = p.xy + np.array([0.0, 3.0])
                moved.add((image_id, idx))
    assert len(moved) > 80
    one, two = _copy_model(rec, tmp_path / "one"), _copy_model(rec, tmp_path / "two")
    s1 = final_bundle_adjustment(one, FinalBaConfig(outlier_scales=0, principal_point="fixed"))
    s2 = final_bundle_adjustment(two, FinalBaConfig(principal_point="fixed"))
    assert "outlier_threshold_px" not in s1 and s1["observations_dropped"] < 0.1 * len(moved)
    assert 1.0 < s2["outlier_threshold_px"] < 3.0
    assert s2["outlier_threshold_px"] == pytest.approx(3 * s2["second_scale_px"], abs=2e-4)  # both rounded to 4 digits

    def kept(m: pycolmap.Reconstruction) -> set[tuple[int, int]]:
        return {(i, k) for i in m.reg_image_ids() for k, p in enumerate(m.image(i).points2D) if p.has_point3D()}

    gone_moved = len(moved - kept(two))
    gone_clean = len((kept(one) | moved) - kept(two)) - gone_moved
    assert gone_moved > 0.9 * len(moved) and gone_clean < 0.02 * len(kept(one))
    assert two.compute_mean_reprojection_error() < 0.8 * one.compute_mean_reprojection_error()
    assert pose_errors(two, gt)[0] <= 1.1 * pose_errors(one, gt)[0]


def _off_centre_capture(tmp_path: Path) -> tuple[pycolmap.Reconstruction, pycolmap.Reconstruction]:
    """(mapped model, ground truth) of eight synthetic views all round 400 points, one 1024 x 768
    camera whose true principal point (542, 364) lies 30 / 20 px off the centre; the mapped
    model's principal point is moved to the centre, as COLMAP assumes for a photo."""
    db = tmp_path / "database.db"
    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, 8, 400
    o.camera_params = [1280.0, 542.0, 364.0, 0.0]
    with pycolmap.Database.open(str(db)) as d:
        gt = pycolmap.synthesize_dataset(o, d)
    rec = _map(db).reconstruction
    for cam in rec.cameras.values():
        cam.params = [cam.params[0], 512.0, 384.0, cam.params[3]]
    return rec, gt


def test_refining_the_principal_point_recovers_an_off_centre_one(tmp_path):
    """The synthetic camera's principal point moved to the image centre, as COLMAP assumes for a
    photo: `fixed` keeps it there, `refine` finds the true one back and the poses with it, and so
    does `auto` (the default), whose covariance says the views determine it."""
    rec, gt = _off_centre_capture(tmp_path)
    fixed, free = _copy_model(rec, tmp_path / "fixed"), _copy_model(rec, tmp_path / "free")
    auto = _copy_model(rec, tmp_path / "auto")
    assert final_bundle_adjustment(fixed, FinalBaConfig(principal_point="fixed"))["principal_point_refined"] is False
    assert final_bundle_adjustment(free, FinalBaConfig(principal_point="refine"))["principal_point_refined"] is True
    assert np.allclose(next(iter(fixed.cameras.values())).params[1:3], [512.0, 384.0])
    assert np.allclose(next(iter(free.cameras.values())).params[1:3], [542.0, 364.0], atol=2.0)
    assert pose_errors(free, gt)[0] < 0.5 * pose_errors(fixed, gt)[0]
    # auto: the views determine the point (eight cameras all round), so it is freed
    summary = final_bundle_adjustment(auto, FinalBaConfig())
    assert summary["principal_point"] == "auto"
    assert summary["principal_point_refined"] and summary["principal_point_sigma"] <= PP_SIGMA_MAX
    assert np.allclose(next(iter(auto.cameras.values())).params[1:3], [542.0, 364.0], atol=2.0)


def test_auto_principal_point_stays_fixed_without_a_covariance(tmp_path, monkeypatch):
    """Above `PP_SIGMA_MAX_IMAGES` registered images the covariance (a dense matrix over every
    pose) is not estimated, and an estimate COLMAP refuses counts as none: either way `auto`
    reports no sigma and keeps the principal point where it is, even on a capture whose views
    determine it."""
    import recon.core.sfm as sfm

    rec, _ = _off_centre_capture(tmp_path)
    under = _copy_model(rec, tmp_path / "under")
    assert final_bundle_adjustment(under, FinalBaConfig(principal_point="auto"))["principal_point_refined"]
    monkeypatch.setattr(sfm, "PP_SIGMA_MAX_IMAGES", rec.num_reg_images() - 1)
    over = _copy_model(rec, tmp_path / "over")
    summary = final_bundle_adjustment(over, FinalBaConfig(principal_point="auto"))
    assert summary["principal_point_refined"] is False and summary["principal_point_sigma"] is None
    assert np.allclose(next(iter(over.cameras.values())).params[1:3], [512.0, 384.0])
    # an estimate COLMAP refuses (an exception, not None) counts as none: the point stays, the run goes on
    monkeypatch.setattr(sfm, "PP_SIGMA_MAX_IMAGES", 1000)

    def refuse(*args, **kwargs):
        raise RuntimeError("Check failed")

    monkeypatch.setattr(sfm.pycolmap, "estimate_ba_covariance", refuse)
    refused = _copy_model(rec, tmp_path / "refused")
    summary = final_bundle_adjustment(refused, FinalBaConfig(principal_point="auto"))
    assert summary["applied"] and summary["principal_point_refined"] is False
    assert summary["principal_point_sigma"] is None


def _arc_capture(db_path: Path, num_frames: int = 6, yaw_deg: float = 30.0, noise_px: float = 0.3
                 ) -> pycolmap.Reconstruction:
    """The capture that leaves the principal point loose: `num_frames` cameras on one arc at one
    height (10 units from the origin, yaw -`yaw_deg` to +`yaw_deg`, no pitch), each looking at the
    origin, over 300 points of a shallow facade (4 x 3 x 1 units); one 1024 x 768 camera, focal
    1500 px, principal point at the centre. Returns the model with the true poses and points and
    observations projected with Gaussian noise of `noise_px` (px)."""
    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, num_frames, 300
    o.camera_params = [1500.0, 512.0, 384.0, 0.0]
    with pycolmap.Database.open(str(db_path)) as d:
        rec = pycolmap.synthesize_dataset(o, d)
    rng = np.random.default_rng(0)
    for pid in sorted(rec.points3D.keys()):
        rec.points3D[pid].xyz = rng.uniform([-2.0, -1.5, -0.5], [2.0, 1.5, 0.5])
    for yaw, fid in zip(np.deg2rad(np.linspace(-yaw_deg, yaw_deg, num_frames)), sorted(rec.frames.keys())):
        c, s = np.cos(yaw), np.sin(yaw)
        centre_in_world = np.array([10.0 * s, 0.0, -10.0 * c])
        cam_from_world_R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # optical axis at the origin
        rec.frames[fid].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world_R),
                                                          -cam_from_world_R @ centre_in_world)
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        for p2 in im.points2D:
            if p2.has_point3D():
                xy = np.asarray(cam.img_from_cam(im.cam_from_world() * rec.points3D[p2.point3D_id].xyz)).ravel()
                assert 0 <= xy[0] < 1024 and 0 <= xy[1] < 768
                p2.xy = xy + rng.normal(0.0, noise_px, 2)
    return rec


def test_auto_principal_point_stays_fixed_where_a_row_of_cameras_leaves_it_loose(tmp_path):
    """Cameras on one arc at one height: a shift of the principal point is nearly a common pitch
    of every camera, so refining it drifts tens of px and tilts the poses; `auto` finds the point
    undetermined by the covariance and keeps it (the difficulty curve's case, docs/decisions.md)."""
    truth = _arc_capture(tmp_path / "database.db")
    gt = poses_from_estimate(truth)

    def rotation_error(m: pycolmap.Reconstruction) -> float:  # median relative rotation error, degrees
        return float(evaluate_model(m, gt, with_pairs=False)["rel_rot_err_deg_median"])

    free, auto = _copy_model(truth, tmp_path / "free"), _copy_model(truth, tmp_path / "auto")
    fixed = _copy_model(truth, tmp_path / "fixed")
    final_bundle_adjustment(fixed, FinalBaConfig(principal_point="fixed"))
    final_bundle_adjustment(free, FinalBaConfig(principal_point="refine"))
    assert abs(next(iter(free.cameras.values())).principal_point_y - 384.0) > 10.0
    assert rotation_error(free) > 2 * rotation_error(fixed)
    summary = final_bundle_adjustment(auto, FinalBaConfig(principal_point="auto"))
    sigma = summary["principal_point_sigma"]
    assert summary["principal_point_refined"] is False and (sigma is None or sigma > PP_SIGMA_MAX)
    assert np.allclose(next(iter(auto.cameras.values())).params[1:3], [512.0, 384.0])
    assert rotation_error(auto) == pytest.approx(rotation_error(fixed), rel=1e-6)


def test_final_adjustment_off_leaves_the_model_as_the_mapper_made_it(tmp_path):
    db = tmp_path / "database.db"
    synthesize(db, keypoint_noise_px=0.5)
    rec = _map(db).reconstruction
    before = {i: rec.image(i).cam_from_world().rotation.quat.copy() for i in rec.reg_image_ids()}
    assert final_bundle_adjustment(rec, FinalBaConfig(loss="none")) == {"loss": "none", "applied": False}
    for i, q in before.items():
        assert np.array_equal(rec.image(i).cam_from_world().rotation.quat, q)


@pytest.mark.parametrize("verbose", [False, True])
def test_final_adjustment_prints_colmaps_solver_report_only_when_verbose(tmp_path, capfd, monkeypatch, verbose):
    """COLMAP writes a 10-line solver report per adjustment to stderr past its own log level; a
    run shows it only under `recon -v` (`recon.log.colmap_verbose`)."""
    import recon.core.sfm as sfm

    db = tmp_path / "database.db"
    synthesize(db, num_frames=5, num_points3D=150, keypoint_noise_px=0.3)
    rec = _map(db).reconstruction
    monkeypatch.setattr(sfm, "colmap_verbose", lambda: verbose)
    capfd.readouterr()
    info = final_bundle_adjustment(rec, FinalBaConfig())
    err = capfd.readouterr().err
    assert info["applied"]
    assert ("Bundle adjustment report" in err) == verbose
