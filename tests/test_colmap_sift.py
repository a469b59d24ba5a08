"""COLMAP's covariant SIFT as a detector (`matching.colmap_sift`, DetectorConfig "colmap-sift") and
the fine stage matching the originals with it (`FineConfig.original_detector`): keypoints in
OpenCV's pixel convention on rendered blobs, correct matches on a rendered homography pair, the
originals' matches indexing the target's COLMAP block, and the multi-view preset's setting."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from matching.config import MatcherConfig
from matching.features import DetectorConfig, detect
from matching.fine import FineConfig, fine_match, target_features
from matching.matcher import ExtraAffineMatcher
from matching.store import FeatureStore
from matching.types import ViewParams
from matching.viewfeatures import original_features
from scenes.texture import procedural_texture

COLMAP = DetectorConfig("colmap-sift")
IDENTITY = ViewParams(1.0, 0.0, 1.0)


def _blobs(n: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 400x300 image of `n` Gaussian blobs (sigma 2.5-5 px) and their centres, OpenCV convention
    (the centre of the top-left pixel is (0, 0))."""
    h, w = 300, 400
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.full((h, w), 60.0)
    rng = np.random.default_rng(seed)
    centres = []
    for _ in range(n):
        cx, cy, s = rng.uniform(30, w - 30), rng.uniform(30, h - 30), rng.uniform(2.5, 5.0)
        img += 150.0 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
        centres.append((cx, cy))
    return np.clip(img, 0, 255).astype(np.uint8), np.array(centres)


def _offsets(kpts: np.ndarray, centres: np.ndarray, within: float = 1.5) -> np.ndarray:
    """(K, 2) keypoint - centre of the keypoints within `within` px of a blob centre."""
    d = np.linalg.norm(kpts[:, None, :] - centres[None, :, :], axis=2)
    near = d.min(axis=1) < within
    return kpts[near] - centres[d[near].argmin(axis=1)]


def _pair(tilt: float = 1.6, angle: float = 20.0, size: tuple[int, int] = (360, 270)):
    """A procedural texture and its view under a known tilted homography (H_1_from_0)."""
    w, h = size
    tex = procedural_texture(4.0, 3.0, 90.0, seed=3)
    img0 = cv2.resize(cv2.cvtColor(tex, cv2.COLOR_BGR2GRAY) if tex.ndim == 3 else tex, size,
                      interpolation=cv2.INTER_AREA)
    c = np.array([w / 2.0, h / 2.0])
    L = 1.1 * np.diag([1 / tilt, 1.0]) @ cv2.getRotationMatrix2D((0, 0), angle, 1.0)[:, :2]
    H = np.eye(3)
    H[:2, :2] = L
    H[:2, 2] = c - L @ c
    H[2, :2] = [2e-4, -1e-4]
    return img0, cv2.warpPerspective(img0, H, size, flags=cv2.INTER_LINEAR), H


def _project(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(pts.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)


@pytest.fixture(scope="module")
def blobs():
    img, centres = _blobs()
    return img, centres, detect(img, COLMAP)


@pytest.fixture(scope="module")
def pair_store():
    img0, img1, H = _pair()
    store = FeatureStore()
    store.add_image("a", img0)
    store.add_image("b", img1)
    return store, H


def test_keypoints_are_in_opencv_pixel_convention(blobs):
    img, centres, f = blobs
    off = _offsets(f.kpts, centres)
    assert len(off) >= 30  # nearly every blob found
    # COLMAP's +0.5 convention removed: the blob centres to a small fraction of a pixel
    assert np.all(np.abs(np.median(off, axis=0)) < 0.1)
    assert np.mean(np.linalg.norm(off, axis=1)) < 0.2
    # and on the same blobs as OpenCV's SIFT (centred by `detect`, see the module doc)
    cv_kpts = detect(img, DetectorConfig("sift")).kpts
    on_blob = f.kpts[np.linalg.norm(f.kpts[:, None, :] - centres[None], axis=2).min(axis=1) < 1.5]
    d = np.linalg.norm(on_blob[:, None, :] - cv_kpts[None, :, :], axis=2).min(axis=1)
    assert np.mean(d < 0.5) > 0.8
    # sizes are diameters as OpenCV's (2 x COLMAP's scale): a blob of sigma s has size about 2-4 s
    assert np.all(f.sizes > 0) and np.all((f.angles >= 0) & (f.angles < 360))


def test_descriptors_are_rootsift_at_opencv_scale(blobs):
    _, _, f = blobs
    assert f.descriptors.dtype == np.float32 and f.descriptors.shape[1] == 128
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 512.0, rtol=1e-4)
    assert f.descriptors.min() >= 0


