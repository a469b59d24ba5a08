"""Counting geometrically verified matches (the escalation trigger), planar or general scene."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .matching_utils import ransac_homography


def verify_matches(pts_a: NDArray, pts_b: NDArray, model: str, seed: int = 0,
                   h_thresh_px: float = 3.0, f_thresh_px: float = 1.5) -> tuple[int, NDArray[np.bool_]]:
    """(number of inliers, mask) under a RANSAC homography or fundamental matrix (seeded)."""
    n = len(pts_a)
    if model == "homography":
        _, mask = ransac_homography(pts_a, pts_b, h_thresh_px, seed=seed)
        return int(mask.sum()), mask
    if n < 8:
        return 0, np.zeros(n, bool)
    cv2.setRNGSeed(seed)
    F, mask = cv2.findFundamentalMat(np.asarray(pts_a, np.float32), np.asarray(pts_b, np.float32),
                                     cv2.USAC_MAGSAC, f_thresh_px, 0.999, 10000)
    if F is None or mask is None:
        return 0, np.zeros(n, bool)
    mask = mask.ravel().astype(bool)
    return int(mask.sum()), mask
