"""Choosing the reference image (the one simulated): the one whose camera is closer and so holds
more detail. The whole decision lives here, in three places of the matcher's run:

1. `choose_reference`, from SIFT of the two originals. The paper (§III-A, Eq. 1) sums, over
   segments between consecutive ratio-test matches, the difference of segment lengths in the
   two images weighted by descriptor similarity; f0 uses matching 0 -> 1, f1 matching 1 -> 0,
   and the image with the larger coefficient is the reference. That sum is dominated by
   outliers on extreme pairs (most SIFT matches of the originals are wrong there), so the
   default `robust` variant reads the relative scale off a RANSAC homography of mutual
   matches instead, at image 0's centre as the ground-truth check does (or, without image
   sizes, the median log ratio of inlier segment lengths). When the originals barely match
   (fewer than `min_inliers`) the decision is "undecided".
2. `settle_reference`, after the coarse search: an undecided reference is settled by the
   geometry of the best coarse view of the side Eq. 1 prefers when that view is verified,
   else by searching both sides and keeping the better best view.
3. `reference_from_final_homography`: when an escalation level simulated both images, the
   verified final homography says which one is larger.

Every case reads the same quantity, `geometry.scale_1_from_0` (how much larger image 1 shows the
scene than image 0, at image 0's centre), and applies the same rule, `larger_image`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .coarse import rank_views
from .features import Features, strongest
from .geometry import scale_1_from_0
from .matching_utils import ransac_homography, ratio_match
from .types import CoarseScore, PairResult

ReferenceMode = Literal["paper", "robust"]


@dataclass(frozen=True)
class ReferenceConfig:
    """How the reference is chosen from the originals (step 1 of the module doc) and when two
    scales count as equal. Its RANSAC seed is the matcher's `seed`."""

    mode: ReferenceMode = "robust"
    """"paper" (Eq. 1) or "robust" (relative scale of a RANSAC homography of mutual matches)."""
    ratio: float = 0.75
    """Lowe's ratio for the SIFT matches of the originals (paper: 0.75)."""
    min_inliers: int = 30
    """Below this many mutual matches or RANSAC inliers between the originals the robust
    decision is "undecided" and the coarse search settles it (see docs/decisions.md)."""
    ransac_px: float = 4.0
    """RANSAC threshold of the originals' homography, px of image 1."""
    scale_tolerance: float = 1.1
    """Linear relative scales within this factor count as equal: image 0 (or the side searched
    first, when the coarse search settles it) is then the reference, and no side is wrong."""
    max_segments: int = 2000
    """Random inlier segments of the median-log-ratio fallback (used without image sizes)."""
    max_features: int = 1000
    """SIFT points per image for this step (the paper's cap): the strongest of the features
    detected at `decision_scale`."""
    decision_scale: float = 0.5
    """(0, 1] Each original is downscaled by this factor (area interpolation) for this step's SIFT,
    keypoints mapped back to full-resolution pixels (`viewfeatures.decision_features`). 1 = the
    full-resolution SIFT that the fine stage also reads (the paper's, and `recon run`'s: in a scene
    every original's full-resolution SIFT is needed as some pair's target anyway). Why 0.5 for the
    pair matcher: a scale ratio and a rough homography need only the 1000 strongest, mostly coarse
    features, and a half-size detection costs a quarter of a full one, while on a pair that
    simulates views the reference's full-resolution SIFT served nothing but this step. On the 18
    shared pairs the reference and the path are the same as at 1 on every pair and the targeted
    views on 17 (docs/decisions.md, "Reference decision at half resolution")."""

    def __post_init__(self) -> None:
        if not 0.0 < self.decision_scale <= 1.0:
            raise ValueError(f"ReferenceConfig.decision_scale must be in (0, 1], not {self.decision_scale!r}")


@dataclass
class ReferenceDecision:
    """Which image to simulate (0 or 1, or None when undecided), the coefficients and why."""

    reference: int | None
    f0: float
    f1: float
    reason: str
    inliers: int = 0
    scale_1_from_0: float | None = None  # linear scale factor image 0 -> image 1 (robust mode)
    H_1_from_0: NDArray[np.float64] | None = None  # the originals' RANSAC homography (robust mode)
    inliers0: NDArray[np.float32] | None = None  # its inliers' points in image 0, px (robust mode)


def larger_image(scale_1_from_0: float, tolerance: float) -> int | None:
    """The image that shows the scene larger (0 or 1) given `geometry.scale_1_from_0`, or None
    when the two scales are equal within `tolerance` (a linear factor) or the scale is unknown.

    Below 1, image 0 shrinks when mapped into image 1: image 0 holds more detail.
    """
    if not math.isfinite(scale_1_from_0) or abs(math.log(scale_1_from_0)) < math.log(tolerance):
        return None
    return 0 if scale_1_from_0 < 1.0 else 1


