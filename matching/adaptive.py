"""Adaptive per-pair work: decide from the originals' SIFT how much view simulation a pair needs.

The reference decision (`matching.reference.choose_reference`) already matches the originals'
SIFT (mutual ratio-test matches, RANSAC homography). That geometry says how much the viewpoint
changes: the homography's local affine at the inlier centroid, decomposed ASIFT-style
A = lambda R(psi) T_t R(phi), gives the transition tilt t = sigma1 / sigma2 and the longitude
phi of the compression in the reference image; the inliers' count and convex-hull area say how
much to trust it. Three paths, cheapest first (`plan_pair`):

- `originals`: many well-spread inliers and a small tilt: the originals' SIFT matches are the
  result (no coarse search, no simulated view);
- `targeted`: a confident estimate of a larger tilt: the coarse search runs only on the few grid
  views nearest the estimated (t, phi) (`nearest_views`), the fine stage on the best of them;
- `full`: no usable evidence: the full coarse grid, then the escalation, as without `adaptive`.

A path whose attempt verifies fewer than `escalation.min_inliers` matches falls through to the
next one (`matching.matcher`). Angles are degrees, phi in [0, 180) in the reference image's
pixel frame (x right, y down), the convention of `matching.views.linear_part`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .geometry import homography_jacobian, image_centre
from .types import ViewParams

Path = Literal["originals", "targeted", "full"]


@dataclass(frozen=True)
class AdaptiveConfig:
    """Thresholds of the path decision (`plan_pair`); measured reasons in docs/decisions.md."""

    originals_min_inliers: int = 80
    """The `originals` path needs at least this many RANSAC inliers among the originals' mutual
    SIFT matches (of the 1000 strongest per image, `ReferenceConfig.max_features`)."""
    originals_min_spread: float = 0.15
    """...spread over at least this fraction of the reference image (the inliers' convex-hull
    area / image area): a small cluster says nothing about the rest of the overlap..."""
    originals_max_tilt: float = 1.35
    """...and a transition tilt at most this: up to here SIFT on the originals matches about as
    well as a simulated view (graf 1-2, t 1.17: 824 points against 774 in the paper; graf 1-3,
    t 1.54: the originals give 485 points against 769, a simulated t = 1.41 view 895)."""
    targeted_min_inliers: int = 10
    """The `targeted` path needs at least this many inliers (fewer: the `full` grid); graf 1-4's
    12 inliers (of 23 mutual matches) give its tilt within 5 % (1.97 against 2.08). A wrong
    estimate only costs the few targeted views: an unverified attempt falls through..."""
    targeted_min_spread: float = 0.05
    """...spread over at least this fraction of the reference image: v_dogman 1-6's 20 inliers
    in a 4 % cluster estimate tilt 1.27 against the true 2.68 (targeted views there cost 8
    points of precision)..."""
    targeted_max_tilt: float = 8.0
    """...and an estimated tilt at most this (beyond, the estimate is a folded or wrong model)."""
    targeted_views: int = 6
    """Grid views nearest the estimated (t, phi) that the targeted coarse search scores."""


@dataclass(frozen=True)
class ViewpointEstimate:
    """What the originals' geometry says about the pair, in the reference image's frame."""

    inliers: int
    """RANSAC inliers among the originals' mutual SIFT matches."""
    spread: float
    """Convex-hull area of the reference image's inliers / the reference image's area (0..1)."""
    tilt: float
    """Transition tilt sigma1 / sigma2 of the local affine at the inlier centroid (>= 1; nan without a model)."""
    phi: float
    """Longitude of that tilt in the reference image, degrees in [0, 180) (the grid's phi)."""


@dataclass(frozen=True)
class PathPlan:
    """The chosen path, why, and the estimate it rests on (None without a homography)."""

    path: Path
    reason: str
    estimate: ViewpointEstimate | None = None


def tilt_and_longitude(A_target_from_ref: NDArray[np.float64]) -> tuple[float, float]:
    """(t, phi in degrees [0, 180)) of a 2x2 affine map A = lambda R(psi) diag(1/t, 1) R(phi).

    `matching.views.linear_part` simulates the view s diag(1/t, 1) R(phi): compress by 1/t along
    the direction at angle phi. That direction is the right singular vector of A's smaller
    singular value, and t the ratio of the singular values (ASIFT's decomposition).
    """
    _, s, vt = np.linalg.svd(np.asarray(A_target_from_ref, np.float64))
    if not np.all(np.isfinite(s)) or s[1] <= 0:
        return math.nan, math.nan
    v_min = vt[1]
    phi = math.degrees(math.atan2(v_min[1], v_min[0])) % 180.0
    return float(s[0] / s[1]), (0.0 if phi >= 180.0 - 1e-9 else phi)


