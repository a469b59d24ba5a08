"""Coarse search (§III-B): ORB-match every simulated view of the reference against the target.

Views are warped with nearest-neighbour interpolation (fast; ORB only needs to rank views),
ORB keypoints are mapped back to the original reference image and cached per view in the
FeatureStore, so another pair with the same reference reuses them. Every view's score is
returned, not only the best one: the fine stage and the escalation use the ranking, and the
diagnostics show the (tilt, longitude) grid.

By default the grid is searched coarse to fine (`CoarseConfig.search`): a sparse subset of the
views first (`seed_views`: every `search_stride`-th longitude per tilt, the offset turning with
the tilt so that every longitude band is sampled at some tilt; while no view shows clear
overlap, >= `search_min_inliers`, the next offset, up to the whole grid), then the grid
neighbours of the best views until the best views' neighbourhoods are all scored
(`grid_neighbours`). Unscored views
are absent from the returned scores. `search="grid"` scores every view, as the paper.
"""

from __future__ import annotations

from collections.abc import Callable
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
    search: Literal["grid", "coarse-to-fine"] = "coarse-to-fine"
    """"grid" scores every view (the paper); "coarse-to-fine" scores a sparse subset, then the
    neighbours of the best views (module doc): on graf and v_dogman it finds the full grid's two
    best views on every side with a signal, scoring about half the views (docs/decisions.md)."""
    search_stride: int = 3
    """Coarse-to-fine: every this-many-th longitude of each tilt is scored first (1 = all)."""
    search_refine_top: int = 2
    """Coarse-to-fine: the unscored grid neighbours of this many best views are scored, again
    and again, until they are all scored (at least `fine_top_k`, the views the fine stage uses)."""
    search_min_inliers: int = 15
    """Coarse-to-fine: below this many RANSAC inliers in the best view of a sparse pass the side
    shows no clear overlap yet (random ORB matches reach ~10) and the next pass (the next
    longitudes) is scored; after `search_stride` passes every view is, as in "grid"."""
    settle_targeted: bool = True
    """When the reference is undecided and the first side's best view says the *other* image is
    the reference (`reference.settle_reference`), search that image only on the grid views
    nearest the viewpoint change the view's homography implies (`AdaptiveConfig.targeted_views`,
    the full search when none reaches `accept_inliers` / 2), not on its whole grid."""
    search_min_views: int = 20
    """Coarse-to-fine only for view lists of at least this many distinct ORB views (the main
    grid has 43); shorter lists, such as the adaptive path's targeted views, are scored in full."""

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


