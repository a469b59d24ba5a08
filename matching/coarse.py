"""Coarse search (§III-B): ORB-match every simulated view of the reference against the target.

Views are warped with nearest-neighbour interpolation (fast; ORB only needs to rank views),
ORB keypoints are mapped back to the original reference image and cached per view in the
FeatureStore, so another pair with the same reference reuses them. Every view's score is
returned, not only the best one: the fine stage and the escalation use the ranking, and the
diagnostics show the whole (tilt, longitude) grid.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Literal

import cv2

from .features import DetectorConfig, Features
from .matching_utils import ransac_homography, ratio_match
from .store import FeatureStore
from .types import CoarseScore, ViewParams
from .viewfeatures import view_features
from .views import Interp, capped_view


@dataclass(frozen=True)
class CoarseConfig:
    """ORB budget and ratio (paper: 1000, 0.75), what ranks the views, the RANSAC check, and the
    cheap rendering (ORB only has to rank views; the fine stage renders each chosen view in full).
    Its RANSAC seed is the matcher's `seed`."""

    orb_features: int = 1000
    """ORB features per view and for the target (paper: 1000)."""
    ratio: float = 0.75
    """Lowe's ratio of the ORB matches (paper: 0.75)."""
    rank_by: Literal["matches", "inliers"] = "inliers"
    """"matches" is the paper's (most ratio-test matches); "inliers" ranks by RANSAC homography
    inliers among them, which ignores views that match many repeated patterns wrongly. Both are
    always computed and reported."""
    ransac_px: float = 8.0
    """RANSAC threshold of a view's homography, px of the original target."""
    interp: Interp = "nearest"
    """Warp interpolation of the coarse views (nearest: fast, enough to rank views)."""
    antialias: bool = False
    """Blur along the compressed axis before warping (see `views.antialias_sigma`)."""
    accept_inliers: int = 40
    """With an undecided reference, a first side whose best view has half this many inliers
    settles the reference without searching the other side (`reference.settle_reference`)."""
    max_area_ratio: float = 1.0
    """A view is rendered at most this many times the original's area (zoom capped at
    sqrt(ratio * t)); the paper's zoom s = 1 + k*ds makes every steep view ~2x the original's
    area, which doubles ORB's cost for views ORB only ranks. 0 disables the cap."""
    max_side: int = 512
    """Views (and the target's ORB) are rendered as if the image's longer side were at most
    this many pixels: ranking views needs no more (docs/decisions.md). 0 disables it."""

    @property
    def detector(self) -> DetectorConfig:
        return DetectorConfig("orb", self.orb_features)


def coarse_view_features(store: FeatureStore, name: str, view: ViewParams, cfg: CoarseConfig) -> Features:
    """ORB of `view` of image `name` as the coarse search renders it (capped zoom, `max_side`),
    keypoints in original pixels; cached, so every later reader gets the same features."""
    h, w = store.image(name).shape[:2]
    rendered = capped_view(view, (w, h), cfg.max_area_ratio, cfg.max_side)
    return view_features(store, name, rendered, cfg.detector, cfg.interp, cfg.antialias)


def coarse_target_features(store: FeatureStore, target: str, cfg: CoarseConfig) -> Features:
    """The target's ORB for the coarse stage, at the coarse resolution (`max_side`)."""
    h, w = store.image(target).shape[:2]
    ident = capped_view(ViewParams(1.0, 0.0, 1.0), (w, h), 0.0, cfg.max_side)
    return view_features(store, target, ident, cfg.detector, cfg.interp, cfg.antialias)


def score_view(store: FeatureStore, ref: str, target: str, view: ViewParams, cfg: CoarseConfig,
               seed: int = 0) -> CoarseScore:
    """ORB ratio matches of one view of `ref` against `target` and their RANSAC homography."""
    fv = coarse_view_features(store, ref, view, cfg)
    ft = coarse_target_features(store, target, cfg)
    m, _ = ratio_match(fv.descriptors, ft.descriptors, cv2.NORM_HAMMING, cfg.ratio)
    inl, H = 0, None
    if len(m) >= 8:  # keypoints are already in original pixels, so H maps reference -> target
        H, mask = ransac_homography(fv.kpts[m[:, 0]], ft.kpts[m[:, 1]], cfg.ransac_px, seed=seed, max_iters=2000)
        inl = int(mask.sum())
    score = float(len(m) if cfg.rank_by == "matches" else inl)
    return CoarseScore(view=view, matches=int(len(m)), inliers=inl, score=score, H_target_from_ref=H)


def coarse_search(store: FeatureStore, ref: str, target: str, views: list[ViewParams],
                  cfg: CoarseConfig, executor: Executor | None = None, seed: int = 0) -> list[CoarseScore]:
    """Scores of all `views` of `ref` against `target`, in grid order (not sorted).

    Views at t = 1 differ only by an in-plane rotation (and s = 1), to which ORB is invariant:
    the first one is scored and its score is reported for the others (the paper's grid and
    its 45 scores are kept; two ORB runs are saved). `seed` seeds every view's RANSAC.
    """
    first_t1 = next((v for v in views if v.t == 1.0), None)
    todo = [v for v in views if v.t != 1.0 or v is first_t1]
    if executor is None:
        scored = [score_view(store, ref, target, v, cfg, seed) for v in todo]
    else:
        scored = list(executor.map(lambda v: score_view(store, ref, target, v, cfg, seed), todo))
    by_view = {c.view: c for c in scored}
    out = []
    for v in views:
        c = by_view.get(v)
        if c is None:  # another t = 1 view: same score as the first one
            assert first_t1 is not None
            base = by_view[first_t1]
            c = CoarseScore(view=v, matches=base.matches, inliers=base.inliers, score=base.score,
                            H_target_from_ref=base.H_target_from_ref)
        out.append(c)
    return out


def rank_views(scores: list[CoarseScore]) -> list[CoarseScore]:
    """Best first; ties broken by raw matches, then by smaller tilt (the cheaper, likelier view)."""
    return sorted(scores, key=lambda c: (-c.score, -c.matches, c.view.t, c.view.phi))
