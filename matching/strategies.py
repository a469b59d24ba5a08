"""The matcher's strategies, in the order the matcher runs them.

Attempts are ways of matching the pair, each returning an `Attempt` with its verified-match
count: the paper's `fast_path` first, then the `ESCALATION` levels, cheapest first (see
`matching.escalation`): `topk`, `swap`, `pairs` (`matching.viewpairs`), `steep` (`matching.steep`),
`mser` (`matching.mserlevel`), `two-sided`
(`matching.twosided`). A level runs only while the best attempt so far is not verified well
enough, and the attempt with the most verified matches wins.

`FINISHING` are steps on the winning attempt's result, in order: the final homography, the
guided round under H, the guided round under F (`matching.guided`), and the reference read off
the final homography when both images were simulated (`matching.reference`).

Each strategy is a small object with one job: `applies(...)` says whether the config and the
state so far call for it, `run(...)` does it.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np

from .coarse import coarse_search, rank_views
from .context import Attempt, MatchContext
from .fine import fine_match, select_fine_views
from .guided import guided_epipolar_round, guided_homography_round
from .matching_utils import polish_homography, ransac_homography
from .mserlevel import mser_attempt
from .planar import distinct_view, one_surface
from .reference import reference_from_final_homography
from .refine import refine_matches
from .steep import steep_attempt
from .twosided import two_sided_attempt
from .types import PairResult, ViewParams
from .viewpairs import view_pair_attempt


def fine_attempt(ctx: MatchContext, ref: int, top_k: int, label: str) -> Attempt:
    """Image `ref` simulated: the fine stage on its `top_k` best coarse views (plus the original
    with `fine_include_original`), and how many of the fused matches verify."""
    cfg = ctx.cfg
    scores = ctx.coarse_for(ref)
    views = select_fine_views(rank_views(scores), top_k, cfg.fine_include_original, cfg.fine_min_view_distance)
    fm = fine_match(ctx.store, ctx.names[ref], ctx.names[1 - ref], views, cfg.fine, ctx.pool, cfg.seed)
    n_verified, mask = ctx.verify(fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]])
    return Attempt(label=label, reference=ref, fine=fm, views=views, coarse=scores, verified=n_verified,
                   verified_mask=mask)


def originals_attempt(ctx: MatchContext, ref: int, verified_only: bool = False) -> Attempt:
    """The adaptive `originals` path (`matching.adaptive`): the unwarped originals' SIFT, image
    `ref` as the reference, no coarse search and no simulated view; with `verified_only` the
    attempt keeps only the matches its verification accepted."""
    cfg = ctx.cfg
    views = [ViewParams(1.0, 0.0, 1.0)]
    fm = fine_match(ctx.store, ctx.names[ref], ctx.names[1 - ref], views, cfg.fine, ctx.pool, cfg.seed)
    n_verified, mask = ctx.verify(fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]])
    if verified_only and len(mask) == len(fm.matches):
        fm = dataclasses.replace(fm, matches=fm.matches[mask], distances=fm.distances[mask])
    return Attempt(label="", reference=ref, fine=fm, views=views, coarse=[], verified=n_verified)


def targeted_attempt(ctx: MatchContext, ref: int, views: list[ViewParams]) -> Attempt:
    """The adaptive `targeted` path: the coarse search on only `views` (the grid views near the
    estimated tilt, `adaptive.nearest_views`), the fine stage on the best `fine_top_k` of them."""
    cfg = ctx.cfg
    scores = coarse_search(ctx.store, ctx.names[ref], ctx.names[1 - ref], views, cfg.coarse, ctx.pool, cfg.seed)
    ctx.targeted_coarse_inliers = max((c.inliers for c in scores), default=0)
    fine_views = select_fine_views(rank_views(scores), cfg.fine_top_k, cfg.fine_include_original,
                                   cfg.fine_min_view_distance)
    fm = fine_match(ctx.store, ctx.names[ref], ctx.names[1 - ref], fine_views, cfg.fine, ctx.pool, cfg.seed)
    n_verified, _ = ctx.verify(fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]])
    return Attempt(label="", reference=ref, fine=fm, views=fine_views, coarse=scores, verified=n_verified)


def one_surface_view(ctx: MatchContext, att: Attempt) -> tuple[Attempt, str]:
    """`matching.planar`: when one homography explains the attempt's epipolar-verified matches
    and the coarse search found a distinct view that overlaps, the attempt again with that view
    fused too, if it verifies more; else `att`. Also the decision in words ("" = not one surface)."""
    cfg = ctx.cfg
    fm = att.fine
    if not cfg.planar.enabled or cfg.verify_model != "fundamental" or not att.coarse or len(fm.matches) < 15:
        return att, ""
    flat, why = one_surface(fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]], cfg.planar, cfg.seed,
                            att.verified_mask)
    if not flat:
        return att, ""
    extra = distinct_view(att.coarse, att.views, cfg.planar)
    if extra is None:
        return att, f"one surface ({why}), no distinct view overlaps"
    views = [*att.views, extra]
    fm2 = fine_match(ctx.store, ctx.names[att.reference], ctx.names[1 - att.reference], views, cfg.fine, ctx.pool,
                     cfg.seed)
    n_verified, mask = ctx.verify(fm2.kpts_ref[fm2.matches[:, 0]], fm2.kpts_target[fm2.matches[:, 1]])
    label = f"one surface ({why}) -> + view (t {extra.t:.2f}, phi {extra.phi:.1f}°)"
    if n_verified <= att.verified:
        return att, f"{label}: {n_verified} verified, not more; kept {att.verified}"
    more = dataclasses.replace(att, fine=fm2, views=views, verified=n_verified, verified_mask=mask)
    return more, f"{label}: {att.verified} -> {n_verified} verified"


def fast_path(ctx: MatchContext) -> Attempt:
    """The paper's path: the reference the coarse stage settled (`ctx.reference`), its
    `fine_top_k` best views."""
    return fine_attempt(ctx, ctx.reference, ctx.cfg.fine_top_k, "")


class Level(Protocol):
    """An escalation level: another way of matching the pair, given the best attempt so far."""

    label: str

    def applies(self, ctx: MatchContext, best: Attempt) -> bool: ...

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt: ...


class TopK:
    """Fuse more of the same side's best views (several surfaces or poses)."""

    label = "topk"

    def applies(self, ctx: MatchContext, best: Attempt) -> bool:
        return ctx.cfg.escalation.top_k > ctx.cfg.fine_top_k

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt:
        return fine_attempt(ctx, best.reference, ctx.cfg.escalation.top_k, self.label)


