"""When a pair escalates beyond the paper's fast path, and what each escalation level does.

The fast path simulates one image once and keeps one view; it fails when the reference choice
is wrong, when one view cannot serve the whole overlap, or when the transition tilt exceeds
what one-sided simulation up to t = 5.66 undoes. Levels (cheapest first, after MODS), each tried
only while the best attempt has fewer than `min_inliers` verified matches (a homography failing
`verify.plausible_homography` verifies 0); the attempt with the most verified matches wins:

1. `topk`: fuse the fine matches of the `top_k` best coarse views (several surfaces / poses);
2. `swap`: simulate the other image instead (the reference choice was wrong);
3. `pairs`: two-sided, view pair by view pair (`matching.viewpairs`);
4. `steep`: one image tilted past the grid, t = 8 .. 22.6 (`matching.steep`): grazing targets;
5. `mser`: affine-normalised MSER regions of both images in views up to t = 4, pooled with the
   best attempt and verified with the local-affine-frame check (`matching.mserlevel`);
6. `two-sided`: both images simulated and pooled (`matching.twosided`).

The levels are strategies of `matching.strategies`; this module holds only their options and the
gate. What each level solves on the EVD pairs, and at what cost, is in docs/decisions.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .mser import MserConfig
from .views import GridConfig, Interp


@dataclass(frozen=True)
class SteepConfig:
    """Options of the `steep` level (`matching.steep`): one-sided views tilted beyond the grid."""

    enabled: bool = True
    """Run the level at all."""
    tilts: tuple[float, ...] = (8.0, 11.3137, 16.0, 22.6274)
    """Tilts simulated: the paper's ratio sqrt(2) continued past its grid (k = 6..9)."""
    b: float = 72.0
    """Longitude step at t = 1, degrees (the step at tilt t is b / t, as the paper's grid)."""
    ratio: float = 0.8
    """Lowe's ratio of each view's matches against the target."""
    ransac_px: float = 8.0
    """RANSAC threshold scoring each view, px of the target (mapped-back keypoints of a view
    tilted by t carry errors of several px along the tilt)."""
    candidates: int = 6
    """Best-scoring views re-matched under their own homography."""
    guided_px: float = 12.0
    """Radius of that guided re-matching, px of the target."""
    guided_ratio: float = 0.9
    """Lowe's ratio of the guided re-matching (only nearby keypoints compete)."""
    min_matches: int = 8
    """Views with fewer ratio-test matches are not scored."""
    both_sides: bool = True
    """Also simulate the other image when the reference's views verify too little."""
    rectify_rounds: int = 2
    """Rounds of matching the reference warped by the winning view's full homography into the
    target's frame (`steep.rectified_round`; 0 = none): the affine view only approximates the
    perspective of a grazing plane, the homography does not."""
    rectify_px: float = 6.0
    """Radius of the rectified rounds' guided matching, px of the target."""
    rectify_candidates: int = 3
    """Best guided-verified views whose homographies seed rectified rounds."""
    rectify_inlier_px: float = 1.5
    """A rectified match verifies within this distance of the re-fitted homography, px of the target."""
    rectify_min_ratio: float = 0.25
    """Share of a rectified round's guided matches that must verify (see `steep.rectified_round`)."""
    rectify_contrast: float = 0.015
    """SIFT contrast threshold of the rectified rounds (both images): a grazing target keeps few
    keypoints at OpenCV's 0.04 (EVD cafe under its ground truth: 16 correct at 0.04, 51-66 at
    0.01-0.02), and matching under a known homography keeps weak keypoints' false matches out."""


@dataclass(frozen=True)
class EscalationConfig:
    """When to escalate and what each level does (see the module doc)."""

    enabled: bool = True
    """Escalate at all (the paper's plain reading does not)."""
    min_coarse_inliers: int = 0
    """Escalate only when some coarse view reached this many ORB RANSAC inliers, i.e. the images
    visibly overlap (0 = always: EVD cafe has no ORB signal at all, so the pair benchmark keeps 0;
    `MatcherConfig.multiview` uses 15, since in exhaustive matching most weak pairs simply do not
    overlap)."""
    min_inliers: int = 30
    """A pair escalates while its best attempt has fewer verified matches (RANSAC homography
    inliers at 3 px, or F-matrix inliers) than this, or when the verified homography is
    implausible (`verify.plausible_homography`)."""
    top_k: int = 4
    """Views the `topk` level fuses (skipped when not above the fast path's `fine_top_k`)."""
    swap: bool = True
    """Run the `swap` level (simulate the other image)."""
    mser: MserConfig = field(default_factory=MserConfig)
    """The `mser` level (`matching.mserlevel`): MSER regions of both images, the LAF check."""
    pairs: bool = True
    """Run the `pairs` level (`matching.viewpairs`: every view of one image against every view of
    the other, the main grid on both sides)."""
    pair_orb: int = 300
    """Strongest ORB features per view that score every view pair (the coarse searches' features,
    already computed) by RANSAC homography inliers."""
    pair_rescore: int = 64
    """The best view pairs re-scored with `pair_orb_fine` features (0 = no re-scoring)."""
    pair_orb_fine: int = 1000
    """ORB features per view of the re-scoring: `pair_orb` ranks the right view pairs of EVD fox
    far down and this many rank them first, but scoring every pair with this many costs several
    times more (docs/decisions.md)."""
    pair_top_k: int = 3
    """Best view pairs fine-matched view against view with SIFT and fused in original pixels."""
    pair_ratio: float = 0.8
    """Lowe's ratio of the view-pair SIFT matches."""
    guided_px: float = 4.0
    """Radius of the view pairs' guided re-matching under the fitted homography, px of the
    original target."""
    guided_ratio: float = 0.8
    """Lowe's ratio of that guided re-matching."""
    steep: SteepConfig = field(default_factory=SteepConfig)
    """The `steep` level (`matching.steep`): the reference tilted past the grid, t = 8 .. 22.6."""
    two_sided: bool = True
    """Run the `two-sided` level, the pooled last resort (`matching.twosided`); the only level
    that solves EVD dum, and the most expensive (docs/decisions.md)."""
    two_sided_grid: GridConfig = field(default_factory=lambda: GridConfig(n=6, ds=0.0, scale_mode="none"))
    """The grid both images are simulated over in the `two-sided` level."""
    two_sided_interp: Interp = "linear"
    """Warp interpolation of the `two-sided` views."""
    ratio: float = 0.8
    """Lowe's ratio of the `two-sided` FGINN test."""
    fginn_px: float = 8.0
    """FGINN: the second neighbour must lie this far (px) from the first, so the same point seen
    in several views does not fail the ratio test against itself."""
    knn: int = 8
    """Neighbours FLANN returns per feature in the `two-sided` level (FGINN searches them)."""


def should_escalate(cfg: EscalationConfig, verified: int, coarse_inliers: int) -> bool:
    """Whether the fast path's result (`verified` matches; `coarse_inliers` = the most ORB RANSAC
    inliers of any coarse view searched so far) goes on to the escalation levels."""
    return cfg.enabled and verified < cfg.min_inliers and coarse_inliers >= cfg.min_coarse_inliers
