"""Escalation: a hard EVD pair is solved by escalating, disabled escalation never runs a level, and
the cheap building blocks (homography sanity check, vectorised ORB ratio test) behave. (Easy pairs
staying on the fast path: tests/test_strategies.py.)"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from matching.context import Attempt
from matching.features import Features
from matching.io import load_gray, read_homography
from matching.matcher import ExtraAffineMatcher, MatcherConfig
from matching.matching_utils import ratio_match
from matching.store import FeatureStore
from matching.strategies import ESCALATION
from matching.verify import plausible_homography
from matching.viewpairs import hamming_ratio_match


def _match(path0: Path, path1: Path, **overrides):
    store = FeatureStore()
    store.add_image("a", load_gray(path0))
    store.add_image("b", load_gray(path1))
    m = ExtraAffineMatcher(MatcherConfig.from_overrides(**overrides))
    try:
        return m.match(store, "a", "b")
    finally:
        m.close()


def _correct(res, H: np.ndarray, thresh_px: float = 3**0.5) -> tuple[int, float]:
    """(matches within `thresh_px` of the ground-truth homography 0 -> 1, their fraction)."""
    p0, p1 = res.matched_points(inliers_only=True)
    if len(p0) == 0:
        return 0, 0.0
    q = np.c_[p0, np.ones(len(p0))] @ H.T
    ok = np.linalg.norm(q[:, :2] / q[:, 2:] - p1, axis=1) < thresh_px
    return int(ok.sum()), float(ok.mean())


@pytest.mark.slow
def test_evd_shop_is_solved_by_escalation(shared_data):
    """EVD shop: the fast path does not reach `min_inliers` verified matches; escalation (the
    `pairs` level, since both images are simulated) solves the pair (benchmarks/results/pairs.txt:
    533 of 544 correct)."""
    e = shared_data / "evd"
    res = _match(e / "1" / "shop.png", e / "2" / "shop.png", workers=2)
    assert res.escalation == "pairs", "the fast path alone should not have reached min_inliers on shop"
    assert "both images simulated, final homography" in res.reference_reason
    n_ok, precision = _correct(res, read_homography(e / "h" / "shop.txt"))
    assert n_ok >= 20 and precision >= 0.5, (n_ok, precision, res.escalation)
    # each level that ran is timed, within the escalation's own time, and none after the winner
    levels = {k: v for k, v in res.timings.items() if k.startswith("level:")}
    assert "level:pairs" in levels and "level:steep" not in levels
    assert sum(levels.values()) <= res.timings["escalation"] + 1e-6


def test_escalation_disabled_never_escalates(monkeypatch):
    def boom(*a, **k) -> Attempt:
        raise AssertionError("an escalation level ran with escalation disabled")

    for level in ESCALATION:
        monkeypatch.setattr(type(level), "run", boom)
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur((rng.random((200, 240)) * 255).astype(np.uint8), (0, 0), 2)
    store = FeatureStore()
    store.add_image("a", img)
    store.add_image("b", img[::-1].copy())
    m = ExtraAffineMatcher(MatcherConfig.from_overrides(escalation__enabled=False, workers=1))
    m.match(store, "a", "b")


def test_plausible_homography_rejects_mirrors_folds_and_degenerate_models():
    pts = np.array([[0, 0], [100, 0], [0, 100], [100, 100]], np.float64)
    assert plausible_homography(np.eye(3), pts)
    assert plausible_homography(np.array([[0.3, 0.1, 5], [0.0, 1.2, 3], [1e-4, 0, 1]]), pts)
    assert not plausible_homography(np.diag([-1.0, 1.0, 1.0]), pts)  # mirror
    assert not plausible_homography(np.array([[1, 0, 0], [0, 1, 0], [-0.02, 0, 1.0]]), pts)  # horizon inside
    assert not plausible_homography(np.diag([1.0, 1e-3, 1.0]), pts)  # collapses to a line
    assert not plausible_homography(None, pts)


def test_hamming_ratio_match_equals_the_brute_force_ratio_test():
    rng = np.random.default_rng(1)
    da = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    db = np.concatenate([da[:100] ^ (rng.random((100, 32)) < 0.02).astype(np.uint8),
                         rng.integers(0, 256, (200, 32), dtype=np.uint8)])
    fa = Features(np.zeros((300, 2), np.float32), np.ones(300, np.float32), np.zeros(300, np.float32), da)
    fb = Features(np.zeros((300, 2), np.float32), np.ones(300, np.float32), np.zeros(300, np.float32), db)
    ref, _ = ratio_match(da, db, cv2.NORM_HAMMING, 0.75)
    got = hamming_ratio_match(fa, fb, 0.75)
    assert len(got) >= 90
    assert {tuple(r) for r in ref} == {tuple(r) for r in got}
