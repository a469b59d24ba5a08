"""Coarse search (matching.coarse): every view of the reference scored against the target, on
the real graf 1-3 pair (about 40 degrees of viewpoint change)."""

from __future__ import annotations

import numpy as np
import pytest

from matching.coarse import CoarseConfig, coarse_search, coarse_view_features, rank_views
from matching.io import load_gray, read_homography
from matching.metrics import project
from matching.store import FeatureStore
from matching.types import CoarseScore, ViewParams
from matching.views import view_grid


@pytest.fixture(scope="module")
def graf_1_3(shared_data):
    g = shared_data / "oxford" / "graf"
    store = FeatureStore()
    store.add_image("img1", load_gray(g / "img1.png"))
    store.add_image("img3", load_gray(g / "img3.png"))
    scores = coarse_search(store, "img1", "img3", view_grid(), CoarseConfig())
    return store, scores, read_homography(g / "H1to3p")


def test_a_tilted_view_wins_with_more_inliers_than_the_original(graf_1_3):
    _, scores, _ = graf_1_3
    assert [c.view for c in scores] == view_grid()  # every view, in grid order
    best = rank_views(scores)[0]
    t1 = [c for c in scores if c.view.t == 1.0]
    assert best.view.t > 1.0
    assert best.inliers > 2 * max(c.inliers for c in t1)
    assert best.score == best.inliers  # ranked by RANSAC inliers by default


def test_the_best_views_homography_agrees_with_the_ground_truth(graf_1_3):
    _, scores, H_gt = graf_1_3
    best = rank_views(scores)[0]
    assert best.H_target_from_ref is not None  # original reference pixels -> target pixels
    grid = np.array([[x, y] for x in range(100, 800, 100) for y in range(100, 600, 100)], np.float64)
    err = np.linalg.norm(project(best.H_target_from_ref, grid) - project(H_gt, grid), axis=1)
    assert np.median(err) < 4.0


def test_t1_views_are_scored_once(graf_1_3):
    """ORB is rotation invariant: the t = 1 views (rotations only) share one score."""
    _, scores, _ = graf_1_3
    t1 = [c for c in scores if c.view.t == 1.0]
    assert len(t1) == 3
    assert len({(c.matches, c.inliers, c.score) for c in t1}) == 1


def test_rank_by_matches_is_the_papers_ranking(graf_1_3):
    store, _, _ = graf_1_3
    views = view_grid()
    scores = coarse_search(store, "img1", "img3", views, CoarseConfig(rank_by="matches"))
    assert all(c.score == c.matches for c in scores)
    ranked = rank_views(scores)
    assert [c.score for c in ranked] == sorted((c.score for c in scores), reverse=True)


def test_rank_views_breaks_ties_by_matches_then_smaller_tilt():
    v = [ViewParams(2.0, 0.0), ViewParams(1.414214, 0.0), ViewParams(1.414214, 45.0)]
    scores = [CoarseScore(v[0], 50, 30, 30.0), CoarseScore(v[1], 50, 30, 30.0), CoarseScore(v[2], 60, 30, 30.0)]
    assert [c.view for c in rank_views(scores)] == [v[2], v[1], v[0]]


def test_coarse_view_features_are_rendered_small_and_cached(graf_1_3):
    store, _, _ = graf_1_3
    cfg = CoarseConfig()
    view = ViewParams(2.0, 36.0, 2.0)
    misses = store.misses
    f = coarse_view_features(store, "img1", view, cfg)  # computed by the search already
    assert store.misses == misses and 0 < len(f) <= cfg.orb_features
    w, h = store.image("img1").shape[1::-1]
    assert f.kpts[:, 0].min() >= -0.5 and f.kpts[:, 0].max() < w - 0.5  # original pixels
    assert f.kpts[:, 1].min() >= -0.5 and f.kpts[:, 1].max() < h - 0.5
