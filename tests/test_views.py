"""The simulation grid, the view affines and the mapping of keypoints back to the original."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from matching.types import ViewParams
from matching.views import (
    GridConfig,
    antialias_sigma,
    apply_affine,
    blur_compress_x,
    map_to_original,
    simulate,
    view_affine,
    view_grid,
)


def test_default_grid_has_the_papers_45_views_per_tilt():
    views = view_grid(GridConfig())
    per_tilt = Counter(round(v.t, 3) for v in views)
    assert [per_tilt[round(math.sqrt(2) ** k, 3)] for k in range(6)] == [3, 4, 5, 8, 10, 15]
    assert len(views) == 45
    # longitudes step by 72/t and stay below 180 degrees
    for v in views:
        assert 0 <= v.phi < 180
        j = v.phi / (72.0 / v.t)
        assert abs(j - round(j)) < 1e-6


def test_grid_scale_is_tied_to_tilt_index_and_configurable():
    tied = view_grid(GridConfig(scale_mode="tied", ds=0.5))
    assert sorted({v.s for v in tied}) == [1.0, 1.5, 2.0, 2.5, 3.0, 3.5]
    assert {v.s for v in view_grid(GridConfig(ds=0.0))} == {1.0}
    assert {v.s for v in view_grid(GridConfig(scale_mode="none"))} == {1.0}
    wider = view_grid(GridConfig(b=36.0))
    assert len(wider) > 45  # a finer longitude step gives more views
    assert len(view_grid(GridConfig(n=2))) == 3 + 4 + 5


@pytest.mark.parametrize("view", [ViewParams(1.0, 0.0, 1.0), ViewParams(2.0, 30.0, 1.5),
                                  ViewParams(5.656854, 171.0, 3.5), ViewParams(1.414214, 90.0, 0.5)])
def test_affine_round_trip_and_canvas_holds_whole_image(view):
    w, h = 320, 200
    A, (ow, oh) = view_affine((w, h), view)
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64)
    warped = apply_affine(A, corners)
    assert warped.min() >= -1e-4
    assert warped[:, 0].max() <= ow - 1 + 1e-4 and warped[:, 1].max() <= oh - 1 + 1e-4
    pts = np.random.default_rng(0).uniform([0, 0], [w - 1, h - 1], (50, 2))
    back, inside = map_to_original(apply_affine(A, pts), A, (w, h))
    assert inside.all()
    np.testing.assert_allclose(back, pts, atol=1e-3)


def test_simulated_view_puts_original_pixels_where_the_affine_says():
    img = np.zeros((120, 160), np.uint8)
    img[40, 100] = 255  # one bright pixel at (x=100, y=40)
    view = ViewParams(2.0, 40.0, 2.0)  # t/s = 1: no anti-alias blur
    sv = simulate(img, view, "nearest")
    x, y = apply_affine(sv.A_view_from_orig, [[100.0, 40.0]])[0]
    ys, xs = np.nonzero(sv.image)
    assert len(xs) > 0
    assert np.hypot(xs.mean() - x, ys.mean() - y) < 1.5
    assert sv.mask[int(round(y)), int(round(x))] == 255
    assert sv.mask[0, 0] == 0  # rotated canvas corner lies outside the original


def test_points_outside_the_original_are_dropped():
    w, h = 100, 80
    A, _ = view_affine((w, h), ViewParams(2.0, 45.0, 1.0))
    view_pts = np.array([[0.0, 0.0], apply_affine(A, [[50.0, 40.0]])[0]])
    _, inside = map_to_original(view_pts, A, (w, h))
    assert inside.tolist() == [False, True]


def test_antialias_blur_only_where_the_view_shrinks():
    assert antialias_sigma(ViewParams(4.0, 0.0, 1.0)) == pytest.approx(0.8 * math.sqrt(15))
    assert antialias_sigma(ViewParams(2.0, 0.0, 2.0)) == 0.0
    img = (np.random.default_rng(1).random((100, 100)) * 255).astype(np.uint8)
    sharp = simulate(img, ViewParams(4.0, 0.0, 1.0), "linear", antialias=False).image
    soft = simulate(img, ViewParams(4.0, 0.0, 1.0), "linear", antialias=True).image
    assert sharp.shape == soft.shape
    assert soft[10:-10, 5:-5].std() < sharp[10:-10, 5:-5].std()  # blur removes aliased noise


def _texture(h: int = 240, w: int = 320) -> np.ndarray:
    """Band-limited random texture (blurred noise), a stand-in for a photo's content."""
    import cv2
    noise = (np.random.default_rng(3).random((h, w)) * 255).astype(np.uint8)
    return cv2.GaussianBlur(noise, (0, 0), 1.5)


@pytest.mark.parametrize("view", [ViewParams(8.0, 0.0, 1.0), ViewParams(16.0, 37.0, 1.0), ViewParams(22.6274, 90.0, 1.0),
                                  ViewParams(11.3137, 20.0, 2.0)])
def test_steep_views_blurred_by_halving_match_the_exact_blur(view):
    img = _texture()
    fast = simulate(img, view, "linear", antialias=True)
    exact = simulate(img, view, "linear", antialias=True, halving=False)
    assert fast.image.shape == exact.image.shape
    np.testing.assert_array_equal(fast.A_view_from_orig, exact.A_view_from_orig)
    inside = exact.mask > 0
    diff = np.abs(fast.image.astype(int) - exact.image.astype(int))[inside]
    assert diff.mean() < 1.5 and np.percentile(diff, 99) <= 6  # uint8 rounding of the stages, no shift
    # the exact blur is what the halving replaces: without any blur the views differ far more
    sharp = simulate(img, view, "linear", antialias=False).image.astype(int)
    assert np.abs(sharp - exact.image.astype(int))[inside].mean() > 3 * diff.mean()


