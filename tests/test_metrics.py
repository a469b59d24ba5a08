"""The paper's metrics (Eq. 5-7) and the ground-truth reference choice."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from matching.geometry import local_scale
from matching.metrics import (
    DEFAULT_TH,
    gt_reference,
    inlier_ratio,
    precision,
    precision_of_points,
    project,
    reference_correct,
    reprojection_errors,
)
from matching.types import PairResult

# Oxford graf H1to2p: a real, clearly projective homography
H_GRAF = np.array([[8.7976964e-01, 3.1245438e-01, -3.9430589e01],
                   [-1.8389418e-01, 9.3847198e-01, 1.5315784e02],
                   [1.9641425e-04, -1.6015275e-05, 1.0]])


def _zoom(s: float, cx: float, cy: float) -> np.ndarray:
    """Zoom by s about (cx, cy): image 1 = image 0 magnified s times."""
    return np.array([[s, 0, cx * (1 - s)], [0, s, cy * (1 - s)], [0, 0, 1.0]])


def _result(pts0: np.ndarray, pts1: np.ndarray, inlier_mask=None) -> PairResult:
    n = len(pts0)
    return PairResult(method="test", kpts0=pts0.astype(np.float32), kpts1=pts1.astype(np.float32),
                      matches=np.stack([np.arange(n), np.arange(n)], 1).astype(np.int32),
                      distances=np.zeros(n, np.float32), inlier_mask=inlier_mask)


def _grid_points(n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([0, 0], [800, 640], size=(n, 2))


def test_project_matches_homogeneous_product():
    pts = _grid_points(20)
    q = (H_GRAF @ np.c_[pts, np.ones(len(pts))].T).T
    np.testing.assert_allclose(project(H_GRAF, pts), q[:, :2] / q[:, 2:], rtol=1e-12)
    # scale of H does not matter, a point at infinity is never close to anything
    np.testing.assert_allclose(project(3.0 * H_GRAF, pts), project(H_GRAF, pts), rtol=1e-12)
    Hinf = np.array([[1, 0, 0], [0, 1, 0], [1, 0, 0.0]])
    assert np.isinf(project(Hinf, [[0.0, 5.0]])).all()
    assert np.isinf(reprojection_errors(Hinf, [[0.0, 5.0]], [[0.0, 0.0]])).all()


def test_precision_exact_points_is_one():
    p0 = _grid_points()
    p1 = project(H_GRAF, p0)
    rep = precision(_result(p0, p1), H_GRAF)
    assert (rep.points, rep.correct, rep.precision) == (200, 200, 1.0)
    assert np.allclose(reprojection_errors(H_GRAF, p0, p1), 0, atol=1e-3)


def test_precision_perturbed_points_drop_exactly():
    p0 = _grid_points()
    p1 = project(H_GRAF, p0)
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(200, 2))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    p1[:30] += 5.0 * dirs[:30]  # 30 clearly wrong
    p1[30:60] += 1.0 * dirs[30:60]  # 30 within sqrt(3): still correct
    p1[60:70] += 1.9 * dirs[60:70]  # 10 just outside sqrt(3), inside sqrt(8)
    rep = precision(_result(p0, p1), H_GRAF)
    assert (rep.points, rep.correct) == (200, 160)
    assert rep.precision == pytest.approx(0.8)
    assert precision(_result(p0, p1), H_GRAF, th=math.sqrt(8)).correct == 170
    assert DEFAULT_TH == pytest.approx(math.sqrt(3))


def test_precision_counts_only_ransac_inliers_by_default():
    p0 = _grid_points(100)
    p1 = project(H_GRAF, p0)
    p1[:40] += 10.0  # wrong matches ...
    mask = np.ones(100, bool)
    mask[:40] = False  # ... that RANSAC rejected
    r = _result(p0, p1, inlier_mask=mask)
    assert precision(r, H_GRAF) == precision_of_points(p0[40:], p1[40:], H_GRAF)
    assert (precision(r, H_GRAF).points, precision(r, H_GRAF).correct) == (60, 60)
    all_ = precision(r, H_GRAF, inliers_only=False)
    assert (all_.points, all_.correct) == (100, 60)
    assert inlier_ratio(r) == pytest.approx(0.6)


def test_precision_direction_follows_image_order():
    """A swapped result is evaluated with the inverse homography and scores the same."""
    p0 = _grid_points(50)
    p1 = project(H_GRAF, p0)
    p1[:5] += 4.0
    r = _result(p0, p1)
    a = precision(r, H_GRAF)
    b = precision(r.swapped(), np.linalg.inv(H_GRAF))
    assert a.correct == 45 and a.points == 50
    assert b.points == 50 and abs(b.correct - a.correct) <= 1  # thresholds differ by the local scale


def test_a_result_matched_downscaled_maps_back_to_the_originals_pixels():
    """`PairResult.in_original_frame`: keypoints matched on 800 x 640 images resized to 400 x 321
    and 200 x 161 (per-axis scales of rounded sides; pixel centres kept: x_work = sx (x + 0.5) -
    0.5) and the homography between them come back to the originals' frame, where the ground
    truth scores them all correct."""
    p0 = _grid_points(50)
    p1 = project(H_GRAF, p0)
    (sx0, sy0), (sx1, sy1) = (400 / 800, 321 / 640), (200 / 800, 161 / 640)

    def work_from_orig(sx, sy):
        return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])

    w0 = np.array([sx0, sy0]) * (p0 + 0.5) - 0.5
    w1 = np.array([sx1, sy1]) * (p1 + 0.5) - 0.5
    H_work = work_from_orig(sx1, sy1) @ H_GRAF @ np.linalg.inv(work_from_orig(sx0, sy0))
    r = _result(w0, w1)
    r.H_1_from_0 = H_work
    back = r.in_original_frame(((400, 321), (200, 161)), ((800, 640), (800, 640)))
    assert np.abs(back.kpts0 - p0).max() < 1e-3 and np.abs(back.kpts1 - p1).max() < 1e-2
    assert np.allclose(back.H_1_from_0, H_GRAF / H_GRAF[2, 2], atol=1e-6)
    assert back.image_sizes == ((800, 640), (800, 640)) and r.kpts0 is not back.kpts0
    assert precision(back, H_GRAF).correct == 50 and precision(r, H_GRAF).correct < 5


def test_empty_result_scores_zero():
    r = PairResult.empty("x", "nothing")
    rep = precision(r, H_GRAF)
    assert (rep.points, rep.correct, rep.precision) == (0, 0, 0.0)
    assert inlier_ratio(r) == 0.0


def test_local_scale_is_jacobian_determinant():
    for x, y in [(0.0, 0.0), (400.0, 320.0), (799.0, 10.0)]:
        e = 1e-3
        f = lambda p: project(H_GRAF, [p])[0]  # noqa: E731
        J = np.c_[(f((x + e, y)) - f((x - e, y))) / (2 * e), (f((x, y + e)) - f((x, y - e))) / (2 * e)]
        assert local_scale(H_GRAF, (x, y)) == pytest.approx(abs(np.linalg.det(J)), rel=1e-6)
    assert local_scale(_zoom(2.0, 100, 50), (3.0, 7.0)) == pytest.approx(4.0)
    assert local_scale(-5 * H_GRAF, (400, 320)) == pytest.approx(local_scale(H_GRAF, (400, 320)))


def test_gt_reference_on_synthetic_zoom():
    size0 = (800, 640)
    # image 1 is image 0 magnified 2x: the surface covers more pixels in image 1 -> image 1 is the reference
    assert gt_reference(_zoom(2.0, 399.5, 319.5), size0) == 1
    # image 1 is image 0 shrunk to half: image 0 holds the detail -> image 0 is the reference
    assert gt_reference(_zoom(0.5, 399.5, 319.5), size0) == 0
    # area scales within 10 %: either answer is fine
    assert gt_reference(_zoom(1.02, 399.5, 319.5), size0) is None
    assert gt_reference(_zoom(1 / 1.02, 399.5, 319.5), size0) is None
    assert gt_reference(np.eye(3), size0) is None
    # graf 1-2: img2 sees the wall obliquely, so img1 (frontal) is the detailed one
    assert gt_reference(H_GRAF, size0) == 0
    assert gt_reference(np.linalg.inv(H_GRAF), size0) == 1


def test_reference_correct():
    r = PairResult.empty("x", "")
    assert reference_correct(r, _zoom(2, 0, 0), (100, 100)) is None  # method chose no reference
    r.reference = 1
    assert reference_correct(r, _zoom(2, 0, 0), (100, 100)) is True
    assert reference_correct(r, _zoom(0.5, 0, 0), (100, 100)) is False
    assert reference_correct(r, np.eye(3), (100, 100)) is None  # GT: same scale


def test_gt_reference_direction_on_real_zoom(shared_data):
    """A real image zoomed 2x: SIFT keypoints of the same points are ~2x larger in image 1, i.e.
    image 1 resolves the surface better, and gt_reference says image 1."""
    img0 = cv2.imread(str(shared_data / "oxford" / "graf" / "img1.png"), cv2.IMREAD_GRAYSCALE)[200:456, 300:556]
    H = _zoom(2.0, 127.5, 127.5)
    img1 = cv2.warpPerspective(img0, H, (256, 256), flags=cv2.INTER_CUBIC)
    sift = cv2.SIFT_create()
    k0, d0 = sift.detectAndCompute(img0, None)
    k1, d1 = sift.detectAndCompute(img1, None)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [m for m, n in knn if m.distance < 0.75 * n.distance]
    p0 = np.array([k0[m.queryIdx].pt for m in good])
    p1 = np.array([k1[m.trainIdx].pt for m in good])
    ok = reprojection_errors(H, p0, p1) <= 3
    assert ok.sum() >= 10
    size_ratio = np.median([k1[m.trainIdx].size / k0[m.queryIdx].size for m, o in zip(good, ok, strict=True) if o])
    assert size_ratio == pytest.approx(2.0, rel=0.25)
    assert gt_reference(H, (256, 256)) == 1