def _circular_deg(a: float, b: float) -> float:
    """Distance of two longitudes, degrees modulo 180 (phi and phi + 180 are one view)."""
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def _tilt_levels(views: list[ViewParams]) -> tuple[list[float], dict[float, float]]:
    """(the distinct tilts in increasing order, {tilt: its longitude step in degrees}); the step
    is the median gap between consecutive longitudes of that tilt (180 for a single view)."""
    levels = sorted({v.t for v in views})
    step = {}
    for t in levels:
        phis = sorted(v.phi for v in views if v.t == t)
        gaps = [b - a for a, b in zip(phis, phis[1:], strict=False)]
        step[t] = sorted(gaps)[len(gaps) // 2] if gaps else 180.0
    return levels, step


def grid_neighbours(views: list[ViewParams]) -> dict[ViewParams, list[ViewParams]]:
    """{view: its neighbours in the (tilt, longitude) grid}: the adjacent longitudes of the same
    tilt (across 0 / 180 degrees), and at the adjacent tilts the views within 0.75 of the coarser
    of the two longitude steps (every view of the first tilt above t = 1 neighbours t = 1, which
    is one view up to a rotation ORB ignores)."""
    levels, step = _tilt_levels(views)
    k_of = {t: k for k, t in enumerate(levels)}
    out: dict[ViewParams, list[ViewParams]] = {}
    for v in views:
        nb = []
        for u in views:
            if u == v:
                continue
            dk = abs(k_of[u.t] - k_of[v.t])
            d = _circular_deg(u.phi, v.phi)
            if (dk == 0 and d <= 1.01 * step[v.t]) or (
                    dk == 1 and (min(u.t, v.t) == 1.0 or d <= 0.75 * max(step[u.t], step[v.t]))):
                nb.append(u)
        out[v] = nb
    return out


def seed_views(views: list[ViewParams], stride: int, phase: int = 0) -> list[ViewParams]:
    """One sparse pass of the coarse-to-fine search: t = 1 (one view, in pass 0 only), and at
    the k-th tilt every `stride`-th longitude starting at the ((k + phase) mod stride)-th, so
    that consecutive tilts sample different longitudes (a peak narrow in longitude and spanning
    two tilts is hit); the passes `phase` = 0 .. stride - 1 together cover every view once."""
    levels, _ = _tilt_levels(views)
    out: list[ViewParams] = []
    for k, t in enumerate(levels):
        at_t = [v for v in views if v.t == t]
        if t == 1.0:
            out += at_t[:1] if phase == 0 else []
        else:
            out += at_t[(k + phase) % stride::stride]
    return out


def search_coarse_to_fine(views: list[ViewParams], score: Callable[[list[ViewParams]], list[CoarseScore]],
                          cfg: CoarseConfig) -> list[CoarseScore]:
    """Scores of the views the coarse-to-fine search visits (module doc), in visiting order.

    `score(views)` scores a batch (in parallel when the caller has a pool). Deterministic: each
    round's batch is in grid order and depends only on the scores so far.
    """
    order = {v: i for i, v in enumerate(views)}
    stride = max(1, cfg.search_stride)
    scored: dict[ViewParams, CoarseScore] = {}
    for phase in range(stride):  # sparse passes until one view shows clear overlap
        batch = [v for v in seed_views(views, stride, phase) if v not in scored]
        scored.update((c.view, c) for c in score(batch))
        if rank_views(list(scored.values()))[0].inliers >= cfg.search_min_inliers:
            break
    nb = grid_neighbours(views)
    while True:
        top = rank_views(list(scored.values()))[:max(1, cfg.search_refine_top)]
        todo = sorted({u for c in top for u in nb[c.view] if u not in scored}, key=order.__getitem__)
        if not todo:
            return list(scored.values())
        scored.update((c.view, c) for c in score(todo))


def coarse_search(store: FeatureStore, ref: str, target: str, views: list[ViewParams],
                  cfg: CoarseConfig, executor: Executor | None = None, seed: int = 0) -> list[CoarseScore]:
    """Scores of the searched `views` of `ref` against `target`, in grid order (not sorted):
    all of them with `search="grid"` or a short list, else those the coarse-to-fine search
    visits (module doc).

    Views at t = 1 differ only by an in-plane rotation (and s = 1), to which ORB is invariant:
    the first one is scored and its score is reported for the others (the paper's grid and
    its 45 scores are kept; two ORB runs are saved). `seed` seeds every view's RANSAC.
    """
    first_t1 = next((v for v in views if v.t == 1.0), None)
    todo = [v for v in views if v.t != 1.0 or v is first_t1]

    def score(batch: list[ViewParams]) -> list[CoarseScore]:
        if executor is None:
            return [score_view(store, ref, target, v, cfg, seed) for v in batch]
        return list(executor.map(lambda v: score_view(store, ref, target, v, cfg, seed), batch))

    if cfg.search == "coarse-to-fine" and len(todo) >= cfg.search_min_views:
        scored = search_coarse_to_fine(todo, score, cfg)
    else:
        scored = score(todo)
    by_view = {c.view: c for c in scored}
    out = []
    for v in views:
        c = by_view.get(v)
        if c is None and (v.t != 1.0 or first_t1 not in by_view):
            continue  # not visited by the coarse-to-fine search
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
