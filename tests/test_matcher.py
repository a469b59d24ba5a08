"""The extra-affine matcher end to end on real pairs with ground-truth homographies."""

from __future__ import annotations

import numpy as np
import pytest

from matching.io import load_gray, read_homography
from matching.matcher import ExtraAffineMatcher, MatcherConfig
from matching.metrics import precision
from matching.registry import get_matcher
from matching.store import FeatureStore

needs_graf = pytest.mark.requires_shared("oxford/graf/img1.png", "oxford/graf/img3.png", "oxford/graf/img4.png")


def _store(shared_data, *names):
    store = FeatureStore()
    for n in names:
        store.add_image(n, load_gray(shared_data / "oxford" / "graf" / f"{n}.png"))
    return store


@pytest.mark.slow
@needs_graf
def test_graf_1_4_precision_above_90_percent(shared_data):
    store = _store(shared_data, "img1", "img4")
    result = get_matcher("extra-affine").match(store, "img1", "img4")
    rep = precision(result, read_homography(shared_data / "oxford" / "graf" / "H1to4p"))
    assert rep.points >= 400
    assert rep.precision >= 0.90
    assert result.reference == 0  # the frontal image 1 is the closer, more detailed view
    assert result.best_view is not None and result.best_view.t > 1.0  # a tilted view won
    assert len(result.coarse_scores) == 45
    assert result.escalation == ""
    assert {"reference", "coarse", "fine", "total"} <= set(result.timings)


@pytest.mark.slow
@needs_graf
def test_results_are_deterministic_and_views_are_reused(shared_data):
    store = _store(shared_data, "img1", "img3", "img4")
    m = ExtraAffineMatcher(MatcherConfig(seed=7))
    r1 = m.match(store, "img1", "img3")
    misses_after_first = store.misses
    r2 = m.match(store, "img1", "img4")  # same reference image: its views come from the cache
    assert store.misses - misses_after_first < misses_after_first / 2
    fresh = _store(shared_data, "img1", "img3")
    r1b = ExtraAffineMatcher(MatcherConfig(seed=7)).match(fresh, "img1", "img3")
    np.testing.assert_array_equal(r1.matches, r1b.matches)
    np.testing.assert_array_equal(r1.inlier_mask, r1b.inlier_mask)
    assert r2.num_inliers > 100


@pytest.mark.slow
@needs_graf
def test_swapped_inputs_give_the_same_geometry(shared_data):
    store = _store(shared_data, "img1", "img3")
    m = get_matcher("extra-affine")
    ab, ba = m.match(store, "img1", "img3"), m.match(store, "img3", "img1")
    assert ab.reference == 0 and ba.reference == 1
    H = read_homography(shared_data / "oxford" / "graf" / "H1to3p")
    assert precision(ba, np.linalg.inv(H)).precision >= 0.9


@pytest.mark.slow
@needs_graf
def test_a_pair_that_does_not_match_returns_a_reason_not_an_error(shared_data):
    rng = np.random.default_rng(0)
    noise = (rng.random((480, 640)) * 255).astype(np.uint8)
    store = _store(shared_data, "img1")
    store.add_image("noise", noise)
    cfg = MatcherConfig.from_overrides(escalation__two_sided=False)
    r = ExtraAffineMatcher(cfg).match(store, "img1", "noise")
    assert r.num_inliers < 20
    assert r.reason or r.num_matches < 20


def test_paper_variant_is_selectable():
    cfg = MatcherConfig.from_overrides(variant="paper")
    assert cfg.reference.mode == "paper" and cfg.fine_top_k == 1 and not cfg.escalation.enabled
    assert cfg.coarse.rank_by == "matches"
    with pytest.raises(ValueError, match="unknown"):
        MatcherConfig.from_overrides(nonsense=1)
