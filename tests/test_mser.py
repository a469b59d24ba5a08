"""Affine-covariant MSER features, the local-affine-frame (LAF) check and the `mser` escalation
level (`matching.mser`, `matching.mserlevel`)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from matching.context import Attempt, MatchContext
from matching.features import Features
from matching.fine import FineMatches
from matching.io import load_gray, read_homography
from matching.matcher import ExtraAffineMatcher, MatcherConfig
from matching.metrics import reprojection_errors
from matching.mser import MserConfig, detect_mser_affine, laf_consistent, laf_errors
from matching.mserlevel import mser_attempt
from matching.store import FeatureStore
from matching.twosided import fginn_match


def blobs(seed: int = 0, size: int = 480) -> np.ndarray:
    """A procedural image of random filled polygons (stable regions of distinct shapes) over
    smooth shading: a filled ellipse would normalise to the same disc as every other."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    img = (96 + 40 * np.sin(xx / 37.0) * np.cos(yy / 53.0)).astype(np.uint8)
    for _ in range(140):
        c = rng.uniform(24, size - 24, 2)
        k = int(rng.integers(3, 7))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        rad = rng.uniform(5, 20, k)
        poly = (c + np.c_[rad * np.cos(ang), rad * np.sin(ang)]).astype(np.int32)
        cv2.fillPoly(img, [poly], int(rng.integers(0, 256)))
    return cv2.GaussianBlur(img, (3, 3), 0.8)


def affine(t: float, phi_deg: float, psi_deg: float, size: int) -> np.ndarray:
    """2x3 A = R(psi) diag(1/t, 1) R(phi), about the image centre (a tilt t view)."""
    def rot(a):
        a = np.radians(a)
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    L = rot(psi_deg) @ np.diag([1.0 / t, 1.0]) @ rot(phi_deg)
    c = np.array([size / 2.0, size / 2.0])
    return np.hstack([L, (c - L @ c)[:, None]])


def matched(a: Features, b: Features, A: np.ndarray):
    m, _ = fginn_match(a, b, 0.85, 8.0, 8, 0)
    pa, pb = a.kpts[m[:, 0]], b.kpts[m[:, 1]]
    err = np.linalg.norm(pa @ A[:, :2].T + A[:, 2] - pb, axis=1)
    return m, err


def test_regions_match_across_a_strong_affine_and_their_frames_follow_it():
    """A tilt-2.5 view rotated by 40 deg: regions of both images match at the true positions, and
    the true map carries each correct match's frame onto its partner's (the LAF check passes),
    while the same frames turned by 90 deg fail it."""
    img = blobs()
    A = affine(2.5, 30.0, 40.0, img.shape[1])
    warped = cv2.warpAffine(img, A, img.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=96)
    cfg = MserConfig()
    a, b = detect_mser_affine(img, cfg), detect_mser_affine(warped, cfg)
    assert a.frames is not None and b.frames is not None and a.frames.shape == (len(a), 2, 2)
    m, err = matched(a, b, A)
    good = err < 2.0
    assert good.sum() >= 25 and good.mean() >= 0.8, (len(m), good.sum())
    H = np.vstack([A, [0, 0, 1]])
    ia, ib = m[good, 0], m[good, 1]
    ok = laf_consistent(H, a.kpts[ia], a.frames[ia], b.frames[ib], cfg)
    assert ok.mean() >= 0.9, ok.mean()
    angle, scale = laf_errors(H, a.kpts[ia], a.frames[ia], b.frames[ib])
    assert np.median(angle) < 10 and np.median(scale) < 1.3
    turned = b.frames[ib] @ np.array([[0.0, -1.0], [1.0, 0.0]])
    assert laf_consistent(H, a.kpts[ia], a.frames[ia], turned, cfg).mean() <= 0.1


def test_frames_survive_the_feature_cache(tmp_path):
    img = blobs(1, 240)
    f = detect_mser_affine(img, MserConfig())
    s1 = FeatureStore(tmp_path)
    s1.add_image("x", img)
    s1.get_or_compute("x", "mser", lambda: f)
    s2 = FeatureStore(tmp_path)
    s2.add_image("x", img)
    g = s2.get_or_compute("x", "mser", lambda: pytest.fail("recomputed instead of loaded"))
    assert g.frames is not None and np.array_equal(g.frames, f.frames) and np.array_equal(g.kpts, f.kpts)
    assert np.array_equal(f.subset(np.arange(3)).frames, f.frames[:3])


