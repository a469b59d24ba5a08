"""The adaptive per-pair paths (matching.adaptive): the tilt decomposition, the path decision,
the grid views near an estimate, and the matcher on rendered and real pairs: an easy pair takes
the cheap `originals` path, a large-tilt pair a simulated one, the decision and its reason are in
the PairResult, and `adaptive=False` gives exactly the result of the full-grid flow."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from matching.adaptive import (
    AdaptiveConfig,
    ViewpointEstimate,
    estimate_viewpoint,
    hull_spread,
    nearest_views,
    plan_pair,
    tilt_and_longitude,
)
from matching.config import MatcherConfig
from matching.escalation import should_escalate
from matching.io import load_gray, read_homography
from matching.matcher import ExtraAffineMatcher, decide_reference
from matching.metrics import precision
from matching.reference import reason_for, settle_reference
from matching.store import FeatureStore
from matching.strategies import ESCALATION, FINISHING, escalate, fast_path
from matching.types import ViewParams
from matching.views import linear_part, view_grid


@pytest.mark.parametrize("t, phi", [(1.0, 0.0), (1.5, 30.0), (2.0, 0.0), (2.83, 152.74), (5.66, 89.1)])
def test_tilt_and_longitude_invert_the_view_model(t, phi):
    # a similarity (rotation psi, scale lambda) in front does not change (t, phi)
    psi = math.radians(37.0)
    R = np.array([[math.cos(psi), -math.sin(psi)], [math.sin(psi), math.cos(psi)]])
    A = 1.7 * R @ linear_part(ViewParams(t, phi, 1.3))
    t_est, phi_est = tilt_and_longitude(A)
    assert t_est == pytest.approx(t, rel=1e-6)
    if t > 1.0:
        assert min(abs(phi_est - phi), 180.0 - abs(phi_est - phi)) < 1e-6


def test_estimate_from_a_homography_reads_the_tilt_in_the_reference_frame():
    A = linear_part(ViewParams(2.0, 30.0, 1.0))
    H = np.eye(3)
    H[:2, :2] = A
    H[:2, 2] = (50.0, 20.0)
    pts0 = np.array([[0, 0], [400, 0], [0, 300], [400, 300], [200, 150]], np.float64)
    e0 = estimate_viewpoint(H, pts0, 0, (400, 300))
    assert e0.tilt == pytest.approx(2.0) and e0.phi == pytest.approx(30.0)
    assert e0.spread == pytest.approx(1.0) and e0.inliers == 5
    e1 = estimate_viewpoint(H, pts0, 1, (400, 300))  # image 1 simulated: the inverse map, same tilt
    assert e1.tilt == pytest.approx(2.0)
    assert hull_spread(pts0[:2], (400, 300)) == 0.0


def test_plan_pair_thresholds():
    cfg = AdaptiveConfig()
    easy = ViewpointEstimate(inliers=400, spread=0.6, tilt=1.1, phi=0.0)
    assert plan_pair(easy, cfg).path == "originals"
    assert "400 original inliers over 60 % of the image, tilt 1.10 -> originals" == plan_pair(easy, cfg).reason
    assert plan_pair(replace(easy, tilt=2.0), cfg).path == "targeted"
    assert plan_pair(replace(easy, spread=0.05), cfg).path == "targeted"  # clustered: not trusted for originals
    assert plan_pair(replace(easy, inliers=5), cfg).path == "full"
    assert plan_pair(replace(easy, tilt=20.0), cfg).path == "full"
    none = plan_pair(None, cfg, "undecided: only 3 mutual SIFT matches between the originals")
    assert none.path == "full" and none.reason.startswith("undecided: only 3")


def test_nearest_views_are_the_grid_views_around_the_estimate():
    grid = view_grid(MatcherConfig().grid)
    near = nearest_views(grid, 2.1, 175.0, 6)
    assert len(near) == 6 and len(set(near)) == 6
    assert (near[0].t, near[0].phi) == (2.0, 0.0)  # phi 175 is 5 degrees from 0 (period 180)
    assert all(v in grid for v in near)
    assert sum(v.t == 1.0 for v in nearest_views(grid, 1.0, 0.0, 10)) == 1  # t = 1 views count once


# --- the matcher on rendered pairs -----------------------------------------------------------------
def _store(scene, *names):
    store = FeatureStore()
    for n in names:
        store.add_image(n, load_gray(scene / "images" / n))
    return store


def legacy_match(matcher: ExtraAffineMatcher, store: FeatureStore, n0: str, n1: str):
    """The matcher's flow before the adaptive paths (reference, full coarse grid, fast path,
    escalation, finishing steps), from the public building blocks."""
    cfg = matcher.cfg
    ctx = matcher.context(store, n0, n1)
    decision = decide_reference(ctx)
    ctx.reference = settle_reference(decision, ctx.coarse_for, ctx.size(0), cfg.reference, cfg.coarse.accept_inliers)
    best = fast_path(ctx)
    escalation = ""
    if should_escalate(cfg.escalation, best.verified, ctx.coarse_inliers()):
        best = escalate(ctx, best, ESCALATION)
        escalation = best.label
    result = ctx.to_result(best, reason_for(decision, best.reference), decision.f0, decision.f1)
    result.escalation = escalation
    for step in FINISHING:
        if step.applies(ctx, best, result):
            result = step.run(ctx, best, result)
    return matcher.enough_or_empty(result)


def test_easy_rendered_pair_takes_the_originals_path_and_adaptive_off_is_the_full_flow(corner_scene):
    a, b = "view_02.png", "view_03.png"  # neighbouring views of the corner, 17 degrees apart
    store = _store(corner_scene, a, b)
    cfg = replace(MatcherConfig.multiview(), adaptive=True)  # `recon run --preset adaptive`
    r = ExtraAffineMatcher(replace(cfg, workers=1)).match(store, a, b)
    assert r.path == "originals", r.path_reason
    assert "original inliers" in r.path_reason and r.path_reason.endswith("-> originals")
    assert r.best_views == [ViewParams(1.0, 0.0, 1.0)] and r.coarse_scores == []
    assert r.num_inliers >= 200
    assert "coarse" not in r.timings and "originals" in r.timings

    off = replace(cfg, adaptive=False, workers=1)
    r_off = ExtraAffineMatcher(off).match(store, a, b)
    legacy = legacy_match(ExtraAffineMatcher(off), store, a, b)
    assert r_off.path == "full" and len(r_off.coarse_scores) == 45
    # the evidence is recorded whether or not the adaptive paths act on it
    assert r.planned_path == r_off.planned_path == "originals"
    assert r_off.path_reason.startswith("adaptive off -> full grid (the originals' evidence: ")
    assert r_off.path_reason.endswith("-> originals)"), r_off.path_reason
    np.testing.assert_array_equal(r_off.matches, legacy.matches)
    np.testing.assert_array_equal(r_off.kpts0, legacy.kpts0)
    np.testing.assert_array_equal(r_off.kpts1, legacy.kpts1)
    assert [v.key for v in r_off.best_views] == [v.key for v in legacy.best_views]
    assert r_off.reference_reason == legacy.reference_reason
    # the cheap path keeps most of what the full grid finds on an easy pair (measured: 1225 of 1772:
    # the full grid's top views rectify the second wall of the corner as well)
    assert r.num_inliers >= 0.6 * r_off.num_inliers


@pytest.mark.slow
def test_large_tilt_rendered_pair_simulates(facade_extreme_scene):
    a, b = "view_00.png", "view_01.png"  # grazing views of the facade: the originals barely match
    store = _store(facade_extreme_scene, a, b)
    r = ExtraAffineMatcher(replace(MatcherConfig.multiview(), adaptive=True)).match(store, a, b)  # --preset adaptive
    assert r.path == r.planned_path == "full", r.path_reason
    assert "mutual SIFT matches" in r.path_reason
    assert len(r.coarse_scores) == 45
    assert r.best_view is not None and r.best_view.t >= 2.0
    assert r.num_inliers >= 100


# --- real pairs ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_graf_easy_pair_takes_originals_and_graf_1_5_the_simulated_path(shared_data):
    g = shared_data / "oxford" / "graf"
    store = FeatureStore()
    for i in (1, 2, 3, 5):
        store.add_image(f"img{i}", load_gray(g / f"img{i}.png"))
    m = ExtraAffineMatcher(MatcherConfig())
    paper_points = {2: 774, 3: 769, 5: 240}
    expected = {2: "originals", 3: "targeted", 5: "full"}
    for k in (2, 3, 5):
        r = m.match(store, "img1", f"img{k}")
        rep = precision(r, read_homography(g / f"H1to{k}p"), math.sqrt(3.0))
        assert r.path == r.planned_path == expected[k], (k, r.path_reason)
        assert rep.points > paper_points[k], (k, rep.points)
        if k > 2:
            assert r.best_view is not None and r.best_view.t > 1.0
    m.close()


# --- every image's views computed once per run -------------------------------------------------------
class CountingStore(FeatureStore):
    """A FeatureStore that counts how often each (image, key) entry is computed."""

    def __init__(self):
        super().__init__()
        self.computed: dict[tuple[str, str], int] = {}

    def get_or_compute(self, name, key, compute, persist=True):
        def counted():
            self.computed[(name, key)] = self.computed.get((name, key), 0) + 1
            return compute()
        return super().get_or_compute(name, key, counted, persist)


@pytest.mark.slow
@pytest.mark.parametrize("adaptive", [False, True])
def test_each_images_views_are_computed_once_and_shared_by_its_pairs(corner_wide_scene, adaptive):
    names = [p.name for p in sorted((corner_wide_scene / "images").glob("*.png"))]
    assert len(names) == 4
    store = CountingStore()
    for n in names:
        store.add_image(n, load_gray(corner_wide_scene / "images" / n))
    m = ExtraAffineMatcher(replace(MatcherConfig.multiview(), adaptive=adaptive))
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    for a, b in pairs:
        m.match(store, a, b)
    assert store.computed and max(store.computed.values()) == 1  # no entry computed twice
    first_misses = store.misses
    assert first_misses == len(store.computed)
    # per image: at most the 43 distinct ORB views + the coarse target + the SIFT views; far fewer
    # than one set per pair (each image is in 3 pairs)
    grid = len(view_grid(MatcherConfig().grid))
    for n in names:
        orb = [k for (img, k) in store.computed if img == n and k.startswith("orb")]
        assert len(orb) <= grid - 2 + 1
    assert store.hits > 0  # later pairs read what earlier pairs computed
    for a, b in pairs:  # the same pairs again: everything is served from the store
        m.match(store, a, b)
    assert store.misses == first_misses
    m.close()


def test_path_reaches_the_rerun_text_and_the_pair_cache(tmp_path):
    from matching.types import PairResult
    from recon.core.paircache import load_pair_result, save_pair_result
    from recon.viz.rerun_log import pair_markdown

    r = PairResult.empty("extra-affine", "", path="originals", planned_path="originals",
                         path_reason="412 original inliers over 63 % of the image, tilt 1.20 -> originals")
    assert "| path | originals (412 original inliers over 63 % of the image, tilt 1.20 -> originals) |" in \
        pair_markdown("a.jpg", "b.jpg", r, cached=False)
    save_pair_result(tmp_path / "p.npz", r)
    back = load_pair_result(tmp_path / "p.npz")
    assert back is not None and (back.path, back.path_reason, back.planned_path) == (r.path, r.path_reason, "originals")
    sw = r.swapped()
    assert (sw.path, sw.path_reason, sw.planned_path) == (r.path, r.path_reason, r.planned_path)
    assert r.without_matches("x").planned_path == "originals"


def test_finishing_notes_reach_the_rerun_text_the_cache_and_the_report(tmp_path):
    """`PairResult.finishing` (what the guided round and refinement did) survives the pair
    cache, a swap and an emptied result, and shows in the pair's Rerun text."""
    from matching.types import PairResult
    from recon.core.paircache import load_pair_result, save_pair_result
    from recon.viz.rerun_log import pair_markdown

    note = "epipolar round: 412 -> 655 matches; refinement moved 640 of 655 points (median 0.21 px)"
    r = PairResult.empty("extra-affine", "", finishing=note)
    assert f"| finishing | {note} |" in pair_markdown("a.jpg", "b.jpg", r, cached=False)
    save_pair_result(tmp_path / "p.npz", r)
    back = load_pair_result(tmp_path / "p.npz")
    assert back is not None and back.finishing == note
    assert r.swapped().finishing == r.without_matches("x").finishing == note


def test_recon_run_keeps_the_full_grid_unless_asked():
    """Scenes default to the full grid (the cheap paths cost accuracy on wide-baseline facades,
    see matching.config.MatcherConfig.multiview); pair matching and `--preset adaptive` use them."""
    from recon.config import RunConfig, preset
    from recon.core.stages.match import make_matcher

    assert MatcherConfig().adaptive and not MatcherConfig.multiview().adaptive
    assert not make_matcher(RunConfig().match).cfg.adaptive
    assert make_matcher(preset("adaptive").match).cfg.adaptive
