"""Each strategy of the matcher in isolation on the real graf 1-2 pair (matching.strategies):
the fast path, the escalation levels (topk, swap, view pairs, two-sided) and the finishing steps
(final homography, guided rounds under H and under F), run on one shared MatchContext."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from matching.config import MatcherConfig
from matching.context import Attempt, MatchContext
from matching.escalation import should_escalate
from matching.fine import FineMatches, epipolar_pair_distance
from matching.geometry import scale_1_from_0
from matching.guided import trusted_fundamental
from matching.io import load_gray, read_homography
from matching.matcher import ExtraAffineMatcher, decide_reference
from matching.metrics import precision, precision_of_points
from matching.reference import settle_reference
from matching.store import FeatureStore
from matching.strategies import (
    ESCALATION,
    FINISHING,
    FinalHomography,
    GuidedEpipolar,
    GuidedHomography,
    ReferenceFromFinalHomography,
    Swap,
    TopK,
    TwoSided,
    ViewPairs,
    fast_path,
)
from matching.views import GridConfig

# small grids keep the two-sided levels to a few seconds on graf
SMALL_TWO_SIDED = GridConfig(n=1, ds=0.0, scale_mode="none")


@pytest.fixture(scope="module")
def graf(shared_data):
    g = shared_data / "oxford" / "graf"
    store = FeatureStore()
    store.add_image("img1", load_gray(g / "img1.png"))
    store.add_image("img2", load_gray(g / "img2.png"))
    return store, read_homography(g / "H1to2p")


def _settled(store, cfg: MatcherConfig):
    """A context after the reference and coarse stages, as the matcher leaves it."""
    m = ExtraAffineMatcher(cfg)
    ctx = m.context(store, "img1", "img2")
    decision = decide_reference(ctx)
    ctx.reference = settle_reference(decision, ctx.coarse_for, ctx.size(0), cfg.reference, cfg.coarse.accept_inliers)
    return ctx, decision


@pytest.fixture(scope="module")
def settled(graf):
    store, _ = graf
    cfg = MatcherConfig(workers=1, escalation=replace(MatcherConfig().escalation, two_sided_grid=SMALL_TWO_SIDED))
    ctx, _ = _settled(store, cfg)
    return ctx, fast_path(ctx)


def test_fast_path_solves_graf_1_2_without_escalating(graf, settled):
    _, H = graf
    ctx, fast = settled
    assert fast.label == "" and fast.reference == 0  # img1 is the frontal, more detailed view
    assert len(fast.views) == ctx.cfg.fine_top_k
    assert fast.verified >= ctx.cfg.escalation.min_inliers
    assert not should_escalate(ctx.cfg.escalation, fast.verified, ctx.coarse_inliers())
    res = FinalHomography().run(ctx, fast, ctx.to_result(fast))
    rep = precision(res, H)
    assert rep.points >= 800 and rep.precision >= 0.95


def test_the_matcher_never_enters_the_escalation_list_on_graf_1_2(graf, monkeypatch):
    store, H = graf

    def boom(*a, **k):
        raise AssertionError("an escalation level ran on graf 1-2")

    for level in ESCALATION:
        monkeypatch.setattr(type(level), "run", boom)
    res = ExtraAffineMatcher(MatcherConfig(workers=1)).match(store, "img1", "img2")
    assert res.escalation == "" and "escalation" not in res.timings
    assert precision(res, H).precision >= 0.95


def test_topk_fuses_more_views_of_the_same_side(graf, settled):
    _, H = graf
    ctx, fast = settled
    level = TopK()
    assert level.applies(ctx, fast)
    att = level.run(ctx, fast)
    assert att.label == "topk" and att.reference == fast.reference
    assert len(att.views) == ctx.cfg.escalation.top_k > len(fast.views)
    assert att.views[:len(fast.views)] == fast.views  # the same ranking, further down
    assert att.verified > fast.verified
    assert not TopK().applies(replace(ctx, cfg=replace(ctx.cfg, fine_top_k=4)), fast)


@pytest.mark.slow
def test_swap_simulates_the_other_image(graf, settled):
    _, H = graf
    ctx, fast = settled
    att = Swap().run(ctx, fast)
    assert att.label == "swap" and att.reference == 1 - fast.reference
    assert set(ctx.coarse) == {0, 1}  # the other side's coarse search ran for it
    assert att.coarse is ctx.coarse[att.reference]
    res = FinalHomography().run(ctx, att, ctx.to_result(att))
    assert res.reference == 1  # the result says which image was simulated
    assert precision(res, H).precision >= 0.8  # still the right geometry, in image 0 -> 1 order


@pytest.mark.slow
def test_view_pairs_level_matches_view_against_view(graf):
    store, H = graf
    ctx, _ = _settled(store, MatcherConfig(workers=1, grid=GridConfig(n=2)))  # 12 x 12 view pairs
    fast = fast_path(ctx)
    att = ViewPairs().run(ctx, fast)
    assert att.label == "pairs" and att.both_simulated and att.views == []
    assert att.verified >= ctx.cfg.escalation.min_inliers
    assert len(att.fine.per_view) == ctx.cfg.escalation.pair_top_k  # the best view pairs, by key
    res = FinalHomography().run(ctx, att, ctx.to_result(att))
    assert precision(res, H).precision >= 0.95


@pytest.mark.slow
def test_two_sided_level_pools_both_images(graf, settled):
    _, H = graf
    ctx, fast = settled
    att = TwoSided().run(ctx, fast)
    assert att.label == "two-sided" and att.both_simulated and att.views == []
    assert att.verified >= ctx.cfg.escalation.min_inliers
    res = FinalHomography().run(ctx, att, ctx.to_result(att))
    assert precision(res, H).precision >= 0.9


def test_guided_round_under_h_keeps_precision_and_inliers(graf, settled):
    _, H = graf
    ctx, fast = settled
    first = FinalHomography().run(ctx, fast, ctx.to_result(fast))
    assert first.H_1_from_0 is not None
    step = GuidedHomography()
    assert step.applies(ctx, fast, first)
    guided = step.run(ctx, fast, first)
    # the round replaces the first result only by one with as many inliers (on graf 1-2 the two
    # are within 1 %: 1059 guided against 1071, so the first is kept; 1070 against 1068 before
    # OpenCV's SIFT keypoints were centred)
    assert guided.num_inliers >= first.num_inliers >= 1000
    assert precision(guided, H).precision >= 0.95
    assert guided.reference_reason == first.reference_reason and guided.best_views == fast.views
    assert not GuidedEpipolar().applies(ctx, fast, first)  # under H, never also under F


def test_guided_round_under_f_adds_f_consistent_matches(graf):
    store, H = graf
    # a 1.5 px band: at the default 1 px the F-filtered union of graf 1-2 is within a few matches
    # of the first round (2866 against 2859 with two warps per view, equal with one), so the step
    # keeps the first round there and the test would measure rounding, not the round
    ctx, _ = _settled(store, replace(MatcherConfig.multiview(), workers=1, guided_epipolar_px=1.5))
    fast = fast_path(ctx)
    first = ctx.to_result(fast)
    assert not FinalHomography().applies(ctx, fast, first) and not GuidedHomography().applies(ctx, fast, first)
    step = GuidedEpipolar()
    assert step.applies(ctx, fast, first)
    guided = step.run(ctx, fast, first)
    assert guided.num_matches > first.num_matches
    F = trusted_fundamental(ctx, fast.fine)  # reference (image 0 here) -> target
    assert F is not None and fast.reference == 0
    p0, p1 = guided.matched_points(inliers_only=False)
    assert np.all(epipolar_pair_distance(F, p0, p1) <= ctx.cfg.guided_epipolar_px + 1e-6)
    before = precision_of_points(*first.matched_points(inliers_only=False), H)
    after = precision_of_points(p0, p1, H)
    assert after.correct > before.correct


def test_reference_from_final_homography_runs_only_for_two_sided_attempts(graf, settled):
    ctx, fast = settled
    res = FinalHomography().run(ctx, fast, ctx.to_result(fast))
    step = ReferenceFromFinalHomography()
    assert not step.applies(ctx, fast, res)
    assert step.applies(ctx, replace(fast, both_simulated=True), res)
    out = step.run(ctx, replace(fast, both_simulated=True), res)
    assert out.reference == 0 and "both images simulated, final homography: image 0" in out.reference_reason


def test_finishing_steps_are_in_order():
    names = [type(s).__name__ for s in FINISHING]
    assert names == ["FinalHomography", "GuidedHomography", "GuidedEpipolar", "RefinePoints",
                     "ReferenceFromFinalHomography"]
    assert [lvl.label for lvl in ESCALATION] == ["topk", "swap", "pairs", "steep", "mser", "two-sided"]


def test_reference_from_final_homography_reads_image_0s_size_from_the_store():
    """Images of different sizes, image 1 simulated: the scale is read at image 0's centre (the
    result's `image_sizes` are not what this step trusts)."""
    store = FeatureStore()
    store.add_image("a", np.zeros((100, 200), np.uint8))
    store.add_image("b", np.zeros((300, 400), np.uint8))
    ctx = MatchContext(store, ("a", "b"), MatcherConfig(), views=[])
    H = np.array([[1.0, 0, 0], [0, 1.0, 0], [-0.004, 0, 1.6]])  # < 1 at a's centre, > 1 at b's
    assert scale_1_from_0(H, (200, 100)) < 1 < scale_1_from_0(H, (400, 300))
    k = np.zeros((40, 2), np.float32)
    fm = FineMatches(k, k.copy(), np.stack([np.arange(40)] * 2, 1).astype(np.int32), np.zeros(40, np.float32), {})
    att = Attempt("two-sided", 1, fm, [], [], 40, both_simulated=True)
    res = ctx.to_result(att)
    res.H_1_from_0, res.inlier_mask = H, np.ones(40, bool)
    out = ReferenceFromFinalHomography().run(ctx, att, res)
    assert out.reference == 0 and out.reference_reason.endswith("image 0 is 1.04x larger")


def test_results_of_image_1_simulated_keep_image_sizes_in_image_order():
    store = FeatureStore()
    store.add_image("a", np.zeros((100, 200), np.uint8))
    store.add_image("b", np.zeros((300, 400), np.uint8))
    ctx = MatchContext(store, ("a", "b"), MatcherConfig(), views=[])
    k = np.zeros((4, 2), np.float32)
    fm = FineMatches(k, k.copy(), np.stack([np.arange(4)] * 2, 1).astype(np.int32), np.zeros(4, np.float32), {})
    res = ctx.to_result(Attempt("swap", 1, fm, [], [], 4))
    assert res.image_sizes == ((200, 100), (400, 300))
