"""Escalation for pairs the paper's fast path cannot solve, cheapest first (after MODS).

The fast path simulates one image once and keeps one view; it fails when the reference choice
is wrong, when one view cannot serve the whole overlap, or when the transition tilt exceeds
what one-sided simulation up to t = 5.66 undoes (EVD pairs reach ~50). Levels, each tried only
while the best attempt has fewer than `min_inliers` verified matches:

1. `topk`: fuse the fine matches of the `top_k` best coarse views (several surfaces / poses);
2. `swap`: simulate the other image instead (the reference choice was wrong);
3. `two-sided`: simulate both images over a tilt grid reaching `two_sided_max_tilt` (as ASIFT
   and MODS do), pool each image's SIFT features in original coordinates, and match the pools
   with FLANN and the first-geometrically-inconsistent-nearest-neighbour ratio test (MODS'
   FGINN: the second neighbour must lie `fginn_px` away from the first, so the same point
   seen in several views does not fail the ratio test against itself).
The attempt with the most verified inliers wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from .coarse import coarse_search, view_features
from .features import DetectorConfig, Features
from .fine import FineMatches
from .matching_utils import unique_train
from .store import FeatureStore
from .types import CoarseScore, ViewParams
from .verify import verify_matches
from .views import GridConfig, view_grid

if TYPE_CHECKING:
    from .matcher import ExtraAffineMatcher


@dataclass(frozen=True)
class EscalationConfig:
    enabled: bool = True
    min_inliers: int = 30
    top_k: int = 4
    swap: bool = True
    two_sided: bool = True
    two_sided_grid: GridConfig = field(default_factory=lambda: GridConfig(n=6, ds=0.0, scale_mode="none"))
    two_sided_interp: str = "linear"
    ratio: float = 0.8
    fginn_px: float = 8.0
    knn: int = 8


@dataclass
class Attempt:
    """One way of matching the pair: which image was simulated, the fused fine matches, and
    how many of them a RANSAC model verified."""

    label: str
    reference: int
    fine: FineMatches
    views: list[ViewParams]
    coarse: list[CoarseScore]
    verified: int


def escalate(m: "ExtraAffineMatcher", store: FeatureStore, names: tuple[str, str], fast: Attempt,
             coarse: dict[int, list[CoarseScore]]) -> Attempt:
    """Run the escalation levels until one reaches `min_inliers`; return the best attempt."""
    cfg = m.cfg.escalation
    best = fast
    if cfg.top_k > m.cfg.fine_top_k:
        att = m._attempt(store, names, fast.reference, coarse[fast.reference], cfg.top_k, "topk")
        best = max(best, att, key=lambda a: a.verified)
        if best.verified >= cfg.min_inliers:
            return best
    if cfg.swap:
        other = 1 - fast.reference
        if other not in coarse:
            coarse[other] = coarse_search(store, names[other], names[fast.reference], m.views, m.cfg.coarse, m._pool)
        att = m._attempt(store, names, other, coarse[other], max(cfg.top_k, 1), "swap")
        best = max(best, att, key=lambda a: a.verified)
        if best.verified >= cfg.min_inliers:
            return best
    if cfg.two_sided:
        att = two_sided_attempt(m, store, names, best)
        best = max(best, att, key=lambda a: a.verified)
    return best


def pooled_features(store: FeatureStore, name: str, views: list[ViewParams], det: DetectorConfig,
                    interp: str, pool) -> tuple[Features, NDArray[np.int32]]:
    """All views' features of one image, keypoints in the original frame, and each one's view index."""
    fn = lambda v: view_features(store, name, v, det, interp, True)  # noqa: E731
    parts = list(pool.map(fn, views)) if pool is not None else [fn(v) for v in views]
    view_idx = np.concatenate([np.full(len(f), i, np.int32) for i, f in enumerate(parts)])
    feats = Features(np.concatenate([f.kpts for f in parts]), np.concatenate([f.sizes for f in parts]),
                     np.concatenate([f.angles for f in parts]), np.concatenate([f.descriptors for f in parts]))

    return feats, view_idx


def fginn_match(fa: Features, fb: Features, ratio: float, fginn_px: float, knn: int, seed: int,
                ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """FLANN k-NN from a to b with the FGINN ratio test (see module doc); one-to-one on b."""
    if len(fa) < 1 or len(fb) < 2:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    cv2.setRNGSeed(seed)
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    k = min(knn, len(fb))
    res = flann.knnMatch(fa.descriptors.astype(np.float32), fb.descriptors.astype(np.float32), k=k)
    out, dist = [], []
    r2 = fginn_px * fginn_px
    for nn in res:
        if len(nn) < 2:
            continue
        first = nn[0]
        p = fb.kpts[first.trainIdx]
        second = None
        for cand in nn[1:]:
            q = fb.kpts[cand.trainIdx]
            if (q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2 > r2:
                second = cand
                break
        if second is None or first.distance < ratio * second.distance:
            out.append((first.queryIdx, first.trainIdx))
            dist.append(first.distance)
    if not out:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    return unique_train(np.asarray(out, np.int32), np.asarray(dist, np.float32))


def dedupe_by_location(kpts_a: NDArray, kpts_b: NDArray, matches: NDArray[np.int32], dist: NDArray,
                       cell_px: float = 1.5) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Drop matches whose (point a, point b) repeat within `cell_px` (the same point found in
    several views); keeps the closest descriptor of each group."""
    if len(matches) == 0:
        return matches, dist
    key = np.concatenate([np.floor(kpts_a[matches[:, 0]] / cell_px), np.floor(kpts_b[matches[:, 1]] / cell_px)], axis=1)
    order = np.argsort(dist, kind="stable")
    _, first = np.unique(key[order], axis=0, return_index=True)
    keep = np.sort(order[first])
    return matches[keep], dist[keep]


def two_sided_attempt(m: "ExtraAffineMatcher", store: FeatureStore, names: tuple[str, str], prev: Attempt) -> Attempt:
    """Simulate both images over the two-sided grid and match the pooled SIFT (see module doc)."""
    cfg = m.cfg.escalation
    det = m.cfg.fine.detector
    views = view_grid(cfg.two_sided_grid)
    ref = prev.reference
    fa, _ = pooled_features(store, names[ref], views, det, cfg.two_sided_interp, m._pool)
    fb, _ = pooled_features(store, names[1 - ref], views, det, cfg.two_sided_interp, m._pool)
    mm, d = fginn_match(fa, fb, cfg.ratio, cfg.fginn_px, cfg.knn, m.cfg.seed)
    mm, d = dedupe_by_location(fa.kpts, fb.kpts, mm, d)
    used_a, inv_a = np.unique(mm[:, 0], return_inverse=True) if len(mm) else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    used_b, inv_b = np.unique(mm[:, 1], return_inverse=True) if len(mm) else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    matches = np.stack([inv_a.ravel(), inv_b.ravel()], axis=1).astype(np.int32) if len(mm) else np.zeros((0, 2), np.int32)
    fine = FineMatches(fa.kpts[used_a], fb.kpts[used_b], matches, d.astype(np.float32), {"two-sided": int(len(mm))})
    n_ver, _ = verify_matches(fine.kpts_ref[matches[:, 0]], fine.kpts_target[matches[:, 1]], m.cfg.verify_model, m.cfg.seed) \
        if len(matches) else (0, None)
    return Attempt(label="two-sided", reference=ref, fine=fine, views=[], coarse=prev.coarse, verified=n_ver)
