"""Fine stage (§III-C): SIFT on Lanczos re-simulations of the chosen views against the target.

Each chosen view of the reference is re-warped with Lanczos (8x8 kernel), SIFT keypoints are
detected in it and mapped back to the original reference image, and its descriptors are
ratio-matched against the target's SIFT. Several views (the top of the coarse search) can be
fused: their matches are concatenated and made one-to-one on the target side, keeping the
closest descriptor. The paper uses a single view (`top_k = 1`).

The unwarped originals (the identity view) may be matched with another detector
(`FineConfig.original_detector`, e.g. COLMAP's covariant SIFT): its descriptors are comparable
only with its own, so each view is matched against the target's features of the same detector
(`TargetFeatures`), and the target keypoints of the result are the union of both sets.

Also here, the matching primitives of the second, guided rounds (`matching.guided`): ratio tests
restricted to target keypoints near a homography's prediction (`guided_match`) or within a band
around a fundamental matrix's epipolar line (`epipolar_guided_match`).
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .adaptive import tilt_plane_point
from .features import DetectorConfig, Features
from .matching_utils import mutual_matches, ratio_match, unique_train
from .store import FeatureStore
from .types import CoarseScore, ViewParams
from .viewfeatures import original_features, view_features
from .views import Interp, capped_view

OriginalDetector = Literal["sift", "colmap-sift", "colmap-sift-affine", "colmap-sift-plain"]


@dataclass(frozen=True)
class FineConfig:
    """SIFT on the chosen views, re-rendered with care (paper: Lanczos, ratio 0.75)."""

    ratio: float = 0.75
    """Lowe's ratio of the SIFT matches (paper: 0.75)."""
    interp: Interp = "lanczos"
    """Warp interpolation of the fine views (paper: Lanczos, 8x8 kernel)."""
    antialias: bool = True
    """ASIFT's blur along the compressed axis before compressing (`views.antialias_sigma`)."""
    root_sift: bool = False
    """RootSIFT descriptors (L1-normalised, square-rooted), kept at OpenCV's L2 scale, for the
    views, the target and the reference decision. Off: on the 18 shared pairs 2.4 % more correct
    matches, but EVD mag's precision 43 -> 30 % and one of the 96 rendered tilt pairs lost, and no
    gain in scenes (docs/decisions.md, "RootSIFT in the pair matcher measured")."""
    sift_features: int = 0
    """SIFT budget per image or view (0 = unlimited)."""
    sift_contrast: float = 0.04
    """OpenCV SIFT's contrast threshold in the simulated views (OpenCV's default). A matcher that
    simulates nothing (`recon run --simulate needed`'s first pass) sets it to its originals' so
    the target's features are one set (`TargetFeatures`) instead of two detections."""
    max_area_ratio: float = 1.0
    """(> 0) caps a view's zoom so its area is at most that multiple of the original's
    (`views.capped_view`); 0 renders the paper's zoom s = 1 + k*ds in full. The cap gives the
    same points for less time and memory: SIFT's scale space doubles its input
    (docs/decisions.md)."""

    original_detector: OriginalDetector = "sift"
    """Detector of the unwarped originals when they are matched with each other (the identity
    view): "sift" = the views' OpenCV SIFT (`detector`); "colmap-sift" = COLMAP's SIFT with affine
    shape estimation and domain-size pooling (`matching.colmap_sift`, what COLMAP's `high` preset
    extracts; RootSIFT on both sides, a few seconds per 800x600 image). The simulated views keep
    OpenCV's SIFT against the target's OpenCV SIFT (`TargetFeatures`); "colmap-sift-affine" = the
    same without domain-size pooling (affine shape only, 40 % of the time at 1600 px);
    "colmap-sift-plain" = neither (COLMAP's default extraction, what stock `default` matches)."""
    original_contrast: float = 0.04
    """OpenCV SIFT's contrast threshold on the originals when `original_detector` = "sift"
    (0.04 = the views' detector, one feature set; 0.02 finds about 4x the keypoints on a
    1600 px photo, about COLMAP's default peak threshold, for 0.2 s more per image)."""
    original_precise_upscale: bool = False
    """OpenCV SIFT's `enable_precise_upscale` on the originals when `original_detector` = "sift"
    (`DetectorConfig.precise_upscale`)."""
    centre_keypoints: bool = True
    """OpenCV SIFT's keypoints (views and originals) moved by -0.25 px onto pixel centres
    (`DetectorConfig.centre_keypoints`); False keeps OpenCV's positions, as before 2026-12-02."""
    original_dsp_scales: int = 10
    """Support sizes of "colmap-sift"'s domain-size pooling (`DetectorConfig.dsp_scales`)."""
    original_cross_check: bool = False
    """Keep only the originals' ratio-test matches that are mutual nearest neighbours (COLMAP's
    cross-check): a target keypoint whose own nearest reference keypoint is another one is
    dropped. `recon run --simulate needed` turns it on in its first pass
    (`recon.config.MatchConfig.first_pass_cross_check`)."""

    @property
    def detector(self) -> DetectorConfig:
        """The simulated views' detector (OpenCV SIFT)."""
        return DetectorConfig("sift", self.sift_features, self.root_sift, contrast=self.sift_contrast,
                              centre_keypoints=self.centre_keypoints)

    @property
    def originals_detector(self) -> DetectorConfig:
        """The detector of the originals matched with each other (`original_detector`)."""
        if self.original_detector == "sift":
            return dataclasses.replace(self.detector, contrast=self.original_contrast,
                                       precise_upscale=self.original_precise_upscale)
        return DetectorConfig(self.original_detector, self.sift_features, True, dsp_scales=self.original_dsp_scales)

    def detector_for(self, view: ViewParams) -> DetectorConfig:
        """The detector of `view` of the reference (and of the target features it is matched with)."""
        return self.originals_detector if view.is_identity else self.detector