class Swap:
    """Simulate the other image (the reference choice was wrong)."""

    label = "swap"

    def applies(self, ctx: MatchContext, best: Attempt) -> bool:
        return ctx.cfg.escalation.swap

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt:
        return fine_attempt(ctx, 1 - best.reference, max(ctx.cfg.escalation.top_k, 1), self.label)


class Mser:
    """Affine-normalised MSER regions pooled with the best attempt (`matching.mserlevel`)."""

    label = "mser"

    def applies(self, ctx: MatchContext, best: Attempt) -> bool:
        return ctx.cfg.escalation.mser.enabled

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt:
        return mser_attempt(ctx, best, ctx.cfg.escalation.mser)


class ViewPairs:
    """Two-sided, view pair by view pair (`matching.viewpairs`)."""

    label = "pairs"

    def applies(self, ctx: MatchContext, best: Attempt) -> bool:
        return ctx.cfg.escalation.pairs

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt:
        return view_pair_attempt(ctx, best)


class Steep:
    """One image tilted past the grid, t = 8 .. 22.6 (`matching.steep`)."""

    label = "steep"

    def applies(self, ctx: MatchContext, best: Attempt) -> bool:
        return ctx.cfg.escalation.steep.enabled

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt:
        return steep_attempt(ctx, best, ctx.cfg.escalation.steep, self.label)


class TwoSided:
    """Both images simulated and pooled (`matching.twosided`)."""

    label = "two-sided"

    def applies(self, ctx: MatchContext, best: Attempt) -> bool:
        return ctx.cfg.escalation.two_sided

    def run(self, ctx: MatchContext, best: Attempt) -> Attempt:
        return two_sided_attempt(ctx, best)


ESCALATION: tuple[Level, ...] = (TopK(), Swap(), ViewPairs(), Steep(), Mser(), TwoSided())
"""The escalation levels, cheapest first; `fast_path` precedes them."""


def escalate(ctx: MatchContext, best: Attempt, levels: tuple[Level, ...] = ESCALATION) -> Attempt:
    """Run `levels` in order while the best attempt has fewer than `escalation.min_inliers`
    verified matches; the attempt with the most verified matches wins (the earlier on ties).
    Each level that runs records its wall seconds as `timings["level:<label>"]`."""
    ctx.attempts.append(best)
    for level in levels:
        if best.verified >= ctx.cfg.escalation.min_inliers:
            break
        if level.applies(ctx, best):
            with ctx.timed(f"level:{level.label}"):
                att = level.run(ctx, best)
            ctx.attempts.append(att)
            best = max(best, att, key=lambda a: a.verified)
    return best


