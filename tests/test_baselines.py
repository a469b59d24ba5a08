"""Baseline matchers (SIFT, ORB, ASIFT, AORB) on real Oxford graf pairs."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from matching.baselines import AsiftConfig, make_baseline
from matching.io import load_gray, read_homography
from matching.metrics import precision
from matching.registry import get_matcher
from matching.store import FeatureStore


def _store(img0, img1) -> FeatureStore:
    s = FeatureStore()
    s.add_image("a", img0)
    s.add_image("b", img1)
    return s


def _graf(shared_data, k: int, half: bool = False):
    graf = shared_data / "oxford" / "graf"
    a, b = load_gray(graf / "img1.png"), load_gray(graf / f"img{k}.png")
    H = read_homography(graf / f"H1to{k}p")
    if half:  # INTER_AREA halving; pixel centres: x_half = (x + 0.5) / 2 - 0.5
        S = np.array([[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1.0]])
        a, b = (cv2.resize(x, (x.shape[1] // 2, x.shape[0] // 2), interpolation=cv2.INTER_AREA) for x in (a, b))
        H = S @ H @ np.linalg.inv(S)
    return a, b, H


@pytest.fixture(scope="module")
def graf13_asift(shared_data):
    a, b, H = _graf(shared_data, 3)
    return make_baseline("asift").match(_store(a, b), "a", "b"), H


def test_make_baseline_configs():
    m = make_baseline("orb", max_features=500, ratio=0.8)
    assert m.name == "orb" and m.cfg.max_features == 500 and m.cfg.ratio == 0.8
    assert get_matcher("asift").cfg == AsiftConfig()
    with pytest.raises(ValueError, match="unknown config field"):
        make_baseline("sift", trees=3)
    with pytest.raises(ValueError, match="unknown baseline"):
        make_baseline("surf")
    with pytest.raises(dataclasses.FrozenInstanceError):  # frozen config
        m.cfg.ratio = 0.5  # type: ignore[misc]


def test_final_filter_defaults_to_stock_and_can_match_the_extra_affine_filter():
    """Baselines are stock (OpenCV's asift sample: RANSAC 5 px) unless told to use ours."""
    from matching.matcher import MatcherConfig

    for method in ("sift", "orb", "asift", "aorb"):
        assert make_baseline(method).cfg.ransac_px == 5.0
        same = make_baseline(method, ransac_px=MatcherConfig().final_ransac_px)
        assert same.cfg.ransac_px == 1.5


@pytest.mark.parametrize("method", ["sift", "orb", "aorb"])
def test_featureless_pair_is_empty_not_an_error(method):
    flat = np.full((96, 128), 127, np.uint8)
    r = make_baseline(method).match(_store(flat, flat.copy()), "a", "b")
    assert r.num_matches == 0 and r.reason
    assert r.image_sizes == ((128, 96), (128, 96))
    assert set(r.timings) >= {"detect", "total"}


def test_sift_graf_1_2(shared_data):
    a, b, H = _graf(shared_data, 2)
    r = make_baseline("sift").match(_store(a, b), "a", "b")
    rep = precision(r, H)
    assert r.H_1_from_0 is not None and r.inlier_mask is not None
    assert rep.points == r.num_inliers >= 100
    # Measured: 913 points, 88.4 % at 1.5 px; 1023 points, 85.7 % at 3 px (stock is 5 px). The
    # misses sit mostly in the bottom rows of graf, where matches and the GT homography disagree by
    # 2-5 px; a tighter final filter trades points for precision (1 px: ~750 points, > 99 %).
    assert rep.precision >= 0.8
    tight = precision(make_baseline("sift", ransac_px=1.0).match(_store(a, b), "a", "b"), H)
    assert tight.points >= 100 and tight.precision >= 0.9
    assert set(r.timings) == {"detect", "match", "ransac", "total"}
    assert r.reference is None and r.image_sizes == ((800, 640), (800, 640))


def test_orb_graf_1_2(shared_data):
    a, b, H = _graf(shared_data, 2)
    r = make_baseline("orb").match(_store(a, b), "a", "b")
    rep = precision(r, H)
    assert rep.correct >= 100 and rep.precision >= 0.6


def test_final_homography_off_keeps_all_ratio_matches(shared_data):
    a, b, _ = _graf(shared_data, 2, half=True)
    r = make_baseline("sift", final_homography=False).match(_store(a, b), "a", "b")
    assert r.H_1_from_0 is None and r.inlier_mask is None and r.num_inliers == r.num_matches > 0
    assert "ransac" not in r.timings


def test_features_come_from_the_store(shared_data):
    a, b, _ = _graf(shared_data, 2, half=True)
    store = _store(a, b)
    m = make_baseline("sift")
    r1 = m.match(store, "a", "b")
    assert store.misses == 2
    r2 = m.match(store, "b", "a")  # the other direction reuses both images' features
    assert store.misses == 2 and store.hits >= 2
    assert r2.num_matches > 0 and r1.num_matches > 0


@pytest.mark.slow
def test_asift_beats_sift_on_graf_1_3(shared_data, graf13_asift):
    r_asift, H = graf13_asift
    a, b, _ = _graf(shared_data, 3)
    r_sift = make_baseline("sift").match(_store(a, b), "a", "b")
    c_asift, c_sift = precision(r_asift, H).correct, precision(r_sift, H).correct
    assert c_asift > c_sift
    assert c_asift >= 1000  # measured ~7000
    assert r_asift.H_1_from_0 is not None


@pytest.mark.slow
def test_asift_is_deterministic(shared_data):
    """Two fresh runs (FLANN KD-trees and RANSAC re-seeded) give identical matches."""
    a, b, _ = _graf(shared_data, 3, half=True)
    m = make_baseline("asift")
    r1 = m.match(_store(a, b), "a", "b")
    r2 = m.match(_store(a, b), "a", "b")
    assert r1.num_matches > 50
    np.testing.assert_array_equal(r1.matches, r2.matches)
    np.testing.assert_array_equal(r1.distances, r2.distances)
    np.testing.assert_array_equal(r1.inlier_mask, r2.inlier_mask)
    np.testing.assert_array_equal(r1.H_1_from_0, r2.H_1_from_0)
    np.testing.assert_array_equal(r1.kpts0, r2.kpts0)