def test_mask_limits_the_keypoints(blobs):
    img, _, full = blobs
    mask = np.zeros_like(img)
    mask[:, :200] = 255
    f = detect(img, COLMAP, mask)
    assert 0 < len(f) < len(full)
    assert np.all(f.kpts[:, 0] < 200.5)


@pytest.mark.parametrize("detector", ["colmap-sift", "colmap-sift-affine", "colmap-sift-plain"])
def test_homography_pair_matches_land_on_the_truth(pair_store, detector):
    store, H = pair_store
    f0, f1 = (original_features(store, n, FineConfig(original_detector=detector).originals_detector)
              for n in ("a", "b"))
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(f0.descriptors, f1.descriptors, k=2)
    m = np.array([(a.queryIdx, a.trainIdx) for a, b in knn if a.distance < 0.8 * b.distance])
    assert len(m) >= 100
    err = np.linalg.norm(_project(H, f0.kpts[m[:, 0]]) - f1.kpts[m[:, 1]], axis=1)
    assert np.mean(err < 1.5) > 0.8
    assert np.median(err) < 0.5


def test_fine_stage_matches_the_originals_with_colmap_sift(pair_store):
    store, H = pair_store
    cfg = FineConfig(original_detector="colmap-sift")
    assert cfg.detector_for(IDENTITY).name == "colmap-sift"
    assert cfg.detector_for(ViewParams(2.0, 45.0, 1.0)).name == "sift"
    tf = target_features(store, "b", cfg)
    (cv_feats, cv_off), (cm_feats, cm_off) = tf.part(cfg.detector), tf.part(cfg.originals_detector)
    assert cv_off == 0 and cm_off == len(cv_feats) and len(tf.kpts) == len(cv_feats) + len(cm_feats)

    fm = fine_match(store, "a", "b", [IDENTITY], cfg)
    assert len(fm.matches) >= 100
    assert np.all(fm.matches[:, 1] >= cm_off)  # the originals' matches index the COLMAP block
    err = np.linalg.norm(_project(H, fm.kpts_ref[fm.matches[:, 0]]) - fm.kpts_target[fm.matches[:, 1]], axis=1)
    assert np.mean(err < 1.5) > 0.8

    # a simulated view next to the original: its matches index the OpenCV block, both are correct
    tilted = ViewParams(1.4142, 0.0, 1.0)
    fm2 = fine_match(store, "a", "b", [tilted, IDENTITY], cfg)
    assert np.any(fm2.matches[:, 1] < cm_off) and np.any(fm2.matches[:, 1] >= cm_off)
    err2 = np.linalg.norm(_project(H, fm2.kpts_ref[fm2.matches[:, 0]]) - fm2.kpts_target[fm2.matches[:, 1]], axis=1)
    assert np.mean(err2 < 1.5) > 0.8

    # the default keeps one block, OpenCV's SIFT: the fine stage as before
    plain = FineConfig()
    assert plain.originals_detector == plain.detector
    tf_plain = target_features(store, "b", plain)
    assert list(tf_plain.parts) == [plain.detector.key] and tf_plain.kpts is cv_feats.kpts


@pytest.mark.slow
def test_multiview_matcher_with_colmap_originals_gives_correct_matches(pair_store):
    store, H = pair_store
    cfg = MatcherConfig.from_overrides(variant="multiview", **{"fine.original_detector": "colmap-sift"}, workers=1)
    assert cfg.fine.originals_detector.name == "colmap-sift"
    assert cfg.fine_include_original and cfg.guided_epipolar
    res = ExtraAffineMatcher(cfg).match(store, "a", "b")
    assert res.num_matches >= 100
    p0, p1 = res.matched_points(inliers_only=False)
    err = np.linalg.norm(_project(H, p0) - p1, axis=1)
    assert np.mean(err < 1.5) > 0.8


def test_recon_run_matches_the_originals_with_colmap_sift_by_default():
    from recon.config import build_run_config
    from recon.core.stages.match import make_matcher

    assert MatcherConfig.multiview().fine.original_detector == "colmap-sift"
    assert MatcherConfig().fine.original_detector == "sift" and MatcherConfig.paper().fine.original_detector == "sift"
    run = build_run_config()
    assert make_matcher(run.match).cfg.fine.originals_detector.name == "colmap-sift"
    off = build_run_config(settings=["matcher.fine.original_detector=sift"])
    assert make_matcher(off.match).cfg.fine.originals_detector.name == "sift"


