"""Descriptor matching helpers shared by the stages: ratio test, mutual check, RANSAC."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

FLANN_MIN_SIZE = 1500  # brute force below this many descriptors on either side
FLANN_TREES, FLANN_CHECKS = 4, 64  # the k-d forest FlannBasedMatcher builds by default; leaves searched


class KdForest:
    """A seeded FLANN k-d forest over float descriptors (the index `ratio_match` searches), built
    once and searched any number of times, from any thread (a FLANN search keeps its state on the
    caller's stack). Built with OpenCV's RNG seeded to `seed` just before, so it is the forest
    `ratio_match` would build itself for these descriptors and seed: sharing it changes no match.
    Why: an original's forest was rebuilt for every pair and view that searched it (0.07 CPU s
    for 15k SIFT descriptors, a fifth of a search; docs/decisions.md, "One k-d forest per image")."""

    def __init__(self, desc: NDArray, seed: int = 0):
        self.source = desc  # the array it was built for (`fits`)
        # FLANN indexes this memory without copying it: the forest keeps it alive
        self.data = np.ascontiguousarray(desc, np.float32)
        self.seed = int(seed)
        cv2.setRNGSeed(self.seed)
        self._index = cv2.flann.Index(self.data, {"algorithm": 1, "trees": FLANN_TREES})

    def __len__(self) -> int:
        return len(self.data)

    def fits(self, desc: NDArray, seed: int) -> bool:
        """Whether this is the forest a search of `desc` with `seed` would build: built for this
        very array with this seed."""
        return self.seed == int(seed) and desc is self.source

    def knn(self, queries: NDArray, k: int) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
        """(indices, squared L2 distances), each (len(queries), k), nearest first."""
        return self._index.knnSearch(np.ascontiguousarray(queries, np.float32), k, params={"checks": FLANN_CHECKS})


def _shared_or_own(provider: Callable[[int], KdForest] | None, desc: NDArray, seed: int) -> KdForest:
    """The provider's forest for `seed` when it indexes `desc`, else a forest built for this search."""
    if provider is not None:
        forest = provider(seed)
        if forest.fits(desc, seed):
            return forest
    return KdForest(desc, seed)


