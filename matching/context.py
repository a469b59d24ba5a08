"""What every step of one pair's matching shares: `MatchContext` (store, names, views, pool,
config, timings, the coarse searches run so far) and `Attempt` (one way of matching the pair).

The strategies (`matching.strategies`) read and extend the context and return attempts; the
matcher (`matching.matcher`) runs them and turns the winning attempt into a `PairResult`.
Index conventions: `names[0]`, `names[1]` are the pair's images 0 and 1; an attempt's
`reference` is the image it simulated, and its matches are in (reference, target) order until
`MatchContext.to_result` puts them in (image 0, image 1) order.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from .adaptive import nearest_views, viewpoint_at_centre
from .coarse import coarse_search, rank_views
from .config import MatcherConfig
from .fine import FineMatches
from .store import FeatureStore
from .types import CoarseScore, PairResult, ViewParams
from .verify import verify_matches

T = TypeVar("T")
R = TypeVar("R")


@dataclass
class Attempt:
    """One way of matching the pair: which image was simulated, the fused fine matches (reference
    keypoints, target keypoints), the fine views, the coarse scores it used, and how many of its
    matches a RANSAC model verified."""

    label: str
    reference: int
    fine: FineMatches
    views: list[ViewParams]
    coarse: list[CoarseScore]
    verified: int
    both_simulated: bool = False  # both images were simulated: the final homography decides the reference
    verified_mask: NDArray[np.bool_] | None = field(default=None, repr=False)
    """Which of `fine.matches` the verification accepted (None where an attempt did not keep it)."""


@dataclass
class MatchContext:
    """One pair's matching state. `views` (the main grid) and `pool` belong to the matcher and are
    shared by its pairs; `coarse` holds the coarse search of each side once it has run, and
    `reference` the side the coarse stage settled on (`reference.settle_reference`)."""

    store: FeatureStore
    names: tuple[str, str]
    cfg: MatcherConfig
    views: list[ViewParams]
    pool: Executor | None = None
    method: str = "extra-affine"
    timings: dict[str, float] = field(default_factory=dict)
    coarse: dict[int, list[CoarseScore]] = field(default_factory=dict)
    reference: int = 0
    targeted_coarse_inliers: int = 0  # the most ORB inliers of the adaptive targeted search, if it ran
    fallen_through: Attempt | None = None  # the best adaptive attempt that verified too little
    attempts: list[Attempt] = field(default_factory=list)  # every attempt of the escalation so far, in order
    notes: list[str] = field(default_factory=list)  # what each finishing step did (`PairResult.finishing`)

    def size(self, i: int) -> tuple[int, int]:
        """(width, height) of image `i` (0 or 1)."""
        h, w = self.store.image(self.names[i]).shape[:2]
        return w, h

    def coarse_for(self, side: int) -> list[CoarseScore]:
        """The coarse search with image `side` simulated against the other, run on first use."""
        if side not in self.coarse:
            self.coarse[side] = coarse_search(self.store, self.names[side], self.names[1 - side], self.views,
                                              self.cfg.coarse, self.pool, self.cfg.seed)
        return self.coarse[side]

    def coarse_near(self, side: int, H_1_from_0: NDArray[np.float64]) -> list[CoarseScore]:
        """The coarse search of image `side` on the `paths.targeted_views` grid views nearest the
        viewpoint change `H_1_from_0` implies at its centre (`adaptive.viewpoint_at_centre`), kept
        as that side's search when its best view has >= `coarse.accept_inliers` / 2 RANSAC
        inliers; else (or already searched) `coarse_for(side)`."""
        if side not in self.coarse:
            t, phi = viewpoint_at_centre(H_1_from_0, side, self.size(side))
            if math.isfinite(t):
                views = nearest_views(self.views, t, phi, self.cfg.paths.targeted_views)
                scores = coarse_search(self.store, self.names[side], self.names[1 - side], views,
                                       self.cfg.coarse, self.pool, self.cfg.seed)
                if scores and rank_views(scores)[0].inliers >= self.cfg.coarse.accept_inliers // 2:
                    self.coarse[side] = scores
        return self.coarse_for(side)

    def coarse_inliers(self) -> int:
        """The most ORB RANSAC inliers of any coarse view searched so far (evidence of overlap)."""
        full = max((c.inliers for scores in self.coarse.values() for c in scores), default=0)
        return max(full, self.targeted_coarse_inliers)

    def map(self, fn: Callable[[T], R], items: Sequence[T], min_items: int = 1) -> list[R]:
        """[fn(x) for x in items], on the pool when there is one and at least `min_items` items."""
        if self.pool is not None and len(items) >= min_items:
            return list(self.pool.map(fn, items))
        return [fn(x) for x in items]

    def verify(self, pts_ref: NDArray, pts_target: NDArray) -> tuple[int, NDArray[np.bool_]]:
        """(verified matches, mask) under the config's model (`verify.verify_matches`)."""
        return verify_matches(pts_ref, pts_target, self.cfg.verify_model, self.cfg.seed)

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Record the wall-clock seconds of the block as `timings[stage]`."""
        t = time.perf_counter()
        try:
            yield
        finally:
            self.timings[stage] = time.perf_counter() - t

    def to_result(self, att: Attempt, reason: str = "", f0: float | None = None,
                  f1: float | None = None) -> PairResult:
        """The attempt as a PairResult in image 0 / image 1 order (keypoints, matches and the
        views' reference swapped when image 1 was simulated)."""
        fm = att.fine
        sizes = (self.size(att.reference), self.size(1 - att.reference))  # (reference, target), swapped below
        res = PairResult(method=self.method, kpts0=fm.kpts_ref, kpts1=fm.kpts_target,
                         matches=fm.matches, distances=fm.distances, reference=0,
                         reference_reason=reason, f0=f0, f1=f1,
                         best_views=att.views, coarse_scores=att.coarse, image_sizes=sizes)
        if att.reference == 1:
            res = res.swapped()
            res.f0, res.f1 = f0, f1
        return res