def hull_spread(pts: NDArray, size: tuple[int, int]) -> float:
    """Convex-hull area of `pts` (N, 2) px / the area of a (width, height) image."""
    if len(pts) < 3:
        return 0.0
    hull = cv2.convexHull(np.asarray(pts, np.float32).reshape(-1, 1, 2))
    return float(cv2.contourArea(hull)) / float(size[0] * size[1])


def estimate_viewpoint(H_1_from_0: NDArray[np.float64] | None, inliers0: NDArray, reference: int,
                       size_ref: tuple[int, int]) -> ViewpointEstimate:
    """The estimate from the originals' homography and image 0's inlier points, expressed in
    image `reference`'s frame (the image that would be simulated; `size_ref` = its (w, h))."""
    n = len(inliers0)
    if H_1_from_0 is None or n < 4:
        return ViewpointEstimate(n, 0.0, math.nan, math.nan)
    H = np.asarray(H_1_from_0, np.float64)
    pts_ref = np.asarray(inliers0, np.float64)
    if reference == 1:
        H = np.asarray(np.linalg.inv(H), np.float64)
        q = np.c_[pts_ref, np.ones(n)] @ H_1_from_0.T
        pts_ref = q[:, :2] / q[:, 2:3]
    J = homography_jacobian(H, pts_ref.mean(axis=0))
    tilt, phi = tilt_and_longitude(J)
    return ViewpointEstimate(n, hull_spread(pts_ref, size_ref), tilt, phi)


def viewpoint_at_centre(H_1_from_0: NDArray[np.float64], reference: int,
                        size_ref: tuple[int, int]) -> tuple[float, float]:
    """(t, phi in degrees) of the homography's local affine at image `reference`'s centre, in
    that image's frame (the image that would be simulated; `size_ref` = its (w, h)): where a
    coarse view's homography says the other image is the reference, the grid views near this
    viewpoint are the ones to search there (`matching.context.MatchContext.coarse_near`)."""
    H = np.asarray(H_1_from_0, np.float64)
    if reference == 1:
        H = np.asarray(np.linalg.inv(H), np.float64)
    return tilt_and_longitude(homography_jacobian(H, image_centre(size_ref)))


def plan_pair(estimate: ViewpointEstimate | None, cfg: AdaptiveConfig, why_none: str = "") -> PathPlan:
    """The cheapest path the evidence supports (module doc), with a one-line reason."""
    if estimate is None or not math.isfinite(estimate.tilt):
        return PathPlan("full", f"{why_none or 'no homography between the originals'} -> full grid", estimate)
    e = estimate
    what = f"{e.inliers} original inliers over {100 * e.spread:.0f} % of the image, tilt {e.tilt:.2f}"
    if (e.inliers >= cfg.originals_min_inliers and e.spread >= cfg.originals_min_spread
            and e.tilt <= cfg.originals_max_tilt):
        return PathPlan("originals", f"{what} -> originals", e)
    if (e.inliers >= cfg.targeted_min_inliers and e.spread >= cfg.targeted_min_spread
            and e.tilt <= cfg.targeted_max_tilt):
        return PathPlan("targeted", f"{what} (phi {e.phi:.0f}°) -> views near it", e)
    return PathPlan("full", f"{what}: not enough evidence -> full grid", e)


def tilt_plane_point(t: float, phi_deg: float) -> NDArray[np.float64]:
    """A view as a point of the tilt plane: radius log t, angle 2 phi (phi has period 180°), so
    views with t near 1 are near each other whatever their phi."""
    r = math.log(max(t, 1.0))
    a = math.radians(2.0 * phi_deg)
    return np.array([r * math.cos(a), r * math.sin(a)])


def nearest_views(views: list[ViewParams], tilt: float, phi: float, k: int) -> list[ViewParams]:
    """The `k` grid views nearest (tilt, phi) in the tilt plane, nearest first (t = 1 views
    count once: they differ only by an in-plane rotation)."""
    target = tilt_plane_point(tilt, phi)
    seen_t1 = False
    cands = []
    for v in views:
        if v.t == 1.0:
            if seen_t1:
                continue
            seen_t1 = True
        d = float(np.linalg.norm(tilt_plane_point(v.t, v.phi) - target))
        cands.append((d, v.t, v.phi, v))
    cands.sort(key=lambda c: c[:3])
    return [c[3] for c in cands[:k]]