def test_extraction_in_child_processes_is_identical_and_runs_there():
    """Inside `extraction_processes` the covariant extraction runs in spawned children (it holds
    the GIL in this process) and gives bit-identical keypoints and descriptors; outside it, in
    this process again; a dead child's call is taken back into this process."""
    import os

    from matching import colmap_sift

    img, _ = _blobs(60, seed=4)
    here = colmap_sift.detect_colmap_sift(img)
    pids: set[int] = set()
    with colmap_sift.extraction_processes(2):
        assert colmap_sift._pool is not None
        pool = colmap_sift._pool
        assert pool is not None
        there = colmap_sift.detect_colmap_sift(img)
        pids = {p for p in (pool._processes or {})}
        assert pids and os.getpid() not in pids
        for proc in list((pool._processes or {}).values()):
            proc.kill()
            proc.join()
        after_death = colmap_sift.detect_colmap_sift(img)
    assert colmap_sift._pool is None
    for a, b, c in zip(here, there, after_death, strict=True):
        assert a.shape == b.shape == c.shape and len(a) > 20
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_extraction_processes_is_a_no_op_when_nested_or_zero():
    """n <= 0 and a nested block keep the outer state (one pool, owned by the outer block)."""
    from matching import colmap_sift

    with colmap_sift.extraction_processes(0):
        assert colmap_sift._pool is None
    with colmap_sift.extraction_processes(1):
        outer = colmap_sift._pool
        with colmap_sift.extraction_processes(2):
            assert colmap_sift._pool is outer
        assert colmap_sift._pool is outer
    assert colmap_sift._pool is None


def test_affine_variant_keeps_the_keypoints_and_drops_domain_size_pooling(blobs):
    """"colmap-sift-affine" finds the same (affine-adapted) keypoints as "colmap-sift"; only the
    descriptors differ, pooled over one support size instead of several."""
    img, _, pooled = blobs
    affine = detect(img, DetectorConfig("colmap-sift-affine"))
    np.testing.assert_array_equal(affine.kpts, pooled.kpts)
    np.testing.assert_array_equal(affine.sizes, pooled.sizes)
    assert not np.allclose(affine.descriptors, pooled.descriptors, atol=1.0)
    np.testing.assert_allclose(np.linalg.norm(affine.descriptors, axis=1), 512.0, rtol=1e-4)


def test_plain_variant_is_colmaps_default_extraction(blobs):
    """"colmap-sift-plain" is COLMAP's default extraction (no affine shape, no pooling): the
    keypoints of pycolmap's own default options, upright ellipses of the same SIFT peaks, so
    their positions differ from the affine-adapted ones only by the adaptation."""
    import pycolmap

    from matching import colmap_sift

    img, _, pooled = blobs
    plain = detect(img, DetectorConfig("colmap-sift-plain"))
    opts = pycolmap.FeatureExtractionOptions()
    opts.use_gpu, opts.num_threads, opts.max_image_size = False, 1, 100000
    opts.sift.max_num_features = colmap_sift.UNLIMITED
    kps, _ = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu).extract_from_uint8_array(img)
    ref = np.asarray(pycolmap.keypoints_to_matrix(kps), np.float32).reshape(-1, 4)[:, :2] - 0.5
    assert len(plain) == len(ref) > 0
    np.testing.assert_allclose(np.sort(plain.kpts, axis=0), np.sort(ref, axis=0), atol=1e-3)
    assert len(plain) != len(pooled) or not np.array_equal(plain.kpts, pooled.kpts)


