"""The `pairs` escalation level: two-sided matching, view pair by view pair.

Every view of the reference is paired with every view of the target (the main grid on both
sides: 45 x 45, so transition tilts up to 32), each pair scored by ORB RANSAC homography inliers
with the features the coarse searches already computed; the best few pairs are SIFT-matched view
against view, fused in original pixels, then re-matched under the homography they verify
(`EscalationConfig` holds the budgets).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .coarse import coarse_view_features
from .context import Attempt, MatchContext
from .features import Features, strongest
from .fine import FineMatches, guided_match
from .matching_utils import dedupe_by_location, ransac_homography, ratio_match
from .types import ViewParams
from .viewfeatures import view_features


@dataclass(frozen=True)
class PairScore:
    """ORB evidence that view `a` of the reference and view `b` of the target see the scene alike."""

    a: ViewParams
    b: ViewParams
    matches: int
    inliers: int


def hamming_ratio_match(fa: Features, fb: Features, ratio: float) -> NDArray[np.int32]:
    """Lowe's ratio test on ORB descriptors (exact, array-based; see `ratio_match`)."""
    return ratio_match(fa.descriptors, fb.descriptors, cv2.NORM_HAMMING, ratio)[0]


def score_pair(fa: Features, fb: Features, a: ViewParams, b: ViewParams, ratio: float, ransac_px: float,
               seed: int) -> PairScore:
    """ORB ratio matches of two views and their RANSAC homography inliers (original pixels)."""
    mm = hamming_ratio_match(fa, fb, ratio)
    inl = 0
    if len(mm) >= 8:
        _, mask = ransac_homography(fa.kpts[mm[:, 0]], fb.kpts[mm[:, 1]], ransac_px, seed=seed, max_iters=1000)
        inl = int(mask.sum())
    return PairScore(a, b, int(len(mm)), inl)


def rank_pairs(scores: list[PairScore]) -> list[PairScore]:
    """Most inliers first; ties by matches, then by the smaller tilt product (cheaper views)."""
    return sorted(scores, key=lambda s: (-s.inliers, -s.matches, s.a.t * s.b.t, s.a.phi, s.b.phi))


def score_view_pairs(ctx: MatchContext, ref: int) -> list[PairScore]:
    """All pairs of the main grid's views (`ref` simulated as `a`), scored with `pair_orb` ORB per
    view, the best `pair_rescore` of them re-scored with `pair_orb_fine`; best first."""
    cfg, cc, views = ctx.cfg.escalation, ctx.cfg.coarse, ctx.views
    seed = ctx.cfg.seed

    def feats(side: int, n: int) -> dict[ViewParams, Features]:
        def one(v: ViewParams) -> Features:
            return strongest(coarse_view_features(ctx.store, ctx.names[side], v, cc), n)

        return dict(zip(views, ctx.map(one, views), strict=True))

    fa, fb = feats(ref, cfg.pair_orb), feats(1 - ref, cfg.pair_orb)
    rows = ctx.map(lambda a: [score_pair(fa[a], fb[b], a, b, cc.ratio, cc.ransac_px, seed) for b in views], views)
    ranked = rank_pairs([s for r in rows for s in r])
    if cfg.pair_rescore <= 0 or cfg.pair_orb_fine <= cfg.pair_orb:
        return ranked
    head = ranked[:cfg.pair_rescore]
    fa, fb = feats(ref, cfg.pair_orb_fine), feats(1 - ref, cfg.pair_orb_fine)
    rescored = ctx.map(lambda p: score_pair(fa[p.a], fb[p.b], p.a, p.b, cc.ratio, cc.ransac_px, seed), head)
    return rank_pairs(rescored) + ranked[cfg.pair_rescore:]


def sift_pair_matches(ctx: MatchContext, ref: int, pairs: list[PairScore], H: NDArray | None = None) -> FineMatches:
    """SIFT of each view pair matched view against view (ratio test, or guided under `H`, the
    homography original reference -> original target), fused in original coordinates."""
    cfg, fc = ctx.cfg.escalation, ctx.cfg.fine
    det = fc.detector

    def one(p: PairScore) -> tuple[NDArray, NDArray, NDArray]:
        fa = view_features(ctx.store, ctx.names[ref], p.a, det, fc.interp, fc.antialias)
        fb = view_features(ctx.store, ctx.names[1 - ref], p.b, det, fc.interp, fc.antialias)
        if H is None:
            mm, d = ratio_match(fa.descriptors, fb.descriptors, cv2.NORM_L2, cfg.pair_ratio, ctx.cfg.seed)
        else:
            mm, d = guided_match(fa.kpts, fa.descriptors, fb.kpts, fb.descriptors, H, cfg.guided_px, cfg.guided_ratio)
        return fa.kpts[mm[:, 0]], fb.kpts[mm[:, 1]], d

    parts = ctx.map(one, pairs, min_items=2)
    ka = np.concatenate([p[0] for p in parts]).reshape(-1, 2).astype(np.float32)
    kb = np.concatenate([p[1] for p in parts]).reshape(-1, 2).astype(np.float32)
    d = np.concatenate([p[2] for p in parts]).astype(np.float32)
    idx = np.arange(len(ka), dtype=np.int32)
    mm, d = dedupe_by_location(ka, kb, np.stack([idx, idx], axis=1), d)
    return FineMatches(ka[mm[:, 0]], kb[mm[:, 1]], np.stack([np.arange(len(mm))] * 2, axis=1).astype(np.int32),
                       d, {f"{p.a.key}|{p.b.key}": p.inliers for p in pairs})


def verified_model(ctx: MatchContext, fine: FineMatches) -> tuple[int, NDArray | None]:
    """(verified matches, homography reference -> target or None) of fused matches; an implausible
    homography counts as 0 verified, and no homography is returned under a fundamental matrix."""
    pa, pb = fine.kpts_ref[fine.matches[:, 0]], fine.kpts_target[fine.matches[:, 1]]
    n, mask = ctx.verify(pa, pb)
    if n < 4 or ctx.cfg.verify_model != "homography":
        return n, None
    H, _ = ransac_homography(pa[mask], pb[mask], 3.0, seed=ctx.cfg.seed)
    return n, H


def view_pair_attempt(ctx: MatchContext, prev: Attempt) -> Attempt:
    """The `pairs` level (module doc), with `prev`'s reference simulated as the first view."""
    cfg = ctx.cfg.escalation
    ref = prev.reference
    best = score_view_pairs(ctx, ref)[:cfg.pair_top_k]
    fine = sift_pair_matches(ctx, ref, best)
    n_ver, H = verified_model(ctx, fine)
    if H is not None and ctx.cfg.guided:
        guided = sift_pair_matches(ctx, ref, best, H)
        n_g, _ = verified_model(ctx, guided)
        if n_g > n_ver:
            fine, n_ver = guided, n_g
    return Attempt(label="pairs", reference=ref, fine=fine, views=[], coarse=prev.coarse, verified=n_ver,
                   both_simulated=True)