def paper_coefficient(pts_a: NDArray, pts_b: NDArray, dist: NDArray) -> float:
    """Eq. 1: sum_i (|a_i a_i+1| - |b_i b_i+1|) * (1 - (Des_i + Des_i+1) / 1000).

    `pts_a[i]`, `pts_b[i]` are the i-th match's points in the source and destination images,
    in match-list order; Des is the SIFT descriptor L2 distance (OpenCV units, 0..~512).
    Segments join consecutive matches (the paper's garbled bound "4i+1 < n" read as i < n - 1).
    """
    if len(pts_a) < 2:
        return 0.0
    la = np.linalg.norm(np.diff(pts_a, axis=0), axis=1)
    lb = np.linalg.norm(np.diff(pts_b, axis=0), axis=1)
    w = 1.0 - (dist[:-1] + dist[1:]) / 1000.0
    return float(np.sum((la - lb) * w))


def median_log_scale(pts0: NDArray, pts1: NDArray, max_segments: int, seed: int) -> float:
    """Median over random inlier segments of log(|segment in 1| / |segment in 0|)."""
    n = len(pts0)
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, max_segments)
    j = rng.integers(0, n, max_segments)
    keep = i != j
    l0 = np.linalg.norm(pts0[i[keep]] - pts0[j[keep]], axis=1)
    l1 = np.linalg.norm(pts1[i[keep]] - pts1[j[keep]], axis=1)
    ok = (l0 > 4.0) & (l1 > 4.0)  # short segments are all quantisation noise
    if not np.any(ok):
        return 0.0
    return float(np.median(np.log(l1[ok] / l0[ok])))


def choose_reference(feat0: Features, feat1: Features, cfg: ReferenceConfig = ReferenceConfig(),
                     image0_size: tuple[int, int] | None = None, seed: int = 0) -> ReferenceDecision:
    """Decide the reference from SIFT features of the two originals (step 1 of the module doc).

    `image0_size` (w, h): when given, the robust scale is `geometry.scale_1_from_0` of the RANSAC
    homography (what the ground-truth check measures; under strong perspective it differs from
    the median over the inliers, see docs/decisions.md). `seed` seeds RANSAC and the segment
    sampling.
    """
    feat0, feat1 = strongest(feat0, cfg.max_features), strongest(feat1, cfg.max_features)
    m01, d01 = ratio_match(feat0.descriptors, feat1.descriptors, cv2.NORM_L2, cfg.ratio, seed)
    m10, d10 = ratio_match(feat1.descriptors, feat0.descriptors, cv2.NORM_L2, cfg.ratio, seed)
    f0 = paper_coefficient(feat0.kpts[m01[:, 0]], feat1.kpts[m01[:, 1]], d01) if len(m01) else 0.0
    f1 = paper_coefficient(feat1.kpts[m10[:, 0]], feat0.kpts[m10[:, 1]], d10) if len(m10) else 0.0
    if cfg.mode == "paper":
        if len(m01) < 2 and len(m10) < 2:
            return ReferenceDecision(None, f0, f1, "paper: originals share no ratio-test matches")
        ref = 0 if f0 >= f1 else 1
        return ReferenceDecision(ref, f0, f1, f"paper Eq.1: f0={f0:.1f} {'>=' if ref == 0 else '<'} f1={f1:.1f}")

    # robust: mutual ratio-test matches -> RANSAC homography -> its scale at image 0's centre
    back = {int(q): int(t) for q, t in m10}
    mutual = np.array([back.get(int(t), -1) == int(q) for q, t in m01], bool) if len(m01) else np.zeros(0, bool)
    m = m01[mutual]
    p0, p1 = feat0.kpts[m[:, 0]], feat1.kpts[m[:, 1]]
    if len(m) < max(cfg.min_inliers, 4):
        why = f"undecided: only {len(m)} mutual SIFT matches between the originals"
        if len(m) < 8:
            return ReferenceDecision(None, f0, f1, why)
        # too few to decide, but the homography is kept as evidence for the adaptive paths
        H, inl = ransac_homography(p0, p1, cfg.ransac_px, seed=seed)
        return ReferenceDecision(None, f0, f1, why, int(inl.sum()), H_1_from_0=H, inliers0=p0[inl])
    H, inl = ransac_homography(p0, p1, cfg.ransac_px, seed=seed)
    n_in = int(inl.sum())
    if H is None or n_in < cfg.min_inliers:
        return ReferenceDecision(None, f0, f1, f"undecided: {n_in} RANSAC inliers between the originals", n_in,
                                 H_1_from_0=H, inliers0=p0[inl])
    scale = scale_1_from_0(H, image0_size) if image0_size is not None else math.nan
    if not math.isfinite(scale):  # no image size (or no scale at the centre): median over inlier segments
        scale = math.exp(median_log_scale(p0[inl], p1[inl], cfg.max_segments, seed))
    larger = larger_image(scale, cfg.scale_tolerance)
    if larger is None:
        why = f"scales equal within {cfg.scale_tolerance:.2f}x (0->1 scale {scale:.2f}, {n_in} inliers)"
        return ReferenceDecision(0, f0, f1, why, n_in, scale, H, p0[inl])
    why = f"image {larger} is {max(scale, 1 / scale):.2f}x larger ({n_in} inliers)"
    return ReferenceDecision(larger, f0, f1, why, n_in, scale, H, p0[inl])