def test_an_interrupted_block_abandons_its_extractions():
    """When the block ends with an exception (Ctrl-C), its children are killed and a thread that
    was waiting for them gets CancelledError: it does not redo the extraction in this process."""
    import threading
    import time
    from concurrent.futures import CancelledError

    from matching import colmap_sift

    tex = procedural_texture(4.0, 3.0, 300.0, seed=9)
    big = cv2.resize(cv2.cvtColor(tex, cv2.COLOR_BGR2GRAY) if tex.ndim == 3 else tex, (1600, 1200))
    outcome: list[object] = []

    def extract() -> None:
        try:
            outcome.append(colmap_sift.detect_colmap_sift(big))
        except BaseException as e:  # noqa: BLE001  (recorded for the assertion)
            outcome.append(e)

    worker = threading.Thread(target=extract)
    with pytest.raises(KeyboardInterrupt), colmap_sift.extraction_processes(1):
        worker.start()
        deadline = time.monotonic() + 60
        pool = colmap_sift._pool
        assert pool is not None
        while not any(p.is_alive() for p in (pool._processes or {}).values()) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(2.0)  # the child imports pycolmap and starts the (~10 s) extraction
        assert colmap_sift._users and worker.is_alive()
        raise KeyboardInterrupt
    worker.join(60)
    assert len(outcome) == 1 and isinstance(outcome[0], CancelledError), outcome
    assert colmap_sift._pool is None
    # a later block (or a library call outside any block) extracts normally again
    small, _ = _blobs(20, seed=1)
    assert len(colmap_sift.detect_colmap_sift(small)[0]) > 5
    # so do new threads, also one that gets the abandoned thread's ident (the interpreter reuses a
    # finished thread's ident: a Dask worker's thread once inherited the mark and could not
    # extract). Threads started together take the cached thread stacks, the worker's among them.
    abandoned_ident, runs, start = worker.ident, [], threading.Barrier(16)

    def later() -> None:
        start.wait(60)
        try:
            runs.append((threading.get_ident(), len(colmap_sift.detect_colmap_sift(small)[0])))
        except BaseException as e:  # noqa: BLE001  (recorded for the assertion)
            runs.append((threading.get_ident(), e))

    threads = [threading.Thread(target=later) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert abandoned_ident in {ident for ident, _ in runs}, "no new thread reused the ident"
    assert len(runs) == 16 and all(isinstance(n, int) and n > 5 for _, n in runs), runs


def test_fewer_pooling_scales_change_descriptors_not_keypoints(blobs):
    """`dsp_scales` (FineConfig.original_dsp_scales) reaches COLMAP: same keypoints, other
    descriptors, and another cache key (features of both settings never mix)."""
    img, _, pooled = blobs
    five = DetectorConfig("colmap-sift", dsp_scales=5)
    f5 = detect(img, five)
    np.testing.assert_array_equal(f5.kpts, pooled.kpts)
    assert not np.allclose(f5.descriptors, pooled.descriptors, atol=1.0)
    assert five.key != COLMAP.key
    det = FineConfig(original_detector="colmap-sift", original_dsp_scales=5).originals_detector
    assert det.dsp_scales == 5 and det.key.endswith("d5")


def test_opencv_sift_keypoints_sit_on_pixel_centres():
    """OpenCV's SIFT doubles its input with a half-pixel shift: keypoints of Gaussian blobs land
    about +0.25 px off in x and y (`centre_keypoints=False` keeps that); by default `detect`
    subtracts the shift, same detections and descriptors, and `precise_upscale` places them on
    the centres by another upscale. Each is its own feature-cache key."""
    from matching.features import detect

    img, centres = _blobs()
    biased = DetectorConfig("sift", contrast=0.02, centre_keypoints=False)
    default = DetectorConfig("sift", contrast=0.02)
    precise = DetectorConfig("sift", contrast=0.02, precise_upscale=True)
    f_biased, f_default = detect(img, biased), detect(img, default)
    shift = np.median(_offsets(f_biased.kpts, centres), axis=0)
    centred = np.median(_offsets(f_default.kpts, centres), axis=0)
    fixed = np.median(_offsets(detect(img, precise).kpts, centres), axis=0)
    assert np.all(shift > 0.15), shift
    assert np.all(np.abs(centred) < 0.05), centred
    assert np.all(np.abs(fixed) < 0.08), fixed
    np.testing.assert_allclose(f_biased.kpts - f_default.kpts, 0.25, atol=1e-4)
    np.testing.assert_array_equal(f_biased.descriptors, f_default.descriptors)
    assert len({biased.key, default.key, precise.key}) == 3
    # `--set matcher.fine.centre_keypoints=false` reaches the views' and the originals' detectors
    old = FineConfig(centre_keypoints=False, original_detector="sift")
    assert not old.detector.centre_keypoints and not old.originals_detector.centre_keypoints
    assert old.detector.key.endswith("b") and not FineConfig().detector.key.endswith("b")
    assert FineConfig(original_precise_upscale=True).originals_detector.precise_upscale
    assert not FineConfig(original_precise_upscale=True).detector.precise_upscale  # the views keep OpenCV's default
