"""Second matching rounds under the first round's geometry: a homography (planar pairs) or a
fundamental matrix (multi-view).

The first round's ratio test compares each keypoint with every target keypoint, so a true match
loses to a similar pattern elsewhere in the image. Once a verified model says where (H) or on
which line (F) a keypoint's match must lie, the fine views' keypoints are re-matched only against
the target keypoints there (`fine.guided_match`, `fine.epipolar_guided_match`): more matches at
equal precision. Each round keeps the first round's result when it does not improve on it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from .context import Attempt, MatchContext
from .features import Features
from .fine import (
    FineMatches,
    TargetFeatures,
    epipolar_guided_match,
    epipolar_pair_distance,
    guided_match,
    target_features,
)
from .matching_utils import polish_fundamental, ransac_homography, unique_train
from .refine import neighbour_transfer_residuals
from .types import PairResult, ViewParams
from .viewfeatures import view_features
from .views import capped_view

MatchFn = Callable[[Features, Features], tuple[NDArray[np.int32], NDArray[np.float32]]]


def rematch_views(ctx: MatchContext, ref: int, views: list[ViewParams], match_fn: MatchFn,
                  tf: TargetFeatures, first: FineMatches | None = None) -> tuple[NDArray, NDArray, NDArray]:
    """(reference keypoints, (K, 2) matches into them and into `tf.kpts`, distances) of every
    fine view of image `ref` re-matched by `match_fn(view features, target features of the same
    detector) -> (matches, distances)`, after `first`'s matches when given."""
    fc = ctx.cfg.fine
    name = ctx.names[ref]
    size = ctx.size(ref)
    kpts_ref: list[NDArray] = []
    pairs: list[NDArray] = []
    dists: list[NDArray] = []
    offset = 0
    if first is not None:
        kpts_ref, pairs, dists, offset = [first.kpts_ref], [first.matches], [first.distances], len(first.kpts_ref)
    for view in views:
        rendered = capped_view(view, size, fc.max_area_ratio)
        det = fc.detector_for(view)
        fv = view_features(ctx.store, name, rendered, det, fc.interp, fc.antialias)
        ft, t_offset = tf.part(det)
        m, d = match_fn(fv, ft)
        kpts_ref.append(fv.kpts[m[:, 0]])
        pairs.append(np.stack([np.arange(len(m)) + offset, m[:, 1] + t_offset], axis=1))
        dists.append(d)
        offset += len(m)
    kr = np.concatenate(kpts_ref) if kpts_ref else np.zeros((0, 2), np.float32)
    m_all = np.concatenate(pairs).astype(np.int32) if pairs else np.zeros((0, 2), np.int32)
    d_all = np.concatenate(dists).astype(np.float32) if dists else np.zeros(0, np.float32)
    return kr, m_all, d_all


def compact(kr: NDArray, kpts_target: NDArray, m_all: NDArray[np.int32], d_all: NDArray[np.float32]) -> FineMatches:
    """FineMatches keeping only the reference keypoints that some match uses (re-indexed)."""
    used = np.unique(m_all[:, 0])
    remap = np.full(len(kr), -1, np.int64)
    remap[used] = np.arange(len(used))
    matches = np.stack([remap[m_all[:, 0]], m_all[:, 1]], 1).astype(np.int32)
    return FineMatches(kr[used], kpts_target, matches, d_all, {})


def guided_homography_round(ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
    """Re-match `att`'s fine views under the fitted homography `res.H_1_from_0` (within
    `guided_px`, ratio `guided_ratio`), then refit the final homography on the guided matches;
    `res` is kept when the refit has fewer inliers."""
    cfg = ctx.cfg
    ref = att.reference
    assert res.H_1_from_0 is not None
    H_t_from_ref = res.H_1_from_0 if ref == 0 else np.asarray(np.linalg.inv(res.H_1_from_0), np.float64)
    tf = target_features(ctx.store, ctx.names[1 - ref], cfg.fine)
    kr, m_all, d_all = rematch_views(
        ctx, ref, att.views,
        lambda fv, ft: guided_match(fv.kpts, fv.descriptors, ft.kpts, ft.descriptors, H_t_from_ref,
                                    cfg.guided_px, cfg.guided_ratio), tf)
    if len(m_all) == 0:
        ctx.notes.append("guided round under H: no match in the band")
        return res
    m_all, d_all = unique_train(m_all, d_all)
    guided = Attempt("guided", ref, compact(kr, tf.kpts, m_all, d_all), att.views, att.coarse, 0)
    out = ctx.to_result(guided, res.reference_reason, res.f0, res.f1)
    out.escalation = res.escalation
    p0, p1 = out.matched_points(inliers_only=False)
    H, inl = ransac_homography(p0, p1, cfg.final_ransac_px, seed=cfg.seed)
    if H is None or inl.sum() < res.num_inliers:
        ctx.notes.append(f"guided round under H kept out: its refit has {0 if H is None else int(inl.sum())} inliers, "
                         f"the first round {res.num_inliers}")
        return res
    out.H_1_from_0, out.inlier_mask = H, inl
    ctx.notes.append(f"guided round under H: {res.num_inliers} -> {int(inl.sum())} inliers")
    return out


def trusted_fundamental(ctx: MatchContext, fm: FineMatches) -> NDArray[np.float64] | None:
    """F (reference -> target) of the first round's matches, or None when it is not trustworthy:
    fewer than `guided_epipolar_min_inliers` inliers, or under `guided_epipolar_min_ratio` of the
    matches. Around a wrong F the band collects chance matches that are consistent with it, so
    COLMAP would verify them (docs/decisions.md). Either way the count goes to `ctx.notes`."""
    cfg = ctx.cfg
    p_ref, p_t = fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]]
    cv2.setRNGSeed(cfg.seed)
    F, mask = cv2.findFundamentalMat(p_ref.astype(np.float32), p_t.astype(np.float32), cv2.FM_RANSAC,
                                     cfg.guided_epipolar_px, 0.999, 10000)
    if F is None or F.shape != (3, 3) or mask is None:
        ctx.notes.append(f"epipolar round skipped: no F fits the {len(p_ref)} first-round matches")
        return None
    inl = mask.ravel().astype(bool)
    if inl.sum() < cfg.guided_epipolar_min_inliers or inl.sum() < cfg.guided_epipolar_min_ratio * len(inl):
        ctx.notes.append(f"epipolar round skipped: F holds {int(inl.sum())} of the {len(inl)} first-round matches "
                         f"(needs >= {cfg.guided_epipolar_min_inliers} and >= {cfg.guided_epipolar_min_ratio:.0%})")
        return None
    if cfg.guided_epipolar_polish:
        F, _ = polish_fundamental(p_ref, p_t, F, cfg.guided_epipolar_px)
    return cast(NDArray[np.float64], F)


