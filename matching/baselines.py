"""Baseline pair matchers the extra-affine method is compared with: SIFT, ORB, ASIFT, AORB.

`make_baseline(method, **overrides)` returns one of four small matchers, each with a frozen
dataclass config. All four follow the same recipe:

1. features of each image, from the shared `FeatureStore` under a key that names the method and
   every config field that changes the features (so a multi-view pipeline computes them once per
   image, not once per pair);
2. nearest / second-nearest ratio test (0.75) from image 0 (query) to image 1 (train);
3. optionally (`final_homography=True`, the default) a seeded RANSAC homography
   (`matching_utils.ransac_homography`). Its threshold defaults to 5 px, what OpenCV's own
   `samples/python/asift.py` uses, so `asift` is *stock* ASIFT; `ransac_px=1.5` (bench flag
   `--baseline-ransac-px 1.5`) applies the extra-affine matcher's own final filter instead,
   for a same-filter comparison.

Result convention (the same as `PairResult`'s): `matches` holds *all* ratio-test matches and
`inlier_mask` flags the RANSAC inliers, with `H_1_from_0` the fitted homography. The paper's
"final matches" are the matches after RANSAC, so `PairResult.matched_points()` and
`matching.metrics.precision` use the inliers by default (`inliers_only=True`). When the
homography is disabled or there are fewer than 4 matches, `inlier_mask` is None and every
ratio-test match counts as final; when RANSAC finds no model, `inlier_mask` is all False (no
final match). `reason` says why in both failure cases.

ASIFT / AORB use OpenCV's `AffineFeature` (Yu & Morel's sampling: tilts sqrt(2)^k, k = 0..5,
rotations 72 deg / t), which pools the keypoints of every simulated view of an image and maps
them back to original-image pixels. That is the OpenCV sample's ASIFT (samples/python/asift.py),
not the IPOL reference implementation, which matches every view pair separately.

Determinism: same images + same config (including `seed`) give the same result. SIFT/ORB and
AffineFeature are deterministic; the FLANN KD-tree (ASIFT) and RANSAC draw from OpenCV's
per-thread RNG, which is re-seeded with `cv2.setRNGSeed(seed)` right before each of them
(FLANN here; RANSAC inside `ransac_homography`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .features import Features, from_keypoints
from .matching_utils import ransac_homography, ratio_filter
from .store import FeatureStore
from .types import PairResult

BASELINES: tuple[str, ...] = ("sift", "orb", "asift", "aorb")

FLANN_INDEX_KDTREE = 1


# configs ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BaselineConfig:
    """Matching and final-filter settings shared by every baseline."""

    ratio: float = 0.75
    """Nearest / second-nearest descriptor distance ratio."""
    final_homography: bool = True
    """Fit a RANSAC homography and flag its inliers."""
    ransac_px: float = 5.0
    """RANSAC reprojection threshold, px of image 1. 5 px is OpenCV's asift sample (stock);
    precision depends strongly on it while the number of correct matches barely changes
    (docs/decisions.md)."""
    ransac_iters: int = 10000
    """RANSAC iterations at most."""
    ransac_confidence: float = 0.999
    """RANSAC confidence."""
    min_inliers: int = 10
    """Fewer RANSAC inliers than this: result kept, `reason` says "weak"."""
    seed: int = 0
    """Seeds OpenCV's RNG before FLANN index building and RANSAC."""


@dataclass(frozen=True)
class SiftConfig(BaselineConfig):
    """SIFT, ratio test, RANSAC."""

    max_features: int = 0
    """SIFT budget per image (0 = unlimited)."""


@dataclass(frozen=True)
class OrbConfig(BaselineConfig):
    """ORB, ratio test, RANSAC."""

    max_features: int = 1000
    """ORB budget per image."""
    fast_threshold: int = 20
    """FAST threshold (OpenCV's default: the plain ORB baseline)."""


@dataclass(frozen=True)
class AffineConfig(BaselineConfig):
    """AffineFeature view sampling (OpenCV's defaults = the ASIFT paper's)."""

    max_tilt: int = 5
    """Highest power index k of the tilt t = tilt_step^k."""
    min_tilt: int = 0
    """Lowest power index k of the tilt."""
    tilt_step: float = math.sqrt(2.0)
    """Tilt ratio between levels."""
    rotate_step_base: float = 72.0
    """Longitude step b / t, degrees."""

    @property
    def view_key(self) -> str:
        return f"t{self.min_tilt}-{self.max_tilt}_s{self.tilt_step:.4f}_r{self.rotate_step_base:g}"


