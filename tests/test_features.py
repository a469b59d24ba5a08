"""Features (matching.features) and the features of simulated views in original pixels
(matching.viewfeatures), on the real graf image 1."""

from __future__ import annotations

import numpy as np
import pytest

from matching.features import DetectorConfig, Features, strongest
from matching.io import load_gray
from matching.store import FeatureStore
from matching.types import ViewParams
from matching.viewfeatures import original_features, pooled_features, view_features

SIFT = DetectorConfig("sift")


def _features(n: int, responses: bool = True) -> Features:
    rng = np.random.default_rng(0)
    return Features(rng.random((n, 2), np.float32) * 100, np.ones(n, np.float32), np.zeros(n, np.float32),
                    rng.random((n, 128), np.float32), rng.random(n, np.float32) if responses else None)


def test_strongest_keeps_the_largest_responses_in_their_order():
    f = _features(50)
    top = strongest(f, 10)
    assert len(top) == 10
    assert set(top.responses) == set(np.sort(f.responses)[-10:])
    idx = [int(np.flatnonzero(f.responses == r)[0]) for r in top.responses]
    assert idx == sorted(idx)  # original order kept
    assert strongest(f, 0) is f and strongest(f, 80) is f
    no_resp = _features(50, responses=False)
    np.testing.assert_array_equal(strongest(no_resp, 5).kpts, no_resp.kpts[:5])


@pytest.fixture(scope="module")
def graf1(shared_data):
    store = FeatureStore()
    store.add_image("g", load_gray(shared_data / "oxford" / "graf" / "img1.png"))
    return store


def _near_original(store: FeatureStore, f: Features, px: float) -> float:
    """Fraction of `f`'s keypoints within `px` of a keypoint of the original image."""
    o = original_features(store, "g", SIFT).kpts
    d = np.sqrt(((f.kpts[:, None, :] - o[None, :, :]) ** 2).sum(-1)).min(axis=1)
    return float(np.mean(d < px))


def test_view_keypoints_map_back_to_the_original_frame(graf1):
    w, h = graf1.image("g").shape[1::-1]
    rotated = view_features(graf1, "g", ViewParams(1.0, 72.0, 1.0), SIFT, "lanczos", True)
    # SIFT is rotation invariant: most keypoints of the rotated view land on the original's own
    assert _near_original(graf1, rotated, 1.0) > 0.6
    tilted = view_features(graf1, "g", ViewParams(2.0, 45.0, 1.0), SIFT, "lanczos", True)
    for f in (rotated, tilted):
        assert len(f) > 500
        assert (f.kpts[:, 0] >= -0.5).all() and (f.kpts[:, 0] < w - 0.5).all()
        assert (f.kpts[:, 1] >= -0.5).all() and (f.kpts[:, 1] < h - 0.5).all()


def test_identity_view_is_the_cached_original(graf1):
    orig = original_features(graf1, "g", SIFT)
    assert view_features(graf1, "g", ViewParams(1.0, 0.0, 1.0), SIFT, "lanczos", True) is orig


def test_pooled_features_concatenate_views_with_their_index(graf1):
    views = [ViewParams(1.0, 0.0, 1.0), ViewParams(1.414214, 0.0, 1.0)]
    pooled, idx = pooled_features(graf1, "g", views, SIFT, "lanczos", None)
    parts = [view_features(graf1, "g", v, SIFT, "lanczos", True) for v in views]
    assert len(pooled) == len(idx) == sum(len(p) for p in parts)
    np.testing.assert_array_equal(pooled.kpts[idx == 1], parts[1].kpts)
    assert set(np.unique(idx)) == {0, 1}


