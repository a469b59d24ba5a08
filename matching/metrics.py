"""Evaluation metrics of the paper (§IV-B) and the ground-truth reference choice.

Conventions:
- Points are (x, y) pixels, OpenCV convention (see `matching.types`), as (N, 2) arrays.
- A homography `H_1_from_0` maps image-0 pixels to image-1 pixels: x1 ~ H @ [x0, y0, 1].
- A `PairResult` always lists its points in image 0 / image 1 order, whichever image the
  method chose to simulate (its `reference`), so the ground-truth homography of the pair
  (image 0 -> image 1) applies directly; no direction flip is ever needed here. For a pair
  stored the other way round, pass `np.linalg.inv(H)` or use `PairResult.swapped()`.
- "Final matches" are the RANSAC inliers when the method fitted a homography (the paper's
  final result is after RANSAC), otherwise all its matches (`inliers_only=True`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .geometry import image_centre, local_scale, scale_1_from_0
from .types import PairResult

__all__ = [
    "DEFAULT_TH", "SAME_SCALE_TOL", "PrecisionReport", "gt_reference", "image_centre", "inlier_ratio", "local_scale",
    "precision", "precision_of_points", "project", "reference_correct", "reprojection_errors",
]

DEFAULT_TH = math.sqrt(3.0)  # paper's default Th: the 3x3 pixel neighbourhood of the true point
SAME_SCALE_TOL = 1.1  # local scales within this factor: either image is an acceptable reference


def project(H: ArrayLike, pts: ArrayLike) -> NDArray[np.float64]:
    """Map (N, 2) points through the 3x3 homography H; (N, 2) float64.

    Points that map to infinity (homogeneous w = 0) come out as inf, so they never count as
    correct.
    """
    H = np.asarray(H, np.float64)
    p = np.asarray(pts, np.float64).reshape(-1, 2)
    q = p @ H[:, :2].T + H[:, 2]
    w = q[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = q[:, :2] / w
    out[~np.isfinite(out).all(axis=1)] = np.inf
    out[(np.abs(w) < 1e-15).ravel()] = np.inf
    return out


def reprojection_errors(H_1_from_0: ArrayLike, pts0: ArrayLike, pts1: ArrayLike) -> NDArray[np.float64]:
    """(N,) Euclidean distance in image 1 between H(pts0[i]) and pts1[i] (Eq. 6's left side)."""
    p1 = np.asarray(pts1, np.float64).reshape(-1, 2)
    d = project(H_1_from_0, pts0) - p1
    with np.errstate(invalid="ignore"):
        e = np.sqrt((d * d).sum(axis=1))
    e[~np.isfinite(e)] = np.inf
    return e


@dataclass(frozen=True)
class PrecisionReport:
    """Eq. 5: `points` = Pt_Num (final matches), `correct` = R_Num, precision = R_Num / Pt_Num.

    precision is 0.0 when there are no points (a method that finds nothing scores nothing).
    """

    points: int
    correct: int
    precision: float


def precision_of_points(pts0: ArrayLike, pts1: ArrayLike, H_1_from_0_gt: ArrayLike,
                        th: float = DEFAULT_TH) -> PrecisionReport:
    """Eq. 5-6 on explicit matched points: correct where |H(pts0) - pts1| <= th pixels."""
    e = reprojection_errors(H_1_from_0_gt, pts0, pts1)
    n = int(len(e))
    k = int(np.count_nonzero(e <= th))
    return PrecisionReport(points=n, correct=k, precision=(k / n) if n else 0.0)


def precision(result: PairResult, H_1_from_0_gt: ArrayLike, th: float = DEFAULT_TH,
              inliers_only: bool = True) -> PrecisionReport:
    """The paper's precision (Eq. 5-6) of a PairResult against the true homography.

    Pt_Num is the number of final matches (RANSAC inliers when the method fitted a homography
    and `inliers_only`, else all matches); a match (p0, p1) is correct when the true homography
    maps p0 to within `th` pixels (<=, default sqrt(3)) of p1. `H_1_from_0_gt` maps image 0 to
    image 1 of the result, whatever reference the method chose (see module doc).
    """
    pts0, pts1 = result.matched_points(inliers_only=inliers_only)
    return precision_of_points(pts0, pts1, H_1_from_0_gt, th)


def inlier_ratio(result: PairResult) -> float:
    """Eq. 7: RANSAC inliers / matches before RANSAC (In_Num / Pt_Num), for pairs without GT.

    1.0 when the method fitted no homography (every match is kept), 0.0 with no matches.
    """
    n = result.num_matches
    return result.num_inliers / n if n else 0.0


def gt_reference(H_1_from_0: ArrayLike, size0: tuple[int, int], tol: float = SAME_SCALE_TOL) -> int | None:
    """Which image the ground truth says is the reference (more detailed) one: 0, 1 or None.

    With s = `geometry.scale_1_from_0(H_1_from_0, size0)` (`size0` = (width, height)): s < 1
    means image 0 shrinks when mapped into image 1, i.e. the same surface covers more pixels
    in image 0, whose camera is closer / more frontal: image 0 is the reference (the rule
    `matching.reference` applies too). s > 1: image 1. When the *area* scales s^2 are within
    `tol` (10 % by default) both choices are acceptable and None is returned.
    """
    s = scale_1_from_0(H_1_from_0, size0)
    if not math.isfinite(s):
        return None
    if abs(2.0 * math.log(s)) < math.log(tol):
        return None
    return 0 if s < 1 else 1


def reference_correct(result: PairResult, H_1_from_0_gt: ArrayLike, size0: tuple[int, int],
                      tol: float = SAME_SCALE_TOL) -> bool | None:
    """Whether the method's reference agrees with `gt_reference`; None when either is None."""
    if result.reference is None:
        return None
    gt = gt_reference(H_1_from_0_gt, size0, tol)
    if gt is None:
        return None
    return int(result.reference) == gt