@dataclass
class TargetFeatures:
    """The target original's features of every detector the fine views use, one index space:
    `kpts` holds each detector's keypoints one block after the other, and `parts[det.key]` =
    (that detector's features, where its block starts in `kpts`)."""

    kpts: NDArray[np.float32]
    parts: dict[str, tuple[Features, int]]

    def part(self, det: DetectorConfig) -> tuple[Features, int]:
        """(`det`'s features of the target, offset of its indices in `kpts`)."""
        return self.parts[det.key]


def target_features(store: FeatureStore, target: str, cfg: FineConfig) -> TargetFeatures:
    """The target's original features for `cfg`'s detectors (`TargetFeatures`); with the default
    `original_detector` a single block, the target's OpenCV SIFT itself."""
    dets = {cfg.detector.key: cfg.detector, cfg.originals_detector.key: cfg.originals_detector}
    parts: dict[str, tuple[Features, int]] = {}
    blocks = []
    offset = 0
    for key, det in dets.items():
        f = original_features(store, target, det)
        parts[key] = (f, offset)
        blocks.append(f.kpts)
        offset += len(f)
    kpts = blocks[0] if len(blocks) == 1 else np.concatenate(blocks).astype(np.float32)
    return TargetFeatures(kpts, parts)


@dataclass
class FineMatches:
    """Matches of fused views: reference keypoints (original frame), target keypoints, pairs."""

    kpts_ref: NDArray[np.float32]
    kpts_target: NDArray[np.float32]
    matches: NDArray[np.int32]  # (K, 2): (index into kpts_ref, index into kpts_target)
    distances: NDArray[np.float32]
    per_view: dict[str, int]


def select_fine_views(ranked: list[CoarseScore], k: int, include_original: bool = False,
                      min_distance: float = 0.0) -> list[ViewParams]:
    """The `k` best distinct views for the fine stage, best first (+ the original if asked).

    At t = 1 a view is the original rotated by phi (and zoomed by s = 1): SIFT is rotation
    invariant, so every t = 1 view is replaced by the original itself, whose SIFT is already
    cached, and counted once. `include_original` adds the original when the top `k` lack it:
    its keypoints are the same in every pair of the image (tracks longer than two views) and
    cover the surfaces the best views do not rectify. With `min_distance` > 0 a view closer than
    that to a chosen one in the tilt plane (`adaptive.tilt_plane_point`) is skipped
    (`MatcherConfig.fine_min_view_distance`).
    """
    identity = ViewParams(1.0, 0.0, 1.0)
    out: list[ViewParams] = []
    for c in ranked:
        v = identity if c.view.t == 1.0 else c.view
        if min_distance > 0 and any(
                float(np.linalg.norm(tilt_plane_point(v.t, v.phi) - tilt_plane_point(u.t, u.phi))) < min_distance
                for u in out):
            continue
        if v not in out:
            out.append(v)
        if len(out) == k:
            break
    if include_original and identity not in out:
        out.append(identity)
    return out