@dataclass(frozen=True)
class AsiftConfig(AffineConfig):
    """ASIFT as OpenCV's samples/python/asift.py: AffineFeature(SIFT), FLANN, ratio test, RANSAC."""

    max_features: int = 0
    """SIFT budget per simulated view (0 = unlimited)."""
    flann_trees: int = 5
    """FLANN KD-tree count (as OpenCV's samples/python/asift.py)."""
    flann_checks: int = 50
    """FLANN leaf checks."""


@dataclass(frozen=True)
class AorbConfig(AffineConfig):
    """AffineFeature(ORB), brute-force Hamming ratio test, RANSAC."""

    max_features: int = 1000
    """ORB budget per simulated view."""
    fast_threshold: int = 20
    """FAST threshold."""


# helpers ----------------------------------------------------------------------------------------
def fit_homography(pts0: NDArray, pts1: NDArray, cfg: BaselineConfig
                   ) -> tuple[NDArray[np.float64] | None, NDArray[np.bool_] | None]:
    """The final filter: seeded RANSAC homography mapping pts0 to pts1 and its inliers.

    The same function (`matching_utils.ransac_homography`) as the extra-affine matcher's final
    filter, so every method is judged after the identical RANSAC. Fewer than 4 points: (None,
    None), every match stays final. No model found: (None, all False), no match is final.
    """
    if len(pts0) < 4:
        return None, None
    H, mask = ransac_homography(pts0, pts1, cfg.ransac_px, seed=cfg.seed, max_iters=cfg.ransac_iters,
                                confidence=cfg.ransac_confidence)
    return (None if H is None else np.asarray(H, np.float64)), mask


# matchers ---------------------------------------------------------------------------------------
class _Baseline:
    """Shared pipeline: store features -> ratio test -> optional RANSAC homography."""

    name: str
    cfg: BaselineConfig

    # subclasses: what to compute on one image, under which store key, and how to match
    @property
    def feature_key(self) -> str:  # pragma: no cover - abstract
        raise NotImplementedError

    def detect(self, img: NDArray[np.uint8]) -> Features:  # pragma: no cover - abstract
        raise NotImplementedError

    def knn(self, d0: NDArray, d1: NDArray):  # pragma: no cover - abstract
        raise NotImplementedError

    def features(self, store: FeatureStore, name: str) -> Features:
        return store.get_or_compute(name, self.feature_key, lambda: self.detect(store.image(name)))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.cfg})"

    def match(self, store: FeatureStore, name0: str, name1: str) -> PairResult:
        cfg = self.cfg
        t_start = time.perf_counter()
        h0, w0 = store.image(name0).shape[:2]
        h1, w1 = store.image(name1).shape[:2]
        sizes = ((int(w0), int(h0)), (int(w1), int(h1)))
        timings: dict[str, float] = {}

        t = time.perf_counter()
        f0 = self.features(store, name0)
        f1 = self.features(store, name1)
        timings["detect"] = time.perf_counter() - t

        def done(result: PairResult) -> PairResult:
            result.timings = {**timings, "total": time.perf_counter() - t_start}
            result.image_sizes = sizes
            return result

        if len(f0) == 0 or len(f1) == 0:
            return done(PairResult.empty(self.name, f"no keypoints in image {0 if len(f0) == 0 else 1}"
                                         f" ({len(f0)} / {len(f1)})"))
        if len(f1) < 2:  # knn with k=2 needs two train descriptors
            return done(PairResult.empty(self.name, f"only {len(f1)} keypoint in image 1"))

        t = time.perf_counter()
        matches, dists = ratio_filter(self.knn(f0.descriptors, f1.descriptors), cfg.ratio)
        timings["match"] = time.perf_counter() - t
        if len(matches) == 0:
            return done(PairResult.empty(self.name, "no ratio-test matches"))

        result = PairResult(method=self.name, kpts0=f0.kpts, kpts1=f1.kpts, matches=matches,
                            distances=dists)
        if cfg.final_homography:
            t = time.perf_counter()
            H, mask = fit_homography(f0.kpts[matches[:, 0]], f1.kpts[matches[:, 1]], cfg)
            timings["ransac"] = time.perf_counter() - t
            result.H_1_from_0, result.inlier_mask = H, mask
            if H is None:
                result.reason = (f"only {len(matches)} ratio-test matches" if len(matches) < 4
                                 else f"RANSAC found no homography in {len(matches)} ratio-test matches")
            else:
                assert mask is not None  # a model comes with its inlier mask
                n_in = int(mask.sum())
                if n_in < cfg.min_inliers:
                    result.reason = f"weak: only {n_in} RANSAC inliers of {len(matches)} matches"
        return done(result)


