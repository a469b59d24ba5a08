"""Reference selection (Eq. 1 and the robust variant) on a pair rendered by zooming a real image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from matching.features import DetectorConfig, detect
from matching.reference import (
    ReferenceConfig,
    ReferenceDecision,
    choose_reference,
    larger_image,
    paper_coefficient,
    reason_for,
    reference_from_final_homography,
    settle_reference,
)
from matching.types import CoarseScore, PairResult, ViewParams

SIZE0 = (801, 601)  # (w, h) of image 0: centre (400, 300)


def test_paper_coefficient_sign_follows_segment_lengths():
    a = np.array([[0, 0], [10, 0], [10, 10]], np.float32)
    d = np.zeros(3, np.float32)
    assert paper_coefficient(a * 2, a, d) > 0  # source segments longer: source is more detailed
    assert paper_coefficient(a, a * 2, d) < 0
    # descriptor distances weight the terms down (1 - (d_i + d_i+1) / 1000)
    weighted = paper_coefficient(a * 2, a, np.full(3, 250, np.float32))
    assert weighted == pytest.approx(0.5 * paper_coefficient(a * 2, a, d))


def _zoom_pair(img: np.ndarray, zoom: float) -> tuple[np.ndarray, np.ndarray]:
    """(far, near): the whole image, and its centre crop enlarged by `zoom` (a closer camera)."""
    h, w = img.shape
    cw, ch = int(w / zoom), int(h / zoom)
    x0, y0 = (w - cw) // 2, (h - ch) // 2
    near = cv2.resize(img[y0:y0 + ch, x0:x0 + cw], (w, h), interpolation=cv2.INTER_CUBIC)
    return img, near


@pytest.mark.requires_shared("oxford/graf/img1.png")
@pytest.mark.parametrize("mode", ["robust", "paper"])
def test_closer_camera_becomes_the_reference(shared_data, mode):
    img = cv2.imread(str(shared_data / "oxford" / "graf" / "img1.png"), cv2.IMREAD_GRAYSCALE)
    far, near = _zoom_pair(img, 1.8)
    det = DetectorConfig("sift")
    f_far, f_near = detect(far, det), detect(near, det)
    cfg = ReferenceConfig(mode=mode)
    assert choose_reference(f_far, f_near, cfg).reference == 1
    assert choose_reference(f_near, f_far, cfg).reference == 0
    if mode == "robust":
        d = choose_reference(f_far, f_near, cfg)
        assert d.scale_1_from_0 == pytest.approx(1.8, rel=0.05)


@pytest.mark.requires_shared("oxford/graf/img1.png")
def test_unrelated_images_leave_the_reference_undecided(shared_data):
    img = cv2.imread(str(shared_data / "oxford" / "graf" / "img1.png"), cv2.IMREAD_GRAYSCALE)
    noise = (np.random.default_rng(0).random(img.shape) * 255).astype(np.uint8)
    noise = cv2.GaussianBlur(noise, (0, 0), 2.0)
    det = DetectorConfig("sift")
    d = choose_reference(detect(img, det), detect(noise, det), ReferenceConfig())
    assert d.reference is None
    assert "undecided" in d.reason


def _zoom_about_centre(s: float) -> np.ndarray:
    """Zoom by `s` about image 0's centre: image 1 shows the scene `s` times larger."""
    c = np.array([[1, 0, 400.0], [0, 1, 300.0], [0, 0, 1]])
    return c @ np.diag([s, s, 1.0]) @ np.linalg.inv(c)


class _Coarse:
    """A fake coarse search: side -> scores, recording which sides were searched."""

    def __init__(self, by_side: dict[int, list[CoarseScore]]):
        self.by_side, self.searched = by_side, []

    def __call__(self, side: int) -> list[CoarseScore]:
        self.searched.append(side)
        return self.by_side[side]


def _graf_store(folder, *names: str):
    from matching.io import load_gray
    from matching.store import FeatureStore

    store = FeatureStore()
    for n in names:
        store.add_image(n, load_gray(folder / f"{n}.png"))
    return store


def _view(inliers: int, H: np.ndarray | None, score: float | None = None, t: float = 2.0) -> CoarseScore:
    return CoarseScore(ViewParams(t, 0.0, 1.0), inliers + 10, inliers, float(inliers if score is None else score), H)


def _undecided(f0: float = 2.0, f1: float = 1.0) -> ReferenceDecision:
    return ReferenceDecision(None, f0, f1, "undecided: only 3 mutual SIFT matches between the originals")