def off_their_neighbours(ctx: MatchContext, kr: NDArray, kt: NDArray, m_all: NDArray, support: NDArray[np.bool_],
                         new: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(len(m_all),) True for the `new` matches whose target point lies more than
    `guided_epipolar_neighbour_px` from where the local affine of their 12 nearest `support`
    matches puts them (`refine.neighbour_transfer_residuals`; kept where no fit exists); the
    count goes to `ctx.notes`."""
    off = np.zeros(len(m_all), bool)
    idx = np.flatnonzero(new)
    if len(idx) == 0:
        return off
    res = neighbour_transfer_residuals(kr[m_all[support, 0]], kt[m_all[support, 1]], kr[m_all[idx, 0]],
                                       kt[m_all[idx, 1]], k=12)
    off[idx] = res > ctx.cfg.guided_epipolar_neighbour_px  # NaN (no fit) compares False: kept
    ctx.notes.append(f"neighbour check dropped {int(off.sum())} of the round's {len(idx)} new F-consistent matches")
    return off


def guided_epipolar_round(ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
    """Re-match `att`'s fine views within `guided_epipolar_px` of the epipolar lines of a
    fundamental matrix fitted to its matches (`trusted_fundamental`), ratio
    `guided_epipolar_ratio`; returns the F-consistent union of both rounds when it has more
    matches than `res`, else `res`."""
    cfg = ctx.cfg
    ref = att.reference
    fm = att.fine
    F = trusted_fundamental(ctx, fm)
    if F is None:
        return res
    tf = target_features(ctx.store, ctx.names[1 - ref], cfg.fine)
    kr, m_all, d_all = rematch_views(
        ctx, ref, att.views,
        lambda fv, ft: epipolar_guided_match(fv.kpts, fv.descriptors, ft.kpts, ft.descriptors, F,
                                             cfg.guided_epipolar_px, cfg.guided_epipolar_ratio),
        tf, first=fm)
    # third column: the match comes from the first round (rematch_views puts those first)
    m_all = np.c_[m_all, np.arange(len(m_all)) < len(fm.matches)].astype(np.int32)
    # one match per reference position and per target keypoint (first round wins ties: it comes first)
    key = np.c_[np.round(kr[m_all[:, 0]] * 4).astype(np.int64), m_all[:, 1].astype(np.int64)]
    _, first = np.unique(key, axis=0, return_index=True)
    m_all, d_all = m_all[np.sort(first)], d_all[np.sort(first)]
    m_all, d_all = unique_train(m_all, d_all)
    from_first, m_all = m_all[:, 2].astype(bool), m_all[:, :2]
    keep = epipolar_pair_distance(F, kr[m_all[:, 0]], tf.kpts[m_all[:, 1]]) <= cfg.guided_epipolar_px
    if cfg.guided_epipolar_neighbour_px > 0:
        keep &= ~off_their_neighbours(ctx, kr, tf.kpts, m_all, keep & from_first, keep & ~from_first)
    fm2 = compact(kr, tf.kpts, m_all[keep], d_all[keep])
    if len(fm2.matches) <= res.num_matches:
        added = keep & ~from_first
        if not (cfg.guided_epipolar_add and added.any()):
            ctx.notes.append(f"epipolar round kept out: {len(fm2.matches)} F-consistent matches, the first round "
                             f"{res.num_matches}")
            return res
        keep |= from_first
        fm2 = compact(kr, tf.kpts, m_all[keep], d_all[keep])
        ctx.notes.append(f"epipolar round added {int(added.sum())} F-consistent matches to the first round's "
                         f"{int(from_first.sum())}: {res.num_matches} -> {len(fm2.matches)} matches")
    else:
        ctx.notes.append(f"epipolar round: {res.num_matches} -> {len(fm2.matches)} matches")
    out = ctx.to_result(Attempt("guided", ref, fm2, att.views, att.coarse, 0), res.reference_reason, res.f0, res.f1)
    out.escalation = res.escalation
    return out