def fine_match(store: FeatureStore, ref: str, target: str, views: list[ViewParams],
               cfg: FineConfig, executor: Executor | None = None, seed: int = 0) -> FineMatches:
    """SIFT of each view of `ref` ratio-matched against the original `target` (features of the
    view's detector, `FineConfig.detector_for`), fused one-to-one on the target side (closest
    descriptor wins); `seed` seeds FLANN for large sets."""
    size = store.image(ref).shape[1::-1]

    def one(view: ViewParams):
        det = cfg.detector_for(view)
        # the view first: its warp and detection need not wait for the target's detection, which
        # may still run (the matcher starts it while the coarse search scores its views)
        fv = view_features(store, ref, capped_view(view, size, cfg.max_area_ratio), det, cfg.interp, cfg.antialias)
        ft, offset = target_features(store, target, cfg).part(det)
        # the target original's forest is shared by all views and pairs; so is the reference
        # original's, which the identity view's cross-check searches
        m, d = ratio_match(fv.descriptors, ft.descriptors, cv2.NORM_L2, cfg.ratio, seed, forest_t=ft.forest)
        if cfg.original_cross_check and view.is_identity and len(m):
            keep = mutual_matches(m, fv.descriptors, ft.descriptors, cv2.NORM_L2, seed, forest_q=fv.forest)
            m, d = m[keep], d[keep]
        if offset and len(m):
            m = m.copy()
            m[:, 1] += offset
        return fv, m, d

    parts = list(executor.map(one, views)) if executor is not None and len(views) > 1 else [one(v) for v in views]
    tf = target_features(store, target, cfg)
    kpts_ref, matches, dists, per_view = [], [], [], {}
    offset = 0
    for view, (fv, m, d) in zip(views, parts, strict=True):
        per_view[view.key] = int(len(m))
        if len(m):
            used = np.unique(m[:, 0])
            remap = np.full(len(fv), -1, np.int64)
            remap[used] = np.arange(len(used)) + offset
            kpts_ref.append(fv.kpts[used])
            matches.append(np.stack([remap[m[:, 0]], m[:, 1]], axis=1).astype(np.int32))
            dists.append(d)
            offset += len(used)
    if not matches:
        return FineMatches(np.zeros((0, 2), np.float32), tf.kpts, np.zeros((0, 2), np.int32),
                           np.zeros(0, np.float32), per_view)
    m_all, d_all = unique_train(np.concatenate(matches), np.concatenate(dists))
    return FineMatches(np.concatenate(kpts_ref), tf.kpts, m_all, d_all, per_view)


def candidate_ratio_test(rows: NDArray, cols: NDArray, dd: NDArray, ratio: float
                         ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float32]]:
    """Lowe's ratio test over sparse candidates: (query, target, distance) of the accepted matches.

    `rows[k]`, `cols[k]`, `dd[k]`: query index, target index and descriptor distance of the k-th
    candidate pair (any order). Each query keeps its nearest candidate when it beats the second
    nearest by `ratio`; a query with a single candidate is kept when its distance is at most the
    median of the accepted two-candidate matches (all singletons are kept when there are none).
    """
    order = np.lexsort((dd, rows))
    rows, cols, dd = rows[order], cols[order], dd[order]
    first = np.ones(len(rows), bool)
    first[1:] = rows[1:] != rows[:-1]
    idx = np.flatnonzero(first)
    nxt = idx + 1
    has_second = np.zeros(len(idx), bool)
    ok = nxt < len(rows)
    has_second[ok] = rows[nxt[ok]] == rows[idx[ok]]
    best = dd[idx]
    second = np.full(len(idx), np.inf, np.float32)
    second[has_second] = dd[idx[has_second] + 1]
    accept = best < ratio * second
    if np.any(accept & has_second):
        accept &= has_second | (best <= float(np.median(best[accept & has_second])))
    return rows[idx[accept]], cols[idx[accept]], best[accept].astype(np.float32)