@pytest.mark.slow
def test_mser_level_solves_evd_dum(shared_data):
    """EVD dum: the levels below `mser` (topk, swap, pairs, steep) stop short of
    `escalation.min_inliers` verified matches (so escalation reaches `mser`), and the level's
    regions solve it: before it, only the costlier `two-sided` level found 22 correct at 66.7 %
    (docs/decisions.md, "The `mser` level"; benchmarks/results/pairs.txt: 89 of 92 now)."""
    e = shared_data / "evd"
    store = FeatureStore()
    store.add_image("a", load_gray(e / "1" / "dum.png"))
    store.add_image("b", load_gray(e / "2" / "dum.png"))
    m = ExtraAffineMatcher(MatcherConfig(workers=2))
    try:
        res = m.match(store, "a", "b")
    finally:
        m.close()
    assert res.escalation == "mser", res.escalation
    p0, p1 = res.matched_points(inliers_only=True)
    err = reprojection_errors(read_homography(e / "h" / "dum.txt"), p0, p1)
    ok = err <= np.sqrt(3)
    assert ok.sum() >= 20 and ok.mean() >= 0.5, (len(err), int(ok.sum()))


def test_mser_attempt_pools_with_the_best_attempt_and_keeps_its_matches():
    """The level pools its region matches after the best attempt's: those come first, unchanged."""
    img = blobs(2, 320)
    A = affine(1.6, 20.0, 10.0, img.shape[1])
    warped = cv2.warpAffine(img, A, img.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=96)
    store = FeatureStore()
    store.add_image("a", img)
    store.add_image("b", warped)
    ctx = MatchContext(store, ("a", "b"), MatcherConfig(workers=1), [])
    kr = np.array([[10.0, 10.0], [50.0, 60.0]], np.float32)
    kt = np.array([[12.0, 11.0], [52.0, 61.0]], np.float32)
    best = Attempt("", 0, FineMatches(kr, kt, np.array([[0, 0], [1, 1]], np.int32), np.array([1.0, 2.0], np.float32), {}),
                   [], [], 2)
    att = mser_attempt(ctx, best, MserConfig())
    assert att.label == "mser" and att.reference == 0
    f = att.fine
    assert np.array_equal(f.kpts_ref[f.matches[:2, 0]], kr) and np.array_equal(f.kpts_target[f.matches[:2, 1]], kt)
    p0, p1 = f.kpts_ref[f.matches[2:, 0]], f.kpts_target[f.matches[2:, 1]]
    err = np.linalg.norm(p0 @ A[:, :2].T + A[:, 2] - p1, axis=1)
    assert f.per_view["mser"] >= 20 and (err < 3).mean() >= 0.8, (f.per_view, (err < 3).mean())
    assert att.verified >= 20


def test_pool_verified_adds_the_other_attempts_verified_matches_on_the_reference_side():
    """`MserConfig.pool = "verified"`: after the best attempt's matches come the verified matches of
    the escalation's other attempts, an attempt of the other reference turned around, and none
    that repeats a pooled match."""
    from matching.mserlevel import earlier_verified

    store = FeatureStore()
    store.add_image("a", np.zeros((64, 64), np.uint8))
    store.add_image("b", np.zeros((64, 64), np.uint8))
    ctx = MatchContext(store, ("a", "b"), MatcherConfig(workers=1), [])

    def attempt(ref, pts_ref, pts_t, mask):
        n = len(pts_ref)
        fm = FineMatches(np.float32(pts_ref), np.float32(pts_t), np.stack([np.arange(n)] * 2, 1).astype(np.int32),
                         np.arange(n, dtype=np.float32), {})
        return Attempt("x", ref, fm, [], [], int(np.sum(mask)), verified_mask=np.array(mask))

    best = attempt(0, [[10, 10]], [[20, 20]], [True])
    other_side = attempt(1, [[31, 30], [41, 40], [20.5, 20.2]], [[30, 30], [40, 40], [10.2, 10.3]], [True, False, True])
    same_side = attempt(0, [[50, 50], [50.3, 50.2]], [[60, 60], [60.2, 60.1]], [True, True])
    ctx.attempts = [best, other_side, same_side]
    pooled = earlier_verified(ctx, best)
    pairs = {(tuple(np.round(pooled.kpts_ref[i])), tuple(np.round(pooled.kpts_target[j]))) for i, j in pooled.matches}
    assert (tuple(pooled.kpts_ref[pooled.matches[0, 0]]), tuple(pooled.kpts_target[pooled.matches[0, 1]])) == ((10, 10), (20, 20))
    assert ((30, 30), (31, 30)) in pairs  # image 1 was the other attempt's reference: turned around
    assert ((40, 40), (41, 40)) not in pairs  # not verified
    assert len(pooled.matches) == 3  # best's, the turned one, one of the two repeats at (50, 50); best's repeat dropped
    assert pooled.per_view["earlier_verified"] == 2
    ctx.attempts = [best]
    assert earlier_verified(ctx, best) is best.fine  # nothing else: the best attempt alone
