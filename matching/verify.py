"""Counting geometrically verified matches (the escalation trigger), planar or general scene.

A homography with many RANSAC inliers can still be wrong: a repeated pattern (windows, tiles)
or a cluster of matches on one line supports a degenerate or folded model. `plausible_homography`
rejects models no camera motion of a plane produces, so such a pair keeps escalating.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .geometry import homography_jacobian
from .matching_utils import ransac_homography


def plausible_homography(H: NDArray[np.float64] | None, pts_a: NDArray, max_anisotropy: float = 40.0,
                         max_scale: float = 30.0) -> bool:
    """Whether `H` (a -> b) could come from a plane seen by two cameras, over the region of `pts_a`.

    Checks at the four corners of the bounding box of `pts_a` (the matched region): the
    projective depth w stays positive (the horizon does not cross the region), the local affine
    keeps orientation (det > 0: no mirror), its area scale is within [1/max_scale^2, max_scale^2]
    and its anisotropy (singular value ratio: the transition tilt) stays below `max_anisotropy`
    (above the hardest EVD pair's, docs/decisions.md).
    """
    if H is None or len(pts_a) < 4:
        return False
    lo, hi = np.min(pts_a, axis=0), np.max(pts_a, axis=0)
    for x, y in ((lo[0], lo[1]), (hi[0], lo[1]), (lo[0], hi[1]), (hi[0], hi[1])):
        if (H[2, 0] * x + H[2, 1] * y + H[2, 2]) * H[2, 2] <= 0:
            return False
        J = homography_jacobian(H, (x, y))
        det = float(np.linalg.det(J))
        if not np.isfinite(det) or det <= 0 or not (1.0 / max_scale**2 <= det <= max_scale**2):
            return False
        s = np.linalg.svd(J, compute_uv=False)
        if s[0] > max_anisotropy * s[1]:
            return False
    return True


def verify_matches(pts_a: NDArray, pts_b: NDArray, model: str, seed: int = 0,
                   h_thresh_px: float = 3.0, f_thresh_px: float = 1.5) -> tuple[int, NDArray[np.bool_]]:
    """(number of inliers, mask) under a RANSAC homography or fundamental matrix (seeded).

    A homography that fails `plausible_homography` on its inliers verifies nothing (0, all False).
    """
    n = len(pts_a)
    if model == "homography":
        H, mask = ransac_homography(pts_a, pts_b, h_thresh_px, seed=seed)
        if not plausible_homography(H, np.asarray(pts_a)[mask]):
            return 0, np.zeros(n, bool)
        return int(mask.sum()), mask
    if n < 8:
        return 0, np.zeros(n, bool)
    cv2.setRNGSeed(seed)
    F, f_mask = cv2.findFundamentalMat(np.asarray(pts_a, np.float32), np.asarray(pts_b, np.float32),
                                       cv2.USAC_MAGSAC, f_thresh_px, 0.999, 10000)
    if F is None or f_mask is None:
        return 0, np.zeros(n, bool)
    inliers = np.asarray(f_mask).ravel().astype(bool)
    return int(inliers.sum()), inliers
