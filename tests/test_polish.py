"""The local optimisation after RANSAC (`matching_utils.polish_homography`, the pair matcher's
re-fit after patch refinement; `polish_fundamental`, the F of the epipolar-guided round) on
synthetic matches of a known homography or a known two-view geometry."""

from __future__ import annotations

import cv2
import numpy as np

from matching.matching_utils import polish_fundamental, polish_homography, ransac_homography
from matching.metrics import project

H_TRUE = np.array([[0.9, 0.12, 30.0], [-0.08, 1.05, -12.0], [2e-4, -1e-4, 1.0]])


def _matches(n_good: int = 400, n_bad: int = 100, noise_px: float = 0.4, seed: int = 0):
    """Points over an 800x600 image 0, their images under H_TRUE with Gaussian noise, then
    `n_bad` random matches; returns (pts0, pts1, is_good)."""
    rng = np.random.default_rng(seed)
    pts0 = rng.uniform([0, 0], [800, 600], size=(n_good + n_bad, 2))
    pts1 = project(H_TRUE, pts0) + rng.normal(0, noise_px, size=(n_good + n_bad, 2))
    pts1[n_good:] = rng.uniform([0, 0], [800, 600], size=(n_bad, 2))
    return pts0, pts1, np.arange(n_good + n_bad) < n_good


def _shifted(H: np.ndarray, dx_px: float) -> np.ndarray:
    return np.array([[1, 0, dx_px], [0, 1, 0], [0, 0, 1.0]]) @ H


def test_polish_recovers_the_inliers_of_a_model_off_by_a_pixel():
    """A model 1.2 px off the truth explains only part of the good matches at 1.5 px; the
    polished one explains nearly all of them and none of the random ones, and lies closer to
    the truth than the start."""
    pts0, pts1, good = _matches()
    H_start = _shifted(H_TRUE, 1.2)
    start = np.linalg.norm(project(H_start, pts0[good]) - pts1[good], axis=1) <= 1.5
    H, mask = polish_homography(pts0, pts1, H_start, 1.5)
    assert start.sum() < 0.8 * good.sum()
    assert mask[good].sum() > 0.97 * good.sum()
    assert mask[~good].sum() <= 2
    err_start = np.median(np.linalg.norm(project(H_start, pts0[good]) - project(H_TRUE, pts0[good]), axis=1))
    err = np.median(np.linalg.norm(project(H, pts0[good]) - project(H_TRUE, pts0[good]), axis=1))
    assert err < 0.2 * err_start, (err_start, err)


def test_polish_explains_more_matches_than_ransac():
    """Seeded RANSAC at a tight threshold on noisy matches, then polished: more inliers on every
    seed (measured: 313 -> 323, 311 -> 316, 317 -> 334, 338 -> 348, 333 -> 338 of 400 good
    matches at 0.8 px noise), and the same input gives the same output (no sampling)."""
    for seed in range(5):
        pts0, pts1, _ = _matches(noise_px=0.8, seed=seed)
        H_r, mask_r = ransac_homography(pts0, pts1, 1.5, seed=seed)
        H_p, mask_p = polish_homography(pts0, pts1, H_r, 1.5)
        assert mask_p.sum() > mask_r.sum()
        H_again, mask_again = polish_homography(pts0, pts1, H_r, 1.5)
        assert np.array_equal(mask_p, mask_again) and np.array_equal(H_p, H_again)


def test_polish_keeps_a_model_it_cannot_improve():
    """Fewer than four explained matches: the model and its (empty) mask come back as they were."""
    pts0, pts1, _ = _matches(n_good=3, n_bad=50)
    H_far = _shifted(H_TRUE, 40.0)
    H, mask = polish_homography(pts0, pts1, H_far, 1.5)
    assert np.array_equal(H, H_far) and mask.sum() < 4


def _two_view(noise_px: float = 0.4, seed: int = 0):
    """600 points 4-8 units in front of an 800x600 pinhole camera (f = 800 px) and of a second one
    moved sideways and turned by 17 degrees, with Gaussian noise in both images; the last 100
    matches replaced by random ones. Returns (pts0, pts1, is_good)."""
    rng = np.random.default_rng(seed)
    K = np.array([[800.0, 0, 400], [0, 800, 300], [0, 0, 1]])
    X = np.c_[rng.uniform(-2, 2, (600, 2)), rng.uniform(4, 8, 600)]
    R, _ = cv2.Rodrigues(np.array([0.05, 0.3, 0.02]))
    t = np.array([-1.0, 0.1, 0.2])

    def image(P):
        q = P @ K.T
        return q[:, :2] / q[:, 2:]

    pts0 = image(X) + rng.normal(0, noise_px, (600, 2))
    pts1 = image(X @ R.T + t) + rng.normal(0, noise_px, (600, 2))
    pts1[500:] = rng.uniform([0, 0], [800, 600], (100, 2))
    return pts0, pts1, np.arange(600) < 500


def test_polished_fundamental_explains_more_true_matches_than_ransac():
    """OpenCV's FM_RANSAC at a 1 px threshold returns a seven-point sample's F; the polished F
    explains more of the true matches and still none of the random ones (measured: 395 -> 453 of
    500 at 0.4 px noise, the same for seeds 0-2)."""
    pts0, pts1, good = _two_view()
    for seed in range(3):
        cv2.setRNGSeed(seed)
        F, mask = cv2.findFundamentalMat(pts0.astype(np.float32), pts1.astype(np.float32), cv2.FM_RANSAC,
                                         1.0, 0.999, 10000)
        F_p, mask_p = polish_fundamental(pts0, pts1, F, 1.0)
        ransac_good = int(mask.ravel().astype(bool)[good].sum())
        assert mask_p[good].sum() > 1.08 * ransac_good, (ransac_good, mask_p[good].sum())
        assert mask_p[~good].sum() <= 2
        assert np.linalg.matrix_rank(F_p, tol=1e-9 * np.abs(F_p).max()) == 2
