"""One more fine view for pairs whose matches lie on one surface (`PlanarConfig`; issue 13).

The fine stage fuses the `fine_top_k` best coarse views. Where one surface dominates the pair's
ORB scores (a textured ground seen from far apart), those views all rectify it, every fused
match lies on it, and COLMAP calls the pair planar (`PLANAR_OR_PANORAMIC`): it gives no initial
pair and only a weak registration. When one homography explains at least `h_ratio` of the
attempt's epipolar-verified matches (COLMAP's test at its default `max_H_inlier_ratio`, 0.8;
`recon run`'s verification calls a pair planar only from 0.95) and the
coarse search found another view far from the chosen ones in the tilt plane (radius log t,
angle 2 phi; `adaptive.tilt_plane_point`) that still overlaps the target (`min_inliers` ORB
inliers), that view is fused as well, and the attempt with more verified matches is kept.
Only for the fundamental-matrix verification (`recon run`): a homography-verified pair is
planar by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .adaptive import tilt_plane_point
from .coarse import rank_views
from .matching_utils import ransac_homography
from .types import CoarseScore, ViewParams
from .verify import verify_matches


@dataclass(frozen=True)
class PlanarConfig:
    """When and how far from the chosen views the extra fine view is taken."""

    enabled: bool = False
    """Fuse one more, distinct view into pairs whose matches fit one homography (on in
    `MatcherConfig.multiview`, i.e. `recon run`; docs/decisions.md, "A distinct view for
    one-surface pairs")."""
    h_ratio: float = 0.8
    """(0-1] A pair is one surface when a homography's inliers (`h_px`) are at least this share
    of its fundamental-matrix inliers (COLMAP's default `max_H_inlier_ratio`)."""
    h_px: float = 3.0
    """Homography inlier threshold, working px (the verification's, `verify.verify_matches`)."""
    min_distance: float = 1.0
    """Tilt-plane distance of the extra view from every chosen simulated view (1.0 ~ three tilt
    steps, or opposite longitudes at t = 2)."""
    min_inliers: int = 15
    """ORB RANSAC inliers the extra view needs in the coarse search (random matches reach ~10)."""


def one_surface(pts_ref: np.ndarray, pts_target: np.ndarray, cfg: PlanarConfig, seed: int = 0,
                f_mask: np.ndarray | None = None) -> tuple[bool, str]:
    """(whether one homography explains the matches' epipolar inliers, the evidence in words).
    `f_mask`: the matches' fundamental-matrix verification when the caller already has it (the
    attempt's own, `verify.verify_matches` with the same seed); computed here otherwise."""
    if f_mask is None or len(f_mask) != len(pts_ref):
        _, f_mask = verify_matches(pts_ref, pts_target, "fundamental", seed)
    n_f = int(np.count_nonzero(f_mask))
    if n_f < 15:
        return False, f"{n_f} epipolar inliers"
    H, h_mask = ransac_homography(np.asarray(pts_ref)[f_mask], np.asarray(pts_target)[f_mask], cfg.h_px, seed=seed)
    n_h = 0 if H is None else int(h_mask.sum())
    why = f"{n_h} of {n_f} epipolar inliers on one homography"
    return n_h >= cfg.h_ratio * n_f, why


def distinct_view(scores: list[CoarseScore], chosen: list[ViewParams], cfg: PlanarConfig) -> ViewParams | None:
    """The best-ranked coarse view with `min_inliers` ORB inliers at least `min_distance` from
    every chosen simulated view (the unwarped original does not count: it is fused anyway), or
    None."""
    simulated = [tilt_plane_point(v.t, v.phi) for v in chosen if not v.is_identity]
    for c in rank_views(scores):
        if c.inliers < cfg.min_inliers or c.view.t == 1.0 or c.view in chosen:
            continue
        p = tilt_plane_point(c.view.t, c.view.phi)
        if all(float(np.linalg.norm(p - q)) >= cfg.min_distance for q in simulated):
            return c.view
    return None
