"""The `two-sided` escalation level, the pooled last resort.

Both images are simulated over `EscalationConfig.two_sided_grid`, each image's SIFT features of
all its views are pooled in original pixels, and the pools are matched with FLANN and MODS'
first-geometrically-inconsistent-nearest-neighbour (FGINN) ratio test: the second neighbour must
lie `fginn_px` away from the first, so the same point seen in several views does not fail the
ratio test against itself.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .context import Attempt, MatchContext
from .features import Features
from .fine import FineMatches
from .matching_utils import dedupe_by_location, unique_train
from .viewfeatures import pooled_features
from .views import view_grid


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


def two_sided_attempt(ctx: MatchContext, prev: Attempt) -> Attempt:
    """The `two-sided` level (module doc); `prev`'s reference is pooled as the query side."""
    cfg = ctx.cfg.escalation
    det = ctx.cfg.fine.detector
    views = view_grid(cfg.two_sided_grid)
    ref = prev.reference
    fa, _ = pooled_features(ctx.store, ctx.names[ref], views, det, cfg.two_sided_interp, ctx.pool)
    fb, _ = pooled_features(ctx.store, ctx.names[1 - ref], views, det, cfg.two_sided_interp, ctx.pool)
    mm, d = fginn_match(fa, fb, cfg.ratio, cfg.fginn_px, cfg.knn, ctx.cfg.seed)
    mm, d = dedupe_by_location(fa.kpts, fb.kpts, mm, d)
    if len(mm):
        used_a, inv_a = np.unique(mm[:, 0], return_inverse=True)
        used_b, inv_b = np.unique(mm[:, 1], return_inverse=True)
        matches = np.stack([inv_a.ravel(), inv_b.ravel()], axis=1).astype(np.int32)
    else:
        used_a = used_b = np.zeros(0, np.int64)
        matches = np.zeros((0, 2), np.int32)
    fine = FineMatches(fa.kpts[used_a], fb.kpts[used_b], matches, d.astype(np.float32), {"two-sided": int(len(mm))})
    n_ver = ctx.verify(fine.kpts_ref[matches[:, 0]], fine.kpts_target[matches[:, 1]])[0] if len(matches) else 0
    return Attempt(label="two-sided", reference=ref, fine=fine, views=[], coarse=prev.coarse, verified=n_ver,
                   both_simulated=True)