def test_flann_ratio_match_equals_opencv_flann_matcher():
    """Above FLANN_MIN_SIZE, `ratio_match` searches the same seeded k-d forest as OpenCV's
    FlannBasedMatcher, for arrays: the same matches and distances (not squared) as its
    knnMatch + ratio test."""
    import cv2 as cv

    from matching.matching_utils import FLANN_MIN_SIZE, ratio_filter, ratio_match
    from scenes.texture import procedural_texture

    tex = procedural_texture(4.0, 3.0, 220.0, seed=7)
    gray = cv.cvtColor(tex, cv.COLOR_BGR2GRAY) if tex.ndim == 3 else tex
    sift = cv.SIFT.create()
    _, d0 = sift.detectAndCompute(gray, None)
    _, d1 = sift.detectAndCompute(cv.resize(gray, None, fx=0.8, fy=0.8, interpolation=cv.INTER_AREA), None)
    assert min(len(d0), len(d1)) >= FLANN_MIN_SIZE
    m, d = ratio_match(d0, d1, cv.NORM_L2, 0.75, seed=3)
    cv.setRNGSeed(3)
    knn = cv.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64}).knnMatch(d0, d1, k=2)
    m_ref, d_ref = ratio_filter(knn, 0.75)
    assert len(m) > 200
    np.testing.assert_array_equal(m, m_ref)
    np.testing.assert_allclose(d, d_ref, rtol=1e-6)


def test_mutual_matches_keep_exactly_the_cross_checked_ratio_matches():
    """`mutual_matches` keeps a ratio-test match when its target keypoint's own nearest reference
    keypoint is the query (COLMAP's cross-check): checked against exact nearest neighbours both
    ways on SIFT of a procedural texture and its shrunk copy, by brute force and by the k-d forest."""
    import cv2 as cv

    from matching.matching_utils import mutual_matches, ratio_match
    from scenes.texture import procedural_texture

    tex = procedural_texture(4.0, 3.0, 220.0, seed=7)
    gray = cv.cvtColor(tex, cv.COLOR_BGR2GRAY) if tex.ndim == 3 else tex
    sift = cv.SIFT.create()
    _, d0 = sift.detectAndCompute(gray, None)
    _, d1 = sift.detectAndCompute(cv.resize(gray, None, fx=0.7, fy=0.7, interpolation=cv.INTER_AREA), None)
    m, _ = ratio_match(d0, d1, cv.NORM_L2, 0.9, seed=0, flann_min_size=10**9)
    _, back = cv.batchDistance(d1, d0, cv.CV_32F, normType=cv.NORM_L2, K=1)
    truth = back.reshape(-1)[m[:, 1]] == m[:, 0]
    assert 0 < truth.sum() < len(m)  # a loose ratio lets in matches that fail the check
    exact = mutual_matches(m, d0, d1, cv.NORM_L2, flann_min_size=10**9)
    np.testing.assert_array_equal(exact, truth)
    approx = mutual_matches(m, d0, d1, cv.NORM_L2, seed=0, flann_min_size=10)
    assert (approx == truth).mean() > 0.97
    assert mutual_matches(m[:0], d0, d1, cv.NORM_L2).shape == (0,)


