"""Coarse search (matching.coarse): every view of the reference scored against the target, on
the real graf 1-3 pair (about 40 degrees of viewpoint change); the coarse-to-fine search finds
the full grid's best views on graf 1-5 with fewer views scored."""

from __future__ import annotations

import numpy as np
import pytest

from matching.coarse import (
    CoarseConfig,
    coarse_search,
    coarse_view_features,
    grid_neighbours,
    rank_views,
    seed_views,
)
from matching.fine import select_fine_views
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
    scores = coarse_search(store, "img1", "img3", view_grid(), CoarseConfig(search="grid"))
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
    scores = coarse_search(store, "img1", "img3", views, CoarseConfig(rank_by="matches", search="grid"))
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


def test_the_sparse_passes_cover_the_grid_once_and_t1_once():
    views = [v for v in view_grid() if v.t != 1.0 or v.phi == 0.0]  # what coarse_search scores
    passes = [seed_views(views, 3, phase) for phase in range(3)]
    flat = [v for p in passes for v in p]
    assert sorted(flat) == sorted(views)  # every view exactly once over the passes
    assert 12 <= len(passes[0]) <= 16  # about a third of the 43
    tilts = sorted({v.t for v in views})
    for k, t in enumerate(tilts[1:], start=1):  # the k-th tilt starts at its (k mod 3)-th longitude
        at_t = [v for v in views if v.t == t]
        assert [v for v in passes[0] if v.t == t][0] == at_t[k % 3]


def test_grid_neighbours_wrap_around_180_degrees_and_link_adjacent_tilts():
    views = [v for v in view_grid() if v.t != 1.0 or v.phi == 0.0]
    nb = grid_neighbours(views)
    t283 = [v for v in views if abs(v.t - 2.828427) < 1e-6]
    first, last = t283[0], t283[-1]  # phi 0 and phi 178.2: one step apart across 180
    assert last in nb[first] and first in nb[last]
    assert any(abs(u.t - 4.0) < 1e-6 for u in nb[first]) and any(abs(u.t - 2.0) < 1e-6 for u in nb[first])
    assert all(v in nb[u] for v in views for u in nb[v])  # symmetric
    t1 = views[0]
    assert {u for u in nb[t1]} == {v for v in views if abs(v.t - 1.414214) < 1e-6}


@pytest.mark.parametrize("side", [0, 1])
def test_coarse_to_fine_finds_the_full_grids_best_views_on_graf_1_5(shared_data, side):
    """Both sides of graf 1-5 (about 60 degrees): image 1 simulated has a strong peak (t 2.83,
    phi 0 / 178), image 5 simulated a weak one (31 inliers); the coarse-to-fine search scores
    about half the views and keeps the two views the fine stage fuses."""
    g = shared_data / "oxford" / "graf"
    store = FeatureStore()
    store.add_image("img1", load_gray(g / "img1.png"))
    store.add_image("img5", load_gray(g / "img5.png"))
    ref, target = ("img1", "img5") if side == 0 else ("img5", "img1")
    full = coarse_search(store, ref, target, view_grid(), CoarseConfig(search="grid"))
    c2f = coarse_search(store, ref, target, view_grid(), CoarseConfig())
    assert rank_views(full)[0].inliers >= 25
    assert select_fine_views(rank_views(c2f), 2) == select_fine_views(rank_views(full), 2)
    scored = [c for c in c2f if c.view.t > 1.0]
    assert len(scored) <= 30 < len([v for v in view_grid() if v.t > 1.0])
    by_view = {c.view: c for c in full}
    assert all((c.matches, c.inliers) == (by_view[c.view].matches, by_view[c.view].inliers) for c in c2f)
    assert [c.view for c in c2f] == [v for v in view_grid() if v in {c.view for c in c2f}]  # grid order


def test_coarse_to_fine_scores_every_view_without_overlap(graf_1_3):
    """No view of graf 1 against an unrelated image (uniform noise) reaches
    `search_min_inliers`: every view is scored, as with the grid."""
    store, _, _ = graf_1_3
    img = store.image("img3")
    store.add_image("noise", np.ascontiguousarray(np.random.default_rng(0).integers(0, 256, img.shape, np.uint8)))
    scores = coarse_search(store, "img1", "noise", view_grid(), CoarseConfig())
    assert max(c.inliers for c in scores) < CoarseConfig().search_min_inliers
    assert [c.view for c in scores] == view_grid()


def test_coarse_to_fine_changes_nothing_on_an_easy_pair(shared_data):
    """graf 1-2 on the full path (adaptive off): the coarse-to-fine search picks the same fine
    views, so the final matches are identical to the full grid's."""
    from matching.config import MatcherConfig
    from matching.matcher import ExtraAffineMatcher

    g = shared_data / "oxford" / "graf"
    results = []
    for search in ("grid", "coarse-to-fine"):
        store = FeatureStore()
        store.add_image("img1", load_gray(g / "img1.png"))
        store.add_image("img2", load_gray(g / "img2.png"))
        cfg = MatcherConfig.from_overrides(adaptive=False, workers=1, coarse__search=search)
        results.append(ExtraAffineMatcher(cfg).match(store, "img1", "img2"))
    grid, c2f = results
    assert len(c2f.coarse_scores) < len(grid.coarse_scores) == 45
    assert [v.key for v in c2f.best_views] == [v.key for v in grid.best_views]
    np.testing.assert_array_equal(c2f.matches, grid.matches)
    np.testing.assert_array_equal(c2f.kpts0, grid.kpts0)
    np.testing.assert_array_equal(c2f.inlier_mask, grid.inlier_mask)
