"""ExtraAffineMatcher: reference choice -> coarse ORB search -> fine SIFT stage -> escalation ->
finishing steps, as a short loop over the strategies of `matching.strategies`.

The fast path is the paper's: one reference, one simulated grid, one fine view. A pair whose
fast path ends with fewer than `escalation.min_inliers` verified matches escalates, cheapest
first (`matching.escalation`), so easy pairs keep the paper's speed and hard pairs still get
solved. `MatcherConfig` (`matching.config`) is re-exported here.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from .config import MatcherConfig
from .context import MatchContext
from .escalation import should_escalate
from .reference import ReferenceDecision, choose_reference, reason_for, settle_reference
from .store import FeatureStore
from .strategies import ESCALATION, FINISHING, escalate, fast_path
from .types import PairResult
from .viewfeatures import original_features
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
        with ctx.timed("reference"):
            decision = decide_reference(ctx)
        with ctx.timed("coarse"):
            ctx.reference = settle_reference(decision, ctx.coarse_for, ctx.size(0), cfg.reference,
                                             cfg.coarse.accept_inliers)
        with ctx.timed("fine"):
            best = fast_path(ctx)
        escalation = ""
        if should_escalate(cfg.escalation, best.verified, ctx.coarse_inliers()):
            with ctx.timed("escalation"):
                best = escalate(ctx, best, ESCALATION)
            escalation = best.label
        result = ctx.to_result(best, reason_for(decision, best.reference), decision.f0, decision.f1)
        result.escalation = escalation
        with ctx.timed("ransac"):
            for step in FINISHING:
                if step.applies(ctx, best, result):
                    result = step.run(ctx, best, result)
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
        return PairResult.empty(self.name, why, reference=result.reference,
                                reference_reason=result.reference_reason, f0=result.f0, f1=result.f1,
                                best_views=result.best_views, coarse_scores=result.coarse_scores,
                                escalation=result.escalation, timings=result.timings, image_sizes=result.image_sizes)

    def close(self) -> None:
        if self._pool_obj is not None:
            self._pool_obj.shutdown(wait=False)
            self._pool_obj = None


def decide_reference(ctx: MatchContext) -> ReferenceDecision:
    """SIFT of both originals (cached in the store: the fine stage reuses them) and the reference
    decision they support (`reference.choose_reference`)."""
    sift = ctx.cfg.fine.detector
    feats = ctx.map(lambda n: original_features(ctx.store, n, sift), list(ctx.names))
    return choose_reference(feats[0], feats[1], ctx.cfg.reference, ctx.size(0), ctx.cfg.seed)