def test_shared_forest_gives_the_matches_of_a_fresh_one_from_any_thread():
    """An original's k-d forest (`Features.forest`), built once and searched by two threads at once,
    returns exactly the matches `ratio_match` and `mutual_matches` find with a forest of their own;
    a forest of another seed or of other descriptors is not used."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2 as cv

    from matching.features import detect
    from matching.matching_utils import mutual_matches, ratio_match
    from scenes.texture import procedural_texture

    tex = procedural_texture(4.0, 3.0, 220.0, seed=7)
    gray = cv.cvtColor(tex, cv.COLOR_BGR2GRAY) if tex.ndim == 3 else tex
    f0 = detect(gray, SIFT)
    views = [detect(cv.resize(gray, None, fx=s, fy=s, interpolation=cv.INTER_AREA), SIFT) for s in (0.9, 0.8, 0.7, 0.6)]
    forest = f0.forest(seed=3)
    assert f0.forest(seed=3) is forest and f0.forest(seed=4) is not forest

    def both(fv: Features, shared: bool):
        m, d = ratio_match(fv.descriptors, f0.descriptors, cv.NORM_L2, 0.8, seed=3, forest_t=f0.forest if shared else None)
        keep = mutual_matches(m[:, ::-1].copy(), f0.descriptors, fv.descriptors, cv.NORM_L2, seed=3,
                              forest_q=f0.forest if shared else None)
        return m, d, keep

    with ThreadPoolExecutor(2) as ex:
        shared = list(ex.map(lambda fv: both(fv, True), views * 2))
    assert f0.forest(seed=3) is forest  # built once, by whichever thread came first
    for fv, (m, d, keep) in zip(views * 2, shared, strict=True):
        m_ref, d_ref, keep_ref = both(fv, False)
        assert len(m) > 100 and 0 < keep.sum()
        np.testing.assert_array_equal(m, m_ref)
        np.testing.assert_array_equal(d, d_ref)
        np.testing.assert_array_equal(keep, keep_ref)
    for other in (lambda _: f0.forest(seed=4), views[1].forest):  # another seed's or set's: not searched
        m, _ = ratio_match(views[0].descriptors, f0.descriptors, cv.NORM_L2, 0.8, seed=3, forest_t=other)
        np.testing.assert_array_equal(m, both(views[0], False)[0])


def test_shared_forests_stay_within_their_memory_budget(monkeypatch):
    """Past `FOREST_BUDGET_BYTES` the least recently used forest is dropped (and rebuilt on its next
    use), and a forest goes with its features when they are freed."""
    import gc

    import matching.features as feats

    monkeypatch.setattr(feats, "FOREST_BUDGET_BYTES", 2 * 2000 * feats._FOREST_BYTES_PER_DESCRIPTOR)
    a, b, c = _features(2000), _features(2000), _features(2000)
    fa = a.forest()
    b.forest()
    assert a.forest() is fa  # a is now the most recently used
    c.forest()  # over budget: b goes, a stays
    assert not b.forests and a.forests and c.forests
    assert b.forest() is not None and not a.forests
    before = len(feats._FOREST_LRU)
    del c
    gc.collect()
    assert len(feats._FOREST_LRU) == before - 1


def test_decision_features_land_on_the_full_resolution_keypoints(graf1):
    """Half-size SIFT mapped back to full-resolution pixels (`decision_features`): most of its
    keypoints have their descriptor's nearest full-resolution keypoint within 3 px, a median
    0.1 px away with no bias (a mapping without the pixel-centre terms would be 0.5 px off), at
    the same size."""
    import cv2

    from matching.viewfeatures import decision_features

    full = original_features(graf1, "g", SIFT)
    half = decision_features(graf1, "g", SIFT, 0.5)
    assert 0.3 * len(full) < len(half) < 0.6 * len(full)
    _, idx = cv2.batchDistance(half.descriptors, full.descriptors, cv2.CV_32F, K=1)
    d = half.kpts - full.kpts[idx[:, 0]]
    close = np.linalg.norm(d, axis=1) < 3.0
    assert close.mean() > 0.7
    assert np.all(np.abs(np.median(d[close], axis=0)) < 0.05)
    assert np.median(np.linalg.norm(d[close], axis=1)) < 0.2
    assert abs(np.median(half.sizes[close] / full.sizes[idx[close, 0]]) - 1.0) < 0.05
    assert decision_features(graf1, "g", SIFT, 1.0) is full  # scale 1: the full-resolution set itself


def test_pixel_gate_runs_small_work_side_by_side_and_large_work_alone():
    """`features.PixelGate`: pieces whose pixels fit the budget run at once, a piece that would
    exceed it waits, and a piece larger than the whole budget still runs (alone)."""
    import threading
    import time

    from matching.features import PixelGate

    def peak_concurrency(gate: PixelGate, sizes: list[int]) -> int:
        running, peak, lock = [0], [0], threading.Lock()

        def work(px: int) -> None:
            with gate.hold(px):
                with lock:
                    running[0] += 1
                    peak[0] = max(peak[0], running[0])
                time.sleep(0.05)
                with lock:
                    running[0] -= 1

        threads = [threading.Thread(target=work, args=(px,)) for px in sizes]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=10)
        assert not any(t.is_alive() for t in threads)
        return peak[0]

    assert peak_concurrency(PixelGate(1000), [400, 400]) == 2
    assert peak_concurrency(PixelGate(1000), [600, 600, 600]) == 1
    assert peak_concurrency(PixelGate(1000), [5000]) == 1  # over budget, still admitted
    assert peak_concurrency(PixelGate(0), [1, 1, 1]) == 1  # 0: one at a time