@pytest.mark.parametrize("view, interp, max_px", [
    (ViewParams(16.0, 30.0, 1.0), "linear", 0.5),  # blurred by halving
    (ViewParams(2.8284, 0.0, 1.6818), "lanczos", 0.25),  # no rotation: blurred on the original, warped once
])
def test_a_blurred_view_keeps_a_point_where_the_view_affine_puts_it(view, interp, max_px):
    img = np.zeros((200, 300), np.uint8)
    img[90:111, 140:161] = 255  # a 21 px square centred on (150, 100)
    sv = simulate(img, view, interp, antialias=True)
    x, y = apply_affine(sv.A_view_from_orig, [[150.0, 100.0]])[0]
    w = sv.image.astype(np.float64)
    ys, xs = np.mgrid[:w.shape[0], :w.shape[1]]
    assert np.hypot((w * xs).sum() / w.sum() - x, (w * ys).sum() / w.sum() - y) < max_px


def test_halving_only_where_the_blur_is_wide():
    img = _texture()
    assert blur_compress_x(img, 6.3, 8.0)[1] == 8  # t = 8: three halvings, then the rest (0.37 px)
    assert blur_compress_x(img, 18.1, 22.6274)[1] == 16
    assert blur_compress_x(img, 1.0, 5.66)[1] == 1  # the tied grid's widest blur (t / s = 1.6): exact
    assert blur_compress_x(img, 4.4, 5.66)[1] == 1  # below `HALVING_MIN_TILT` (the two-sided grid's t = 5.66)
    assert blur_compress_x(img, 18.1, 22.6274, halving=False)[1] == 1


def test_fine_views_skip_rotation_duplicates_and_can_add_the_original():
    from matching.fine import select_fine_views
    from matching.types import CoarseScore

    def score(t, phi, n):
        return CoarseScore(ViewParams(t, phi, 1.0), n, n, float(n))

    ranked = [score(1.0, 72.0, 90), score(1.0, 0.0, 80), score(2.0, 36.0, 70), score(4.0, 18.0, 60)]
    assert select_fine_views(ranked, 2) == [ViewParams(1.0, 0.0, 1.0), ViewParams(2.0, 36.0, 1.0)]
    tilted = ranked[2:]
    assert select_fine_views(tilted, 1, include_original=True) == [ViewParams(2.0, 36.0, 1.0),
                                                                   ViewParams(1.0, 0.0, 1.0)]


def test_fine_views_at_a_minimum_distance_skip_the_same_peak_seen_twice():
    """(5.66, 0) and (5.66, 178.2) are one view (phi has period 180): with a minimum tilt-plane
    distance the second fine view is the next distinct peak instead."""
    from matching.fine import select_fine_views
    from matching.types import CoarseScore

    def score(t, phi, n):
        return CoarseScore(ViewParams(t, phi, 1.0), n, n, float(n))

    ranked = [score(5.656854, 0.0, 90), score(5.656854, 178.19, 85), score(4.0, 0.0, 80), score(2.0, 90.0, 40)]
    assert select_fine_views(ranked, 2) == [ranked[0].view, ranked[1].view]
    assert select_fine_views(ranked, 2, min_distance=0.5) == [ranked[0].view, ranked[3].view]
    assert select_fine_views(ranked, 3, min_distance=0.2) == [ranked[0].view, ranked[2].view, ranked[3].view]
    assert select_fine_views(ranked[:2], 2, min_distance=0.5) == [ranked[0].view]  # nothing else far enough


@pytest.mark.parametrize("view", [ViewParams(2.0, 0.0, 1.0), ViewParams(2.0, 0.0, 1.4142), ViewParams(2.8284, 0.0, 1.6818),
                                  ViewParams(5.6569, 0.0, 2.3784), ViewParams(11.3137, 0.0, 1.0)])
def test_views_without_rotation_warped_once_match_the_two_warps(view):
    import cv2
    noise = (np.random.default_rng(3).random((240, 320)) * 255).astype(np.uint8)
    img = cv2.GaussianBlur(noise, (0, 0), 0.7)  # detail near the pixel scale, where the blur matters
    one = simulate(img, view, "lanczos", antialias=True)
    two = simulate(img, view, "lanczos", antialias=True, fused=False)
    assert one.image.shape == two.image.shape
    np.testing.assert_array_equal(one.A_view_from_orig, two.A_view_from_orig)
    np.testing.assert_array_equal(one.mask, two.mask)
    inside = two.mask > 0
    diff = np.abs(one.image.astype(int) - two.image.astype(int))[inside]
    if view.s == 1.0:  # the first of the two warps was the identity: the same image to the bit
        assert diff.max() == 0
    else:  # the blur before the zoom instead of after it: rounding, no shift
        assert diff.mean() < 1.0 and np.percentile(diff, 99) <= 3
        sharp = simulate(img, view, "lanczos", antialias=False).image.astype(int)
        assert np.abs(sharp - two.image.astype(int))[inside].mean() > 4 * diff.mean()
