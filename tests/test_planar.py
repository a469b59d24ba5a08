"""One more, distinct fine view for pairs whose matches lie on one surface (`matching.planar`)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from matching.planar import PlanarConfig, distinct_view, one_surface
from matching.types import CoarseScore, ViewParams


def _score(t: float, phi: float, inliers: int) -> CoarseScore:
    return CoarseScore(ViewParams(t, phi, 1.0), inliers + 20, inliers, float(inliers))


def test_distinct_view_is_the_best_overlapping_view_far_from_the_chosen_ones():
    """Skips the chosen views, their near-duplicates (phi has period 180), views too close in
    the tilt plane and views without ORB overlap; the original does not count as chosen."""
    cfg = PlanarConfig(enabled=True)
    chosen = [ViewParams(5.656854, 0.0, 1.0), ViewParams(1.0, 0.0, 1.0)]
    scores = [_score(5.656854, 0.0, 90), _score(5.656854, 178.19, 85),  # chosen, and the same view
              _score(4.0, 0.0, 70),  # 0.35 from the chosen one in the tilt plane
              _score(2.0, 90.0, 10),  # far, but below min_inliers: no overlap
              _score(2.828427, 90.0, 30),  # far (opposite longitude) and overlapping
              _score(1.0, 0.0, 95)]  # the original: never the extra view
    assert distinct_view(scores, chosen, cfg) == ViewParams(2.828427, 90.0, 1.0)
    assert distinct_view(scores[:4], chosen, cfg) is None
    # with only the original chosen, every simulated view is far enough from "nothing"
    assert distinct_view(scores, [ViewParams(1.0, 0.0, 1.0)], cfg) == ViewParams(5.656854, 0.0, 1.0)


def _two_views(points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of world points in two cameras 40° apart looking at the origin (f = 800 px)."""
    K = np.array([[800.0, 0, 400], [0, 800, 300], [0, 0, 1]])

    def project(R: np.ndarray, c: np.ndarray) -> np.ndarray:
        x = (K @ (R @ (points_w - c).T)).T
        return x[:, :2] / x[:, 2:]

    a = np.radians(40.0)
    R1 = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    return project(np.eye(3), np.array([0, 0, -6.0])), project(R1, R1.T @ np.array([0, 0, -6.0]))


def test_one_surface_tells_a_plane_from_two():
    """Matches of points on one plane fit one homography (COLMAP's planar test); those of two
    planes at right angles, half each, do not."""
    rng = np.random.default_rng(0)
    n = 300
    floor = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)]
    wall = np.c_[rng.uniform(-2, 2, n // 2), rng.uniform(-1.5, 1.5, n // 2), np.zeros(n // 2)]
    side = np.c_[np.full(n // 2, 1.0), rng.uniform(-1.5, 1.5, n // 2), rng.uniform(-2.0, 0.0, n // 2)]
    cfg = PlanarConfig(enabled=True)
    a, b = _two_views(floor)
    flat, why = one_surface(a, b, cfg)
    assert flat and f"of {n} epipolar inliers" in why
    a, b = _two_views(np.r_[wall, side])
    flat, why = one_surface(a + rng.normal(0, 0.3, a.shape), b + rng.normal(0, 0.3, b.shape), cfg)
    assert not flat, why


PHOTOS = ("scenes/castle_P30/images/0004.jpg", "scenes/sceaux_castle/images/100_7100.JPG",
          "scenes/sacre_coeur/images/02928139_3448003521.jpg")


@pytest.mark.slow
@pytest.mark.requires_shared(*PHOTOS)
def test_a_one_surface_pair_of_the_photo_textured_facade_gets_a_distinct_view(tmp_path, shared_data):
    """The facade textured with three shared photos, views 78° apart: without the option the
    pair's two fine views both rectify the ground (one homography explains the matches); with
    it (`recon run`'s default) a distinct view is fused and more matches verify."""
    import cv2

    from matching.matcher import ExtraAffineMatcher, MatcherConfig
    from matching.store import FeatureStore
    from scenes.render import render_scene

    images = render_scene(tmp_path / "s", "facade-3x78", textures=[shared_data / p for p in PHOTOS]).image_paths
    assert len(images) == 3
    store = FeatureStore()
    for p in images[1:]:
        store.add_image(p.stem, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
    names = images[1].stem, images[2].stem
    off = ExtraAffineMatcher(MatcherConfig.from_overrides(variant="multiview", planar__enabled=False)).match(store, *names)
    on = ExtraAffineMatcher(MatcherConfig.multiview()).match(store, *names)  # `recon run`'s matcher
    assert len(off.best_views) == 3  # two simulated views and the original
    assert "-> + view" in on.path_reason and "one surface" in on.path_reason
    assert len(on.best_views) == 4 and on.best_views[:3] == off.best_views
    # the fused view verifies more matches, and more of the final ones lie off the ground's
    # homography (COLMAP verified this pair as PLANAR_OR_PANORAMIC without the option and as
    # UNCALIBRATED with it in `recon run`)
    before, after = map(int, re.search(r"(\d+) -> (\d+) verified", on.path_reason).groups())
    assert after > before + 30, on.path_reason
    cfg = PlanarConfig(enabled=True)
    off_plane = []
    for r in (off, on):
        _, why = one_surface(r.kpts0[r.matches[:, 0]], r.kpts1[r.matches[:, 1]], cfg)
        n_h, n_f = map(int, re.match(r"(\d+) of (\d+)", why).groups())
        off_plane.append(n_f - n_h)
    assert off_plane[1] > off_plane[0] + 10, off_plane
