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