def test_larger_image_rule():
    assert larger_image(0.5, 1.1) == 0 and larger_image(2.0, 1.1) == 1
    assert larger_image(1.05, 1.1) is None and larger_image(1 / 1.05, 1.1) is None
    assert larger_image(float("nan"), 1.1) is None


def test_a_decided_reference_is_kept_and_only_its_side_searched():
    coarse = _Coarse({1: [_view(5, None)]})
    d = ReferenceDecision(1, 0.0, 0.0, "image 1 is 1.50x larger (80 inliers)")
    assert settle_reference(d, coarse, SIZE0, ReferenceConfig(), accept_inliers=40) == 1
    assert coarse.searched == [1] and d.reason == "image 1 is 1.50x larger (80 inliers)"
    assert reason_for(d, 1) == d.reason


@pytest.mark.parametrize("first, H_target_from_first, expected, searched", [
    (0, _zoom_about_centre(0.5), 0, {0}),  # image 0 shrinks into image 1: image 0 is larger
    (0, _zoom_about_centre(2.0), 1, {0, 1}),  # image 1 is larger: its side is searched too
    (1, _zoom_about_centre(0.5), 1, {1}),  # the view maps image 1 -> image 0, shrinking: image 1 larger
    (0, _zoom_about_centre(1.05), 0, {0}),  # equal within the tolerance: the first side stays
    (1, _zoom_about_centre(1.05), 1, {1}),
])
def test_an_undecided_reference_is_settled_by_the_first_sides_verified_view(first, H_target_from_first, expected,
                                                                             searched):
    coarse = _Coarse({first: [_view(3, None, t=1.0), _view(25, H_target_from_first)], 1 - first: [_view(5, None)]})
    d = _undecided(*((2.0, 1.0) if first == 0 else (1.0, 2.0)))
    assert settle_reference(d, coarse, SIZE0, ReferenceConfig(), accept_inliers=40) == expected
    assert set(coarse.searched) == searched and d.reference == expected
    assert f"so image {expected} is the reference" in d.reason and "coarse view geometry" in d.reason
    assert reason_for(d, expected) == d.reason


def test_the_other_side_is_searched_near_the_first_sides_view_when_given_coarse_near():
    """(0, H 2x): image 1 is larger, so its side is searched, through `coarse_near` with the
    view's homography as image 0 -> image 1 (the first side's own map), not through `coarse_for`."""
    H = _zoom_about_centre(2.0)
    coarse = _Coarse({0: [_view(25, H)], 1: [_view(5, None)]})
    near: list[tuple[int, np.ndarray]] = []
    d = _undecided()
    assert settle_reference(d, coarse, SIZE0, ReferenceConfig(), 40, lambda s, H10: near.append((s, H10)) or []) == 1
    assert coarse.searched == [0] and [s for s, _ in near] == [1]
    np.testing.assert_allclose(near[0][1], H)
    # first side 1: its view maps image 1 -> image 0, handed over inverted (image 0 -> image 1)
    coarse = _Coarse({1: [_view(25, _zoom_about_centre(2.0))], 0: [_view(5, None)]})
    near.clear()
    assert settle_reference(_undecided(1.0, 2.0), coarse, SIZE0, ReferenceConfig(), 40,
                            lambda s, H10: near.append((s, H10)) or []) == 0
    np.testing.assert_allclose(near[0][1], _zoom_about_centre(0.5), atol=1e-12)


def test_graf_1_5_settles_image_1_from_image_5s_view_and_searches_only_views_near_it(shared_data):
    """graf 1-5: 10 mutual SIFT matches leave the reference undecided, Eq. 1 prefers image 5,
    whose best view (31 ORB inliers) says image 1 is the reference; image 1 is then searched on
    the 6 views nearest the tilt that view implies, and they hold the full grid's two best."""
    from matching.coarse import CoarseConfig, coarse_search, rank_views
    from matching.config import MatcherConfig
    from matching.fine import select_fine_views
    from matching.matcher import ExtraAffineMatcher, decide_reference

    g = shared_data / "oxford" / "graf"
    m = ExtraAffineMatcher(MatcherConfig(workers=1))
    store = _graf_store(g, "img1", "img5")
    ctx = m.context(store, "img1", "img5")
    decision = decide_reference(ctx)
    assert decision.reference is None and decision.f1 > decision.f0
    cfg = m.cfg
    ref = settle_reference(decision, ctx.coarse_for, ctx.size(0), cfg.reference, cfg.coarse.accept_inliers,
                           ctx.coarse_near)
    assert ref == 0 and set(ctx.coarse) == {0, 1}
    assert len(ctx.coarse[0]) == cfg.paths.targeted_views
    full = coarse_search(store, "img1", "img5", m.views, CoarseConfig(search="grid"))
    assert select_fine_views(rank_views(ctx.coarse[0]), 2) == select_fine_views(rank_views(full), 2)


