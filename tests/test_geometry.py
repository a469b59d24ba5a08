"""The one relative-scale helper (`geometry.scale_1_from_0`) on homographies of known scale, and
the rules that read it (`reference.larger_image`, `metrics.gt_reference`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from matching.geometry import homography_jacobian, image_centre, local_scale, scale_1_from_0
from matching.metrics import gt_reference
from matching.reference import larger_image

SIZE0 = (801, 601)  # (w, h): centre (400, 300)


def _similarity(s: float, deg: float, centre=(400.0, 300.0), shift=(17.0, -9.0)) -> np.ndarray:
    """Zoom by `s` and rotate by `deg` about `centre`, then translate by `shift`."""
    c, sn = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T = np.array([[1, 0, centre[0] + shift[0]], [0, 1, centre[1] + shift[1]], [0, 0, 1.0]])
    A = np.array([[s * c, -s * sn, 0], [s * sn, s * c, 0], [0, 0, 1.0]])
    Tm = np.array([[1, 0, -centre[0]], [0, 1, -centre[1]], [0, 0, 1.0]])
    return T @ A @ Tm


@pytest.mark.parametrize("s", [0.5, 1.0, 1.7, 3.0])
def test_scale_of_a_similarity_is_its_zoom(s):
    H = _similarity(s, 33.0)
    assert scale_1_from_0(H, SIZE0) == pytest.approx(s, rel=1e-12)
    assert scale_1_from_0(-4.0 * H, SIZE0) == pytest.approx(s, rel=1e-12)  # H is defined up to scale
    assert scale_1_from_0(np.linalg.inv(H), SIZE0) == pytest.approx(1.0 / s, rel=1e-12)


def test_scale_of_a_projective_homography_is_read_at_image_0s_centre():
    g = 1e-3
    H = np.array([[1.0, 0, 0], [0, 1.0, 0], [g, 0, 1.0]])  # det 1, w = g x + 1
    w = g * 400.0 + 1.0
    assert scale_1_from_0(H, SIZE0) == pytest.approx(w**-1.5, rel=1e-12)
    # not anywhere else: at the left edge w = 1 and the scale is 1
    assert math.sqrt(local_scale(H, (0.0, 300.0))) == pytest.approx(1.0)
    # the linear scale is the square root of |det J| at the centre
    J = homography_jacobian(H, image_centre(SIZE0))
    assert scale_1_from_0(H, SIZE0) == pytest.approx(math.sqrt(abs(np.linalg.det(J))), rel=1e-12)


def test_no_scale_where_the_centre_maps_to_infinity():
    H = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0 / 400.0, 0, 1.0]])  # w = 0 at x = 400
    assert math.isnan(scale_1_from_0(H, SIZE0))
    assert larger_image(scale_1_from_0(H, SIZE0), 1.1) is None
    assert gt_reference(H, SIZE0) is None


def test_the_matcher_and_the_ground_truth_read_the_same_scale():
    for s, ref in ((0.5, 0), (2.0, 1), (1.02, None)):
        H = _similarity(s, 10.0)
        assert larger_image(scale_1_from_0(H, SIZE0), 1.1) == ref
        assert gt_reference(H, SIZE0) == ref  # area tolerance 1.1: 1.02^2 is within it
    # the ground truth's tolerance is on area, the matcher's on the linear scale
    H = _similarity(1.07, 0.0)
    assert gt_reference(H, SIZE0) == 1 and larger_image(scale_1_from_0(H, SIZE0), 1.1) is None