def settle_reference(decision: ReferenceDecision, coarse_for: Callable[[int], list[CoarseScore]],
                     image0_size: tuple[int, int], cfg: ReferenceConfig, accept_inliers: int,
                     coarse_near: Callable[[int, NDArray[np.float64]], list[CoarseScore]] | None = None) -> int:
    """The side to simulate, after the coarse search (step 2 of the module doc).

    `coarse_for(side)` runs (or returns the cached) coarse search with image `side` simulated.
    A decided reference is kept and its side searched. An undecided one: the side Eq. 1 prefers
    is searched first; if its best view is verified (>= `accept_inliers` / 2 RANSAC inliers),
    that view's homography gives `scale_1_from_0`, the larger image (by > `scale_tolerance`)
    becomes the reference and the first side stays when the scales are about equal;
    `decision` is updated in place (reference and reason). When that makes the other side the
    reference and `coarse_near(side, H_1_from_0)` is given, it searches that side near the
    viewpoint the view's homography implies instead of `coarse_for`
    (`CoarseConfig.settle_targeted`). With no verified view both sides are searched and the one
    whose best view scores higher is returned, `decision` left undecided (`reason_for` then says
    "by coarse score").
    """
    if decision.reference is not None:
        coarse_for(decision.reference)
        return decision.reference
    first = 0 if decision.f0 >= decision.f1 else 1
    best = rank_views(coarse_for(first))[0]
    if best.inliers >= accept_inliers // 2 and best.H_target_from_ref is not None:
        H = best.H_target_from_ref
        scale = scale_1_from_0(H if first == 0 else np.linalg.inv(H), image0_size)
        if not math.isfinite(scale):
            scale = 1.0
        larger = larger_image(scale, cfg.scale_tolerance)
        chosen = first if larger is None else larger
        if chosen != first and coarse_near is not None:
            coarse_near(chosen, H if first == 0 else np.asarray(np.linalg.inv(H), np.float64))
        else:
            coarse_for(chosen)
        decision.reference = chosen
        decision.reason += (f"; coarse view geometry: image 0 maps {scale:.2f}x into image 1 at its centre, "
                            f"so image {chosen} is the reference")
        return chosen
    coarse = {first: coarse_for(first), 1 - first: coarse_for(1 - first)}
    return max(coarse, key=lambda s: (max(c.score for c in coarse[s]), -s))


def reason_for(decision: ReferenceDecision, reference: int) -> str:
    """Why image `reference` was simulated: the decision's reason, plus "chose image k by coarse
    score" when the decision was undecided or an escalation level simulated the other image."""
    if reference == decision.reference:
        return decision.reason
    return f"{decision.reason}; chose image {reference} by coarse score"


def reference_from_final_homography(result: PairResult, image0_size: tuple[int, int], min_inliers: int) -> PairResult:
    """Step 3 of the module doc: for a result whose level simulated both images, neither was "the"
    reference; report the one the verified final homography `result.H_1_from_0` says is larger
    (at the centre of image 0, of `image0_size` (w, h)). Unchanged when it has fewer than
    `min_inliers` inliers or no scale."""
    if result.H_1_from_0 is None:
        return result
    scale = scale_1_from_0(result.H_1_from_0, image0_size)
    if not math.isfinite(scale) or result.num_inliers < min_inliers:
        return result
    ref = 0 if scale <= 1.0 else 1
    result.reference = ref  # type: ignore[assignment]
    result.reference_reason += (f"; both images simulated, final homography: image {ref} is "
                                f"{max(scale, 1 / scale):.2f}x larger")
    return result
