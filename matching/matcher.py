"""ExtraAffineMatcher: reference choice -> coarse ORB search -> fine SIFT stage -> escalation ->
finishing steps, as a short loop over the strategies of `matching.strategies`.

The fast path is the paper's: one reference, one simulated grid, one fine view. A pair whose
fast path ends with fewer than `escalation.min_inliers` verified matches escalates, cheapest
first (`matching.escalation`), so easy pairs keep the paper's speed and hard pairs still get
solved. `MatcherConfig` (`matching.config`) is re-exported here.
"""

from __future__ import annotations

import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from .adaptive import PathPlan, estimate_viewpoint, nearest_views, plan_pair
from .config import MatcherConfig
from .context import Attempt, MatchContext
from .escalation import should_escalate
from .geometry import scale_1_from_0
from .matching_utils import FLANN_MIN_SIZE
from .reference import (
    ReferenceDecision,
    choose_reference,
    larger_image,
    reason_for,
    settle_reference,
)
from .store import FeatureStore
from .strategies import (
    ESCALATION,
    FINISHING,
    escalate,
    fast_path,
    one_surface_view,
    originals_attempt,
    targeted_attempt,
)
from .types import PairResult
from .viewfeatures import decision_features, original_features
from .views import view_grid

__all__ = ["ExtraAffineMatcher", "MatcherConfig"]


class ExtraAffineMatcher:
    """The extra-affine matcher. Thread-safe: state lives in the FeatureStore, the config and the
    per-pair `MatchContext`; the view thread pool is shared by the pairs."""

    name = "extra-affine"

    def __init__(self, cfg: MatcherConfig | None = None):
        self.cfg = cfg or MatcherConfig()
        self.views = view_grid(self.cfg.grid)
        self._threads = self.cfg.workers or os.cpu_count() or 1
        self._pool_obj: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()

    def _pool(self) -> ThreadPoolExecutor | None:
        """The view thread pool, created on first use (None with `workers` = 1)."""
        if self._threads <= 1:
            return None
        with self._pool_lock:
            if self._pool_obj is None:
                self._pool_obj = ThreadPoolExecutor(max_workers=self._threads, thread_name_prefix="views")
            return self._pool_obj

    def context(self, store: FeatureStore, name0: str, name1: str) -> MatchContext:
        """A fresh per-pair context on this matcher's views, pool and config."""
        return MatchContext(store, (name0, name1), self.cfg, self.views, self._pool(), self.name)

    def match(self, store: FeatureStore, name0: str, name1: str) -> PairResult:
        cfg = self.cfg
        t_start = time.perf_counter()
        ctx = self.context(store, name0, name1)
        if cfg.simulate:
            with ctx.timed("reference"):
                decision = decide_reference(ctx)
        else:  # nothing is simulated: no reference to decide (nor its SIFT at the views' contrast to compute)
            decision = ReferenceDecision(None, math.nan, math.nan, "originals only: no view simulated")
        path, path_reason, planned = "full", "adaptive off -> full grid", ""
        best: Attempt | None = None
        if not cfg.simulate:
            best, path, path_reason = originals_only(ctx, decision)
        else:
            # what the originals' evidence says, recorded whether or not the adaptive paths act on it
            ref, plan = plan_from_decision(ctx, decision)
            planned = plan.path
            if ref is not None:  # the originals the path reads at full resolution
                both = cfg.adaptive and plan.path == "originals"
                prefetch_originals(ctx, [ref, 1 - ref] if both else [1 - ref])
            if cfg.adaptive:
                best, path, path_reason = adaptive_paths(ctx, decision, ref, plan)
            else:
                path_reason = f"adaptive off -> full grid (the originals' evidence: {plan.reason})"
        if best is None:
            with ctx.timed("coarse"):
                ctx.reference = settle_reference(decision, ctx.coarse_for, ctx.size(0), cfg.reference,
                                                 cfg.coarse.accept_inliers,
                                                 ctx.coarse_near if cfg.coarse.settle_targeted else None)
            if decision.reference is None:  # settled only now: its target's detection starts beside the first views'
                prefetch_originals(ctx, [1 - ctx.reference])
            with ctx.timed("fine"):
                best = max_verified(ctx.fallen_through, fast_path(ctx))
        if cfg.simulate and cfg.planar.enabled:
            with ctx.timed("planar"):
                best, planar_reason = one_surface_view(ctx, best)
            if planar_reason:
                path_reason = f"{path_reason}; {planar_reason}"
        escalation = ""
        if cfg.simulate and should_escalate(cfg.escalation, best.verified, ctx.coarse_inliers()):
            with ctx.timed("escalation"):
                best = escalate(ctx, best, ESCALATION)
            escalation = best.label
        result = ctx.to_result(best, reason_for(decision, best.reference),
                               *((decision.f0, decision.f1) if cfg.simulate else (None, None)))
        result.escalation = escalation
        result.verified = best.verified
        if not cfg.simulate:
            result.reference = None  # neither image was simulated
        with ctx.timed("ransac"):
            for step in FINISHING:
                if step.applies(ctx, best, result):
                    result = step.run(ctx, best, result)
        result.path, result.path_reason, result.planned_path = path, path_reason, planned
        result.finishing = "; ".join(ctx.notes)
        ctx.timings["total"] = time.perf_counter() - t_start
        result.timings = ctx.timings
        return self.enough_or_empty(result)

    def enough_or_empty(self, result: PairResult) -> PairResult:
        """`result`, or an empty result with the reason when it has fewer than
        `min_result_inliers` verified matches (diagnostics kept)."""
        n_min = self.cfg.min_result_inliers
        if result.num_inliers >= n_min:
            return result
        why = result.reason or (f"only {result.num_inliers} verified matches (< {n_min}): "
                                "the images probably do not overlap")
        return result.without_matches(why)

    def close(self) -> None:
        if self._pool_obj is not None:
            self._pool_obj.shutdown(wait=False)
            self._pool_obj = None