def test_without_a_verified_view_both_sides_are_searched_and_the_better_one_wins():
    coarse = _Coarse({0: [_view(12, _zoom_about_centre(0.5))], 1: [_view(15, None)]})  # 12 < 40 / 2
    d = _undecided()
    assert settle_reference(d, coarse, SIZE0, ReferenceConfig(), accept_inliers=40) == 1
    assert coarse.searched[0] == 0 and set(coarse.searched) == {0, 1}
    assert d.reference is None  # still undecided: the result's reason says why image 1 was used
    assert reason_for(d, 1).endswith("; chose image 1 by coarse score")


def _two_sided_result(scale: float, n_inliers: int) -> PairResult:
    z = np.zeros((40, 2), np.float32)
    return PairResult("extra-affine", z, z.copy(), np.stack([np.arange(40)] * 2, 1).astype(np.int32),
                      np.zeros(40, np.float32), reference=0, reference_reason="undecided",
                      H_1_from_0=_zoom_about_centre(scale), inlier_mask=np.arange(40) < n_inliers)


def test_reference_from_the_final_homography():
    res = reference_from_final_homography(_two_sided_result(1.6, 35), SIZE0, min_inliers=30)
    assert res.reference == 1
    assert res.reference_reason == "undecided; both images simulated, final homography: image 1 is 1.60x larger"
    res = reference_from_final_homography(_two_sided_result(1 / 1.6, 35), SIZE0, min_inliers=30)
    assert res.reference == 0 and res.reference_reason.endswith("image 0 is 1.60x larger")
    weak = reference_from_final_homography(_two_sided_result(1.6, 20), SIZE0, min_inliers=30)  # too few inliers
    assert weak.reference == 0 and weak.reference_reason == "undecided"


@pytest.mark.slow
def test_the_half_resolution_decision_matches_the_full_one_on_graf(shared_data):
    """`ReferenceConfig.decision_scale` 0.5 (the pair matcher's default) against 1 (the paper's,
    `recon run`'s) on graf 1-2..1-6: the same reference and the same adaptive path; on a pair that
    simulates views (graf 1-3, targeted) the reference's full-resolution SIFT is never computed,
    which is the time it saves, and the result is the full-resolution decision's to the match."""
    import dataclasses

    from matching.config import MatcherConfig
    from matching.matcher import ExtraAffineMatcher, decide_reference, plan_from_decision

    g = shared_data / "oxford" / "graf"
    half_cfg = MatcherConfig(workers=1)
    assert half_cfg.reference.decision_scale == 0.5
    full_cfg = dataclasses.replace(half_cfg, reference=dataclasses.replace(half_cfg.reference, decision_scale=1.0))
    for k in range(2, 7):
        plans = []
        for cfg in (half_cfg, full_cfg):
            m = ExtraAffineMatcher(cfg)
            ctx = m.context(_graf_store(g, "img1", f"img{k}"), "img1", f"img{k}")
            decision = decide_reference(ctx)
            ref, plan = plan_from_decision(ctx, decision)
            plans.append((decision.reference, ref, plan.path))
        assert plans[0] == plans[1], f"graf 1-{k}"
    results = []
    for cfg in (half_cfg, full_cfg):
        store = _graf_store(g, "img1", "img3")
        r = ExtraAffineMatcher(cfg).match(store, "img1", "img3")
        assert r.path == "targeted" and r.reference == 0
        computed = {key for key in store.keys("img1") if key.endswith("@orig")}
        results.append((r, computed))
    assert not results[0][1] and results[1][1]  # the reference's full-resolution SIFT: only at scale 1
    np.testing.assert_array_equal(results[0][0].matches, results[1][0].matches)
    np.testing.assert_array_equal(results[0][0].kpts1, results[1][0].kpts1)


def test_decision_scale_outside_0_1_is_refused():
    from matching.config import MatcherConfig

    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="decision_scale"):
            ReferenceConfig(decision_scale=bad)
        with pytest.raises(ValueError, match="decision_scale"):
            MatcherConfig.from_overrides(reference__decision_scale=bad)
    assert MatcherConfig.from_overrides(reference__decision_scale=0.25).reference.decision_scale == 0.25