class SiftMatcher(_Baseline):
    """Plain SIFT on both original images, L2 brute-force knn, ratio test, RANSAC."""

    name = "sift"
    cfg: SiftConfig

    def __init__(self, cfg: SiftConfig = SiftConfig()):
        self.cfg = cfg

    @property
    def feature_key(self) -> str:
        return f"base_sift{self.cfg.max_features}"

    def detect(self, img):
        kps, desc = cv2.SIFT_create(nfeatures=self.cfg.max_features).detectAndCompute(img, None)
        return from_keypoints(kps, desc, 128, np.float32)

    def knn(self, d0, d1):
        return cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)


class OrbMatcher(_Baseline):
    """Plain ORB (1000 features), Hamming brute-force knn, ratio test, RANSAC."""

    name = "orb"
    cfg: OrbConfig

    def __init__(self, cfg: OrbConfig = OrbConfig()):
        self.cfg = cfg

    @property
    def feature_key(self) -> str:
        return f"base_orb{self.cfg.max_features}_ft{self.cfg.fast_threshold}"

    def detect(self, img):
        orb = cv2.ORB_create(nfeatures=self.cfg.max_features, fastThreshold=self.cfg.fast_threshold)
        kps, desc = orb.detectAndCompute(img, None)
        return from_keypoints(kps, desc, 32, np.uint8)

    def knn(self, d0, d1):
        return cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d0, d1, k=2)


class AsiftMatcher(_Baseline):
    """ASIFT: AffineFeature(SIFT) on both images, FLANN KD-tree knn, ratio test, RANSAC."""

    name = "asift"
    cfg: AsiftConfig

    def __init__(self, cfg: AsiftConfig = AsiftConfig()):
        self.cfg = cfg

    @property
    def feature_key(self) -> str:
        return f"asift_sift{self.cfg.max_features}_{self.cfg.view_key}"

    def detect(self, img):
        c = self.cfg
        af = cv2.AffineFeature.create(cv2.SIFT_create(nfeatures=c.max_features), c.max_tilt, c.min_tilt,
                                      c.tilt_step, c.rotate_step_base)
        kps, desc = af.detectAndCompute(img, None)
        return from_keypoints(kps, desc, 128, np.float32)

    def knn(self, d0, d1):
        flann = cv2.FlannBasedMatcher(dict(algorithm=FLANN_INDEX_KDTREE, trees=self.cfg.flann_trees),
                                      dict(checks=self.cfg.flann_checks))
        cv2.setRNGSeed(self.cfg.seed)  # the KD-trees are randomised with OpenCV's RNG
        return flann.knnMatch(d0, d1, k=2)


class AorbMatcher(_Baseline):
    """AORB: AffineFeature(ORB) on both images, Hamming brute-force knn, ratio test, RANSAC."""

    name = "aorb"
    cfg: AorbConfig

    def __init__(self, cfg: AorbConfig = AorbConfig()):
        self.cfg = cfg

    @property
    def feature_key(self) -> str:
        return f"aorb_orb{self.cfg.max_features}_ft{self.cfg.fast_threshold}_{self.cfg.view_key}"

    def detect(self, img):
        c = self.cfg
        orb = cv2.ORB_create(nfeatures=c.max_features, fastThreshold=c.fast_threshold)
        af = cv2.AffineFeature.create(orb, c.max_tilt, c.min_tilt, c.tilt_step, c.rotate_step_base)
        kps, desc = af.detectAndCompute(img, None)
        return from_keypoints(kps, desc, 32, np.uint8)

    def knn(self, d0, d1):
        return cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d0, d1, k=2)


_CLASSES: dict[str, tuple[Callable[[Any], _Baseline], type[BaselineConfig]]] = {
    "sift": (SiftMatcher, SiftConfig),
    "orb": (OrbMatcher, OrbConfig),
    "asift": (AsiftMatcher, AsiftConfig),
    "aorb": (AorbMatcher, AorbConfig),
}


def make_baseline(method: str, **overrides) -> _Baseline:
    """The baseline matcher `method` (sift, orb, asift, aorb) with config fields overridden.

    Raises ValueError for an unknown method or config field.
    """
    if method not in _CLASSES:
        raise ValueError(f"unknown baseline {method!r}; choose one of {', '.join(BASELINES)}")
    cls, cfg_cls = _CLASSES[method]
    known = {f.name for f in dataclasses.fields(cfg_cls)}
    bad = sorted(set(overrides) - known)
    if bad:
        raise ValueError(f"{method}: unknown config field(s) {', '.join(bad)}; "
                         f"known: {', '.join(sorted(known))}")
    return cls(cfg_cls(**overrides))