def ratio_match(desc_q: NDArray, desc_t: NDArray, norm: int, ratio: float = 0.75, seed: int = 0,
                flann_min_size: int = FLANN_MIN_SIZE, forest_t: Callable[[int], KdForest] | None = None
                ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Lowe's ratio test: (K, 2) (query, train) indices and the nearest distances.

    Brute force (exact) for small sets, such as ORB 1000 or the 1000 strongest SIFT; a seeded
    FLANN k-d forest for float descriptors when both sides exceed `flann_min_size`, where it is
    several times faster with nearly the same matches (docs/decisions.md).
    OpenCV's per-thread RNG is seeded just before the index is built, so results are
    deterministic whichever thread runs them. `forest_t`: gives `desc_t`'s forest for a seed, built
    once and shared (`Features.forest`), asked only when FLANN searches and used only when it is
    the forest this call would build (`KdForest.fits`).
    """
    if len(desc_q) < 1 or len(desc_t) < 2:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    if norm != cv2.NORM_HAMMING and min(len(desc_q), len(desc_t)) >= flann_min_size:
        # the k-d forest FlannBasedMatcher builds, searched for arrays (no DMatch objects: the same
        # neighbours, tests/test_features.py); FLANN returns squared L2 distances
        forest = _shared_or_own(forest_t, desc_t, seed)
        idx, d2 = forest.knn(desc_q, 2)
        d = np.sqrt(np.maximum(d2, 0)).astype(np.float32)
    else:  # exact: the two nearest neighbours as arrays, no per-match Python objects
        dtype = cv2.CV_32S if norm == cv2.NORM_HAMMING else cv2.CV_32F
        d, idx = cv2.batchDistance(desc_q, desc_t, dtype, normType=norm, K=2)
        d = d.astype(np.float32)
    ok = (idx[:, 1] >= 0) & (d[:, 0] < ratio * d[:, 1])
    q = np.flatnonzero(ok)
    return np.stack([q, idx[q, 0]], axis=1).astype(np.int32), d[q, 0]


def mutual_matches(matches: NDArray[np.int32], desc_q: NDArray, desc_t: NDArray, norm: int, seed: int = 0,
                   flann_min_size: int = FLANN_MIN_SIZE, forest_q: Callable[[int], KdForest] | None = None
                   ) -> NDArray[np.bool_]:
    """Mask of the (query, train) `matches` whose train descriptor has its query as nearest
    neighbour among all of `desc_q` (COLMAP's cross-check). Only the matched train descriptors
    are searched, so it costs a fraction of the forward matching; the same k-d forest (seeded;
    `forest_q`: gives `desc_q`'s, as `ratio_match`'s `forest_t`) or brute force as `ratio_match`."""
    if len(matches) == 0:
        return np.zeros(0, bool)
    train, inverse = np.unique(matches[:, 1], return_inverse=True)
    queries = np.ascontiguousarray(desc_t[train])
    if norm != cv2.NORM_HAMMING and min(len(desc_q), len(queries)) >= flann_min_size:
        forest = _shared_or_own(forest_q, desc_q, seed)
        idx, _ = forest.knn(queries, 1)
    else:
        dtype = cv2.CV_32S if norm == cv2.NORM_HAMMING else cv2.CV_32F
        _, idx = cv2.batchDistance(queries, desc_q, dtype, normType=norm, K=1)
    return np.asarray(idx, np.int64).reshape(-1)[inverse.reshape(-1)] == matches[:, 0]


def ratio_filter(knn, ratio: float) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """(K, 2) (query, train) pairs and (K,) distances of OpenCV k-NN results passing the ratio test."""
    out, dist = [], []
    for pair in knn:
        if len(pair) >= 2 and pair[0].distance < ratio * pair[1].distance:
            out.append((pair[0].queryIdx, pair[0].trainIdx))
            dist.append(pair[0].distance)
    if not out:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    return np.asarray(out, np.int32), np.asarray(dist, np.float32)


def unique_train(matches: NDArray[np.int32], dist: NDArray[np.float32]
                 ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Keep, for every train index, only its closest query (one-to-one on the train side)."""
    if len(matches) == 0:
        return matches, dist
    order = np.lexsort((dist, matches[:, 1]))
    m = matches[order]
    first = np.ones(len(m), bool)
    first[1:] = m[1:, 1] != m[:-1, 1]
    keep = np.sort(order[first])
    return matches[keep], dist[keep]


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


def polish_homography(pts0: NDArray, pts1: NDArray, H_1_from_0: NDArray[np.float64], thresh_px: float,
                      rounds: int = 3) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """`H_1_from_0` re-fitted to the matches it explains within `thresh_px` (px of image 1),
    repeated while that set grows, with the final inlier mask (a local optimisation step).

    OpenCV's RANSAC returns its best sample's consensus set with the model refined on it, but not
    the set the refined model explains: after patch refinement moved the points, the refined
    model explains more of them. Each round is OpenCV's least-squares fit (Levenberg-Marquardt
    refined) to the current inliers; a round that does not add inliers ends the loop, so the
    result explains at least as many matches as `H_1_from_0`. Deterministic (no sampling).
    """
    p0 = np.asarray(pts0, np.float32).reshape(-1, 2)
    p1 = np.asarray(pts1, np.float32).reshape(-1, 2)

    def explained(H: NDArray[np.float64]) -> NDArray[np.bool_]:
        q = np.c_[p0.astype(np.float64), np.ones(len(p0))] @ H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            d = q[:, :2] / q[:, 2:3] - p1
            e = np.sqrt((d * d).sum(axis=1))
        return np.isfinite(e) & (e <= thresh_px)

    def fit(mask: NDArray[np.bool_]) -> NDArray[np.float64] | None:
        H, _ = cv2.findHomography(p0[mask], p1[mask], 0)
        if H is None or not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
            return None
        return np.asarray(H / H[2, 2], np.float64)

    return _grow_consensus(np.asarray(H_1_from_0, np.float64), fit, explained, 4, rounds)


def polish_fundamental(pts0: NDArray, pts1: NDArray, F_1_from_0: NDArray[np.float64], thresh_px: float,
                       rounds: int = 3) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """`F_1_from_0` re-fitted by the normalised eight-point method (rank 2 enforced) to the
    matches within `thresh_px` of their epipolar lines in both images (OpenCV's RANSAC error),
    repeated while that set grows, with the final inlier mask (a local optimisation step).

    OpenCV's classic `FM_RANSAC` returns a seven-point sample's model as it is: at a 1 px
    threshold and 0.4 px detection noise it explains 395 of 500 true matches of a synthetic
    pair where the polished model explains 453 (`tests/test_polish.py`). A round
    that does not add inliers ends the loop; deterministic (no sampling).
    """
    p0 = np.asarray(pts0, np.float64).reshape(-1, 2)
    p1 = np.asarray(pts1, np.float64).reshape(-1, 2)
    h0, h1 = np.c_[p0, np.ones(len(p0))], np.c_[p1, np.ones(len(p1))]

    def explained(F: NDArray[np.float64]) -> NDArray[np.bool_]:
        l1, l0 = h0 @ F.T, h1 @ F  # epipolar lines in image 1 of image-0 points, and back
        num = np.abs((l1 * h1).sum(axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.maximum(num / np.hypot(l1[:, 0], l1[:, 1]), num / np.hypot(l0[:, 0], l0[:, 1]))
        return np.isfinite(d) & (d <= thresh_px)

    def fit(mask: NDArray[np.bool_]) -> NDArray[np.float64] | None:
        F, _ = cv2.findFundamentalMat(p0[mask].astype(np.float32), p1[mask].astype(np.float32), cv2.FM_8POINT)
        if F is None or F.shape != (3, 3) or not np.isfinite(F).all():
            return None
        return np.asarray(F, np.float64)

    return _grow_consensus(np.asarray(F_1_from_0, np.float64), fit, explained, 8, rounds)


def _grow_consensus(model: NDArray[np.float64], fit: Callable[[NDArray[np.bool_]], NDArray[np.float64] | None],
                    explained: Callable[[NDArray[np.float64]], NDArray[np.bool_]], min_inliers: int,
                    rounds: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The polish loop shared by `polish_homography` and `polish_fundamental`: re-`fit` the model
    to the matches it `explained`, at most `rounds` times, while that set grows (and holds at least
    `min_inliers`); returns the last model that grew it and its inlier mask."""
    mask = explained(model)
    for _ in range(rounds):
        if mask.sum() < min_inliers:
            break
        new = fit(mask)
        if new is None:
            break
        mask_new = explained(new)
        if mask_new.sum() <= mask.sum():
            break
        model, mask = new, mask_new
    return model, mask


def ransac_homography(pts0: NDArray, pts1: NDArray, thresh_px: float, seed: int = 0,
                      max_iters: int = 10000, confidence: float = 0.999,
                      ) -> tuple[NDArray[np.float64] | None, NDArray[np.bool_]]:
    """H_1_from_0 and its inlier mask by RANSAC with Levenberg-Marquardt refinement (seeded).

    OpenCV's classic RANSAC, not USAC-MAGSAC++: at a tight threshold MAGSAC's model kept fewer
    and less precise inliers on graf (docs/decisions.md). The seed is applied to OpenCV's
    per-thread RNG just before the call, so results do not depend on which thread runs the pair.
    Returns (None, all False) below 4 correspondences.
    """
    n = len(pts0)
    if n < 4:
        return None, np.zeros(n, bool)
    cv2.setRNGSeed(seed)
    H, mask = cv2.findHomography(np.asarray(pts0, np.float32), np.asarray(pts1, np.float32),
                                 cv2.RANSAC, thresh_px, maxIters=max_iters, confidence=confidence)
    if H is None or mask is None or not np.isfinite(H).all():
        return None, np.zeros(n, bool)
    return H / H[2, 2], mask.ravel().astype(bool)