def guided_match(kpts_q: NDArray, desc_q: NDArray, kpts_t: NDArray, desc_t: NDArray,
                 H_t_from_q: NDArray[np.float64], radius_px: float, ratio: float,
                 ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Ratio-test matching restricted to target keypoints within `radius_px` of H(query).

    The homography from the first round predicts where each query keypoint lands; only target
    keypoints near that prediction compete, so the ratio test rejects far fewer true matches
    than the unconstrained one (COLMAP's guided matching, for planar pairs). A query with a
    single candidate is kept when its descriptor distance is below the median of the accepted
    two-candidate matches. Float (SIFT) descriptors; candidates are found on a grid of
    `radius_px` cells, so the cost is linear in the number of keypoints.
    """
    empty = np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    if len(kpts_q) == 0 or len(kpts_t) == 0:
        return empty
    q = np.c_[kpts_q.astype(np.float64), np.ones(len(kpts_q))] @ H_t_from_q.T
    with np.errstate(divide="ignore", invalid="ignore"):
        pred = q[:, :2] / q[:, 2:3]
    ok = np.isfinite(pred).all(axis=1) & (q[:, 2] > 0)
    qi = np.flatnonzero(ok)
    if len(qi) == 0:
        return empty
    pred = pred[qi]
    # candidate pairs via a hash grid of cell size radius: check the 3x3 neighbourhood
    cell_t = np.floor(kpts_t / radius_px).astype(np.int64)
    key_t = cell_t[:, 0] * 1_000_003 + cell_t[:, 1]
    order_t = np.argsort(key_t, kind="stable")
    key_sorted = key_t[order_t]
    cell_q = np.floor(pred / radius_px).astype(np.int64)
    rows_l, cols_l = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            kq = (cell_q[:, 0] + dx) * 1_000_003 + (cell_q[:, 1] + dy)
            lo = np.searchsorted(key_sorted, kq, "left")
            hi = np.searchsorted(key_sorted, kq, "right")
            cnt = hi - lo
            if cnt.sum() == 0:
                continue
            r = np.repeat(np.arange(len(kq)), cnt)
            starts = np.repeat(lo - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
            c = order_t[np.arange(cnt.sum()) + starts]
            rows_l.append(r)
            cols_l.append(c)
    if not rows_l:
        return empty
    rows = np.concatenate(rows_l)
    cols = np.concatenate(cols_l)
    d2 = ((pred[rows] - kpts_t[cols]) ** 2).sum(1)
    near = d2 <= radius_px * radius_px
    rows, cols = rows[near], cols[near]
    if len(rows) == 0:
        return empty
    dd = np.linalg.norm(desc_q[qi[rows]].astype(np.float32) - desc_t[cols].astype(np.float32), axis=1)
    q, t, best = candidate_ratio_test(rows, cols, dd, ratio)
    return np.stack([qi[q], t], axis=1).astype(np.int32), best


def _epipolar_lines(F_t_from_q: NDArray[np.float64], pts_q: NDArray) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """((N, 3) lines F x of the query points, normalised so that a·x + b·y + c is a distance in
    target pixels; (N,) mask of the points whose line is defined). x_tᵀ F x_q = 0."""
    pts = np.asarray(pts_q, np.float64).reshape(-1, 2)
    lines = np.c_[pts, np.ones(len(pts))] @ np.asarray(F_t_from_q, np.float64).T
    norm = np.hypot(lines[:, 0], lines[:, 1])
    valid = norm > 0
    return lines / np.where(valid, norm, np.inf)[:, None], valid


def epipolar_pair_distance(F_t_from_q: NDArray[np.float64], pts_q: NDArray, pts_t: NDArray) -> NDArray[np.float64]:
    """(K,) distance in px of each pts_t[k] to the epipolar line of pts_q[k] in the target."""
    lines, _ = _epipolar_lines(F_t_from_q, pts_q)
    t = np.asarray(pts_t, np.float64).reshape(-1, 2)
    return np.abs(lines[:, 0] * t[:, 0] + lines[:, 1] * t[:, 1] + lines[:, 2])


def _runs(lo: NDArray[np.int64], hi: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(row, position) for every position in [lo[i], hi[i]) of every row i, vectorised."""
    cnt = np.maximum(hi - lo, 0)
    total = int(cnt.sum())
    rows = np.repeat(np.arange(len(lo)), cnt)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(cnt)[:-1]]), cnt)
    return rows, np.arange(total) + starts