def decide_reference(ctx: MatchContext) -> ReferenceDecision:
    """SIFT of both originals at `ReferenceConfig.decision_scale` (cached in the store; at 1 the
    fine stage reuses them) and the reference decision they support
    (`reference.choose_reference`)."""
    sift = ctx.cfg.fine.detector
    scale = ctx.cfg.reference.decision_scale
    feats = ctx.map(lambda n: decision_features(ctx.store, n, sift, scale), list(ctx.names))
    return choose_reference(feats[0], feats[1], ctx.cfg.reference, ctx.size(0), ctx.cfg.seed)


def prefetch_originals(ctx: MatchContext, sides: list[int]) -> None:
    """Start the full-resolution SIFT of the originals on `sides` on the view pool, so it runs
    while the coarse search scores its views (the fine stage then finds it in the store, or waits
    for it there); nothing without a pool or where the decision already read them."""
    if ctx.pool is None or ctx.cfg.reference.decision_scale >= 1.0:
        return
    sift, seed = ctx.cfg.fine.detector, ctx.cfg.seed

    def detect_and_index(name: str) -> None:
        f = original_features(ctx.store, name, sift)
        if len(f) >= FLANN_MIN_SIZE:  # the k-d forest every view's ratio test searches
            f.forest(seed)

    for side in sides:
        ctx.pool.submit(detect_and_index, ctx.names[side])


def max_verified(a: Attempt | None, b: Attempt) -> Attempt:
    """The attempt with more verified matches (`a` on ties), `b` when there is no `a`."""
    return b if a is None or b.verified > a.verified else a


