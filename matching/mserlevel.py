"""The `mser` escalation level: affine-covariant MSER regions of both images, detected in a few
simulated views of each (MODS' MSER step), pooled with the best attempt so far and verified with
the local-affine-frame check (`matching.mser`).

Where the SIFT levels find too little to verify (the best attempt under
`EscalationConfig.min_inliers`), regions normalised by their own shape add matches that no SIFT
view produces: on EVD grand, which has no SIFT or ORB signal at any simulated view, they find
the homography. Each image's regions are detected once per view (`MserConfig.grid`, cached in
the feature store like SIFT's), mapped back to original pixels with their frames
(F_orig = inv(A_view_from_orig) @ F_view), and matched with FGINN (nested regions and the same
region seen in several views share a centre). The pooled matches are fitted with a RANSAC
homography (3 px); an MSER match inside that model whose frames disagree with its local affine
map (`mser.laf_consistent`) is dropped, the rest verified as every level is (`ctx.verify`).
"""

from __future__ import annotations

import numpy as np

from .context import Attempt, MatchContext
from .features import Features
from .fine import FineMatches
from .matching_utils import dedupe_by_location, ransac_homography
from .mser import MserConfig, detect_mser_affine, laf_consistent, mser_key
from .twosided import fginn_match
from .types import ViewParams
from .views import invert_affine, map_to_original, simulate, view_grid


def mser_view_features(ctx: MatchContext, side: int, view: ViewParams, cfg: MserConfig) -> Features:
    """Image `side`'s MSER features in one simulated view (linear warp, anti-aliased), keypoints
    and frames in original pixels; computed once per image and view."""
    name = ctx.names[side]

    def compute() -> Features:
        img = ctx.store.image(name)
        sv = simulate(img, view, "linear", True)
        f = detect_mser_affine(sv.image, cfg)
        kpts, inside = map_to_original(f.kpts, sv.A_view_from_orig, (img.shape[1], img.shape[0]))
        assert f.frames is not None
        frames = invert_affine(sv.A_view_from_orig)[:, :2] @ f.frames
        out = Features(kpts, f.sizes, f.angles, f.descriptors, frames=frames)
        return out.subset(inside)

    return ctx.store.get_or_compute(name, f"{mser_key(cfg)}@{view.key}", compute)


def pooled_mser(ctx: MatchContext, side: int, cfg: MserConfig) -> Features:
    """All of `cfg.grid`'s views' MSER features of image `side`, in original pixels."""
    views = view_grid(cfg.grid)
    parts = (list(ctx.pool.map(lambda v: mser_view_features(ctx, side, v, cfg), views)) if ctx.pool is not None
             else [mser_view_features(ctx, side, v, cfg) for v in views])
    return Features.concat(parts)


def pooled_with(best: FineMatches, kpts_ref: np.ndarray, kpts_target: np.ndarray, distances: np.ndarray
                ) -> FineMatches:
    """`best`'s matches followed by the matches kpts_ref[i] <-> kpts_target[i] (new keypoints)."""
    n_ref, n_t, n = len(best.kpts_ref), len(best.kpts_target), len(kpts_ref)
    extra = np.stack([np.arange(n) + n_ref, np.arange(n) + n_t], 1)
    return FineMatches(np.concatenate([best.kpts_ref, kpts_ref]).astype(np.float32),
                       np.concatenate([best.kpts_target, kpts_target]).astype(np.float32),
                       np.concatenate([best.matches.astype(np.int64), extra]).astype(np.int32),
                       np.concatenate([best.distances, distances]).astype(np.float32),
                       {**best.per_view, "mser": n})


def earlier_verified(ctx: MatchContext, best: Attempt) -> FineMatches:
    """`best`'s matches followed by the verified matches of every other attempt of the escalation
    (`ctx.attempts`), turned to `best`'s reference side and without those repeating a pooled
    match within 1.5 px in both images (`MserConfig.pool` = "verified")."""
    ref_pts, tgt_pts, dist = [], [], []
    for att in ctx.attempts:
        if att is best or len(att.fine.matches) == 0:
            continue
        fm = att.fine
        p_ref, p_t = fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]]
        mask = att.verified_mask if att.verified_mask is not None else ctx.verify(p_ref, p_t)[1]
        if att.reference != best.reference:
            p_ref, p_t = p_t, p_ref
        ref_pts.append(p_ref[mask])
        tgt_pts.append(p_t[mask])
        dist.append(fm.distances[mask])
    if not ref_pts:
        return best.fine
    base = best.fine
    a = np.concatenate([base.kpts_ref[base.matches[:, 0]], *ref_pts]).astype(np.float32)
    b = np.concatenate([base.kpts_target[base.matches[:, 1]], *tgt_pts]).astype(np.float32)
    d = np.concatenate([base.distances, *dist]).astype(np.float32)
    n = len(base.matches)
    idx = np.stack([np.arange(len(a)), np.arange(len(a))], 1).astype(np.int32)
    # one cell of `dedupe_by_location` keeps its closest descriptor; ranking `best`'s own matches
    # first drops every added match that repeats one of them, and the added ones among themselves
    rank = np.concatenate([np.full(n, -1.0, np.float32), d[n:]])
    keep, _ = dedupe_by_location(a, b, idx, rank)
    added = keep[keep[:, 0] >= n, 0]
    pooled = pooled_with(base, a[added], b[added], d[added])
    pooled.per_view = {**base.per_view, "earlier_verified": len(added)}
    return pooled


def mser_attempt(ctx: MatchContext, best: Attempt, cfg: MserConfig) -> Attempt:
    """The `mser` level (module doc): `best`'s reference side stays the query side."""
    ref = best.reference
    fa, fb = pooled_mser(ctx, ref, cfg), pooled_mser(ctx, 1 - ref, cfg)
    mm, d = fginn_match(fa, fb, cfg.ratio, cfg.fginn_px, 8, ctx.cfg.seed)
    mm, d = dedupe_by_location(fa.kpts, fb.kpts, mm, d)
    base = earlier_verified(ctx, best) if cfg.pool == "verified" else best.fine
    pool = pooled_with(base, fa.kpts[mm[:, 0]], fb.kpts[mm[:, 1]], d)
    p_ref, p_t = pool.kpts_ref[pool.matches[:, 0]], pool.kpts_target[pool.matches[:, 1]]
    dropped = 0
    if len(mm) and len(p_ref) >= 4 and fa.frames is not None and fb.frames is not None:
        H, inl = ransac_homography(p_ref, p_t, 3.0, seed=ctx.cfg.seed)
        if H is not None:
            first = len(base.matches)
            ok = laf_consistent(H, fa.kpts[mm[:, 0]], fa.frames[mm[:, 0]], fb.frames[mm[:, 1]], cfg)
            drop = np.zeros(len(pool.matches), bool)
            drop[first:] = inl[first:] & ~ok
            dropped = int(drop.sum())
            pool = FineMatches(pool.kpts_ref, pool.kpts_target, pool.matches[~drop], pool.distances[~drop],
                               pool.per_view)
            p_ref, p_t = pool.kpts_ref[pool.matches[:, 0]], pool.kpts_target[pool.matches[:, 1]]
    pool.per_view["mser_laf_dropped"] = dropped
    n_ver = ctx.verify(p_ref, p_t)[0] if len(pool.matches) else 0
    return Attempt(label="mser", reference=ref, fine=pool, views=best.views, coarse=best.coarse, verified=n_ver,
                   both_simulated=best.both_simulated)