def epipolar_band_candidates(F_t_from_q: NDArray[np.float64], kpts_q: NDArray, kpts_t: NDArray,
                             radius_px: float, near_px: float = 64.0) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(rows, cols): every (query, target) pair whose target lies within `radius_px` of the
    query's epipolar line: the same set as thresholding every (query, target) distance, without
    the (N, M) matrix.

    All lines F x pass through the target epipole e (Fᵀ e = 0). A target at distance rho from
    e, in direction alpha (mod 180°), lies within r of a line through e of direction theta iff
    rho |sin(alpha - theta)| <= r, so with rho >= R only targets with |alpha - theta| <=
    asin(r / R) can qualify. Targets are grouped in rings of rho ([R, 4R), [4R, 16R), ...,
    R = `near_px`), each sorted by alpha and searched with a window that shrinks as its ring
    grows; the few targets nearer the epipole than `near_px` are tested against every line;
    with the epipole at infinity (parallel lines) the search runs on each target's offset
    along the lines' common normal. Every candidate is then checked exactly.
    """
    kq = np.asarray(kpts_q, np.float64).reshape(-1, 2)
    kt = np.asarray(kpts_t, np.float64).reshape(-1, 2)
    F = np.asarray(F_t_from_q, np.float64)
    lines, valid = _epipolar_lines(F, kq)
    lines[~valid] = 0.0  # undefined lines (query at the epipole) match nothing, see `valid` below
    e = np.linalg.svd(F.T)[2][-1]
    found_r: list[NDArray[np.int64]] = []
    found_c: list[NDArray[np.int64]] = []

    def search(keys: NDArray, members: NDArray[np.int64], lo_key: NDArray, hi_key: NDArray) -> None:
        order = np.argsort(keys, kind="stable")
        s = keys[order]
        r, pos = _runs(np.searchsorted(s, lo_key, "left"), np.searchsorted(s, hi_key, "right"))
        found_r.append(r)
        found_c.append(members[order[pos]])

    if abs(e[2]) <= 1e-12 * np.hypot(e[0], e[1]):  # epipole at infinity: parallel lines
        n = np.array([-e[1], e[0]]) / np.hypot(e[0], e[1])  # their common normal
        sign = np.where(lines[:, :2] @ n < 0, -1.0, 1.0)
        offset = -lines[:, 2] * sign
        search(kt @ n, np.arange(len(kt)), offset - 1.5 * radius_px, offset + 1.5 * radius_px)
    else:
        v = kt - e[:2] / e[2]
        rho = np.hypot(v[:, 0], v[:, 1])
        alpha = np.mod(np.arctan2(v[:, 1], v[:, 0]), np.pi)
        theta = np.mod(np.arctan2(-lines[:, 0], lines[:, 1]), np.pi)  # direction (b, -a) of a x + b y + c = 0
        ring_lo = near_px
        while np.any(rho >= ring_lo):
            ring = np.flatnonzero((rho >= ring_lo) & (rho < 4.0 * ring_lo))
            if len(ring):
                w = 1.05 * np.arcsin(min(1.0, radius_px / ring_lo))
                for wrap in (-np.pi, 0.0, np.pi):  # windows that cross 0 / 180 degrees
                    search(alpha[ring], ring, theta + wrap - w, theta + wrap + w)
            ring_lo *= 4.0
        near = np.flatnonzero(rho < near_px)
        if len(near):
            found_r.append(np.repeat(np.arange(len(kq)), len(near)))
            found_c.append(np.tile(near, len(kq)))
    if not found_r:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows, cols = np.concatenate(found_r), np.concatenate(found_c)
    dist = np.abs((lines[rows, :2] * kt[cols]).sum(1) + lines[rows, 2])
    keep = (dist <= radius_px) & valid[rows]
    return rows[keep], cols[keep]


def epipolar_guided_match(kpts_q: NDArray, desc_q: NDArray, kpts_t: NDArray, desc_t: NDArray,
                          F_t_from_q: NDArray[np.float64], radius_px: float, ratio: float,
                          ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Ratio-test matching restricted to target keypoints within `radius_px` of the epipolar line.

    The non-planar counterpart of `guided_match` (COLMAP's guided matching under F): a
    fundamental matrix fitted to the first round's matches says on which line each query
    keypoint's match must lie, so only the target keypoints in that band compete in the ratio
    test and true matches that a global nearest neighbour rejected (a similar pattern elsewhere
    in the image) come back. Float (SIFT) descriptors. The band holds a tiny fraction of the
    target keypoints (a 2 px strip of a 1600 px image), so the candidates are found first
    (`epipolar_band_candidates`, by binary search) and descriptor distances computed only for
    them: linear in the number of candidates, not N x M x 128. A query with a single candidate
    in its band is kept when its descriptor distance is below the median of the accepted
    two-candidate matches.
    """
    empty = np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    if len(kpts_q) == 0 or len(kpts_t) < 2:
        return empty
    dq_all = np.asarray(desc_q, np.float32)
    dt = np.asarray(desc_t, np.float32)
    rows, cols = epipolar_band_candidates(F_t_from_q, kpts_q, kpts_t, radius_px)
    if len(rows) == 0:
        return empty
    dd = np.empty(len(rows), np.float32)
    for lo in range(0, len(rows), 1 << 16):  # bounded temporaries
        diff = dq_all[rows[lo:lo + (1 << 16)]] - dt[cols[lo:lo + (1 << 16)]]
        dd[lo:lo + (1 << 16)] = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    q, t, best = candidate_ratio_test(rows, cols, dd, ratio)
    return np.stack([q, t], axis=1).astype(np.int32), best