def originals_only(ctx: MatchContext, decision: ReferenceDecision) -> tuple[Attempt, str, str]:
    """`simulate=False` (the first pass of a scene's `simulate = "needed"` schedule): the
    originals matched with each other, nothing simulated, only the matches the verification
    accepted kept (COLMAP then verifies nearly clean matches in a few RANSAC trials instead of up
    to 20000 per model: on castle_P30 verification took 75 of the run's 210 s with the raw ones):
    (the attempt, "originals" when it verifies `escalation.min_inliers` matches, else
    "deferred", why). The identity view is symmetric: image 0 is matched as the reference
    unless a decision was made, and the result names no reference."""
    ref = 0 if decision.reference is None else decision.reference
    ctx.reference = ref
    with ctx.timed("originals"):
        att = originals_attempt(ctx, ref, verified_only=True)
    enough = ctx.cfg.escalation.min_inliers
    if att.verified >= enough:
        return att, "originals", f"originals only: {att.verified} verified matches"
    return att, "deferred", (f"originals only: {att.verified} verified matches (< {enough}); "
                             "view simulation left to the scene's second pass")


def plan_from_decision(ctx: MatchContext, decision: ReferenceDecision) -> tuple[int | None, PathPlan]:
    """(the image the evidence would simulate or None, the cheapest path the originals' evidence
    supports, `adaptive.plan_pair`). An undecided reference with enough inliers for a targeted try
    takes the larger image by the originals' homography (its scale decides)."""
    cfg = ctx.cfg
    estimate = None
    ref = decision.reference
    if (ref is None and decision.H_1_from_0 is not None and decision.inliers0 is not None
            and decision.inliers >= cfg.paths.targeted_min_inliers):
        scale = scale_1_from_0(decision.H_1_from_0, ctx.size(0))
        larger = larger_image(scale, cfg.reference.scale_tolerance) if math.isfinite(scale) else None
        ref = 0 if larger is None else larger
    if ref is not None and decision.H_1_from_0 is not None and decision.inliers0 is not None:
        estimate = estimate_viewpoint(decision.H_1_from_0, decision.inliers0, ref, ctx.size(ref))
    return ref, plan_pair(estimate, cfg.paths, decision.reason if ref is None else "")


def adaptive_paths(ctx: MatchContext, decision: ReferenceDecision, ref: int | None,
                   plan: PathPlan) -> tuple[Attempt | None, str, str]:
    """The adaptive paths (`matching.adaptive`), cheapest first, from `plan_from_decision`'s
    (`ref`, `plan`): (the accepted attempt or None when the full path must run, the path taken,
    why). An attempt that verifies fewer than `escalation.min_inliers` matches falls through to
    the next path; the best one so far is kept on `ctx.fallen_through` so the full path only
    replaces it when it does better."""
    cfg = ctx.cfg
    enough = cfg.escalation.min_inliers
    reason = plan.reason
    if plan.path == "originals" and ref is not None:
        ctx.reference = ref
        with ctx.timed("originals"):
            att = ctx.fallen_through = originals_attempt(ctx, ref)
        if att.verified >= enough:
            return att, "originals", reason
        reason += f"; originals verified {att.verified} (< {enough})"
    e = plan.estimate
    if (ref is not None and e is not None and plan.path != "full"
            and math.isfinite(e.tilt) and e.tilt <= cfg.paths.targeted_max_tilt):
        ctx.reference = ref
        views = nearest_views(ctx.views, e.tilt, e.phi, cfg.paths.targeted_views)
        with ctx.timed("targeted"):
            att = targeted_attempt(ctx, ref, views)
        ctx.fallen_through = max_verified(ctx.fallen_through, att)
        if att.verified >= enough:
            if decision.reference is None:
                decision.reference = ref
                decision.reason += f"; the originals' homography makes image {ref} the reference"
            return att, "targeted", (reason if plan.path == "targeted" else reason + " -> views near it")
        reason += f"; targeted views verified {att.verified} (< {enough})"
    if plan.path != "full":
        reason += " -> full grid"
    return None, "full", reason