# --- finishing steps on the winning attempt's result ---------------------------------------------
class Finishing(Protocol):
    """A step on the result of the winning attempt `att`."""

    def applies(self, ctx: MatchContext, att: Attempt, res: PairResult) -> bool: ...

    def run(self, ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult: ...


class FinalHomography:
    """RANSAC homography on the final matches (`final_ransac_px`), inliers flagged."""

    def applies(self, ctx: MatchContext, att: Attempt, res: PairResult) -> bool:
        return ctx.cfg.final_homography and res.num_matches >= 4

    def run(self, ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
        p0, p1 = res.matched_points(inliers_only=False)
        res.H_1_from_0, res.inlier_mask = ransac_homography(p0, p1, ctx.cfg.final_ransac_px, seed=ctx.cfg.seed)
        if res.H_1_from_0 is None:
            res.reason = "no homography fits the matches"
        return res


class GuidedHomography:
    """The guided round under the final homography (`guided.guided_homography_round`)."""

    def applies(self, ctx: MatchContext, att: Attempt, res: PairResult) -> bool:
        return ctx.cfg.guided and res.H_1_from_0 is not None and bool(att.views)

    def run(self, ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
        return guided_homography_round(ctx, att, res)


class GuidedEpipolar:
    """The guided round under a fundamental matrix, without a final homography
    (`guided.guided_epipolar_round`)."""

    def applies(self, ctx: MatchContext, att: Attempt, res: PairResult) -> bool:
        cfg = ctx.cfg
        return cfg.guided_epipolar and not cfg.final_homography and bool(att.views) and res.num_matches >= 15

    def run(self, ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
        return guided_epipolar_round(ctx, att, res)


class RefinePoints:
    """Least-squares patch refinement of the final matches (`matching.refine`): each match's
    simulated-side keypoint is re-localised against the other image's under the local affine
    geometry, then the final homography is re-fitted to the refined points (RANSAC, then
    `polish_homography`: RANSAC's consensus set is its best sample's, and after refinement the
    polished model explains more of the points: on the 18 shared pairs 6239 -> 6320 correct
    matches, none fewer; docs/decisions.md, "Polished re-fit after refinement")."""

    def applies(self, ctx: MatchContext, att: Attempt, res: PairResult) -> bool:
        return ctx.cfg.refine.enabled and res.num_matches >= 4 and bool(att.views)

    def run(self, ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
        with ctx.timed("refine"):
            return refine_result(ctx, att, res)


def refine_result(ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
    """`res` with the simulated image's matched keypoints refined (`refine.refine_matches`);
    the other image's keypoints, detected in its unwarped original, stay where they are."""
    moving = att.reference  # image 0 or 1 of the pair, whichever this attempt simulated
    fixed = 1 - moving
    kpts = (res.kpts0, res.kpts1)
    img = (ctx.store.image(ctx.names[0]), ctx.store.image(ctx.names[1]))
    m = res.matches
    pts_m, pts_f = kpts[moving][m[:, moving]], kpts[fixed][m[:, fixed]]
    H_f_from_m = None if res.H_1_from_0 is None else np.asarray(
        res.H_1_from_0 if moving == 0 else np.linalg.inv(res.H_1_from_0), np.float64)
    refined, moved = refine_matches(img[moving], img[fixed], pts_m, pts_f, H_f_from_m, ctx.cfg.refine, ctx.pool)
    shift = np.linalg.norm(refined - pts_m, axis=1)[moved] if moved.any() else np.zeros(0)
    ctx.notes.append(f"refinement moved {int(moved.sum())} of {len(moved)} points"
                     + (f" (median {float(np.median(shift)):.2f} px)" if len(shift) else ""))
    # one keypoint per match on the moving side, so refined positions never collide across matches
    new_kpts = refined.astype(np.float32)
    new_idx = np.arange(len(m), dtype=np.int32)
    matches = m.copy()
    matches[:, moving] = new_idx
    if moving == 0:
        res.kpts0 = new_kpts
    else:
        res.kpts1 = new_kpts
    res.matches = matches
    if res.H_1_from_0 is not None:
        p0, p1 = res.matched_points(inliers_only=False)
        H, mask = ransac_homography(p0, p1, ctx.cfg.final_ransac_px, seed=ctx.cfg.seed)
        if H is not None:
            H, mask = polish_homography(p0, p1, H, ctx.cfg.final_ransac_px)
        if H is not None and mask.sum() >= res.num_inliers:
            res.H_1_from_0, res.inlier_mask = H, mask
    return res


class ReferenceFromFinalHomography:
    """Both images simulated: the verified final homography names the reference
    (`reference.reference_from_final_homography`)."""

    def applies(self, ctx: MatchContext, att: Attempt, res: PairResult) -> bool:
        return att.both_simulated and res.H_1_from_0 is not None

    def run(self, ctx: MatchContext, att: Attempt, res: PairResult) -> PairResult:
        return reference_from_final_homography(res, ctx.size(0), ctx.cfg.escalation.min_inliers)


FINISHING: tuple[Finishing, ...] = (FinalHomography(), GuidedHomography(), GuidedEpipolar(), RefinePoints(),
                                    ReferenceFromFinalHomography())
"""The finishing steps, in order."""
