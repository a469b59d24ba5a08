"""SIFT descriptors of the original photos at the database's keypoints, so COLMAP's own matchers
(exhaustive, sequential, vocabulary tree) can match new photos against a `recon run` database.

The database's keypoints are *merged* keypoints (`recon.core.tracks`): each is the centre of a
cluster of pair-specific keypoints, many found in simulated (affinely warped) views, so they are
not SIFT keypoints of the original photo one to one and have no scale or orientation of their
own. What is written for keypoint k of an image (full-resolution OpenCV pixels in, COLMAP rows
out, same order as the keypoints):

* when OpenCV's SIFT, run on the original photo at the working resolution, detects a keypoint
  within `SNAP_PX` working px of k: that detection's descriptor (its scale and orientation);
* otherwise: an upright SIFT descriptor computed at k with the median detected size (these
  match only views of similar scale and roll; `DescriptorStats.upright` counts them).

Descriptors are stored as COLMAP's own extractor stores them (`FeatureExtractorType.SIFT`, L1-root
normalised, x512, uint8), so they compare with descriptors COLMAP extracts for new photos.
Only for the SIFT-based methods (`SIFT_METHODS`); ORB has no SIFT descriptors to offer.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.features import DetectorConfig, Features, detect
from recon.core.scene import to_working

SIFT_METHODS: frozenset[str] = frozenset({"extra-affine", "sift", "asift"})
SNAP_PX = 2.0  # working px: how far a merged keypoint may be from a SIFT detection to take its descriptor


@dataclass
class DescriptorStats:
    """How the descriptors of one image were made."""

    snapped: int = 0  # from a SIFT detection within SNAP_PX
    upright: int = 0  # computed at the keypoint, upright, median size


def colmap_sift_u8(desc: NDArray[np.float32]) -> NDArray[np.uint8]:
    """OpenCV SIFT descriptors (N, 128) float -> COLMAP's stored form: L1-root (L1-normalise,
    square root: unit L2 norm), then round(min(512 * d, 255)) as uint8 (COLMAP's
    FeatureDescriptorsToUnsignedByte)."""
    d = np.asarray(desc, np.float64).reshape(-1, 128)
    d = np.sqrt(d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-12))
    return np.round(np.minimum(512.0 * d, 255.0)).astype(np.uint8)


def sift_descriptors(gray_work: NDArray[np.uint8], kpts_full: NDArray[np.float32],
                     scale_xy: tuple[float, float], detections: Features | None = None
                     ) -> tuple[NDArray[np.uint8], DescriptorStats]:
    """(N, 128) uint8 descriptors for the full-resolution keypoints `kpts_full` (see module doc),
    from the working-resolution gray photo `gray_work` (`scale_xy` = working / full size).
    `detections`: an OpenCV SIFT set of `gray_work` (plain descriptors, any contrast threshold;
    the feature store's set of the original, `recon.core.stages.database.descriptor_detector`),
    else OpenCV's default SIFT detected here."""
    from scipy.spatial import cKDTree

    k = np.asarray(kpts_full, np.float64).reshape(-1, 2)
    n = len(k)
    if n == 0:
        return np.zeros((0, 128), np.uint8), DescriptorStats()
    k_work = to_working(k, scale_xy)
    if detections is None:
        detections = detect(gray_work, DetectorConfig("sift"))
    pts = np.asarray(detections.kpts, np.float64).reshape(-1, 2)
    sizes = np.asarray(detections.sizes, np.float64)
    desc_det = detections.descriptors
    sift = cv2.SIFT.create()
    out = np.zeros((n, 128), np.float32)
    snapped = np.zeros(n, bool)
    if len(pts):
        tree = cKDTree(pts)
        dist, idx = tree.query(k_work, distance_upper_bound=SNAP_PX)
        snapped = np.isfinite(dist)
        out[snapped] = desc_det[idx[snapped]]
    rest = np.flatnonzero(~snapped)
    if len(rest):
        size = float(np.median(sizes)) if len(sizes) else 4.0
        kps = [cv2.KeyPoint(float(x), float(y), size, 0.0) for x, y in k_work[rest]]
        kps_out, d_rest = sift.compute(gray_work, kps)
        if d_rest is None or len(kps_out) != len(kps):  # OpenCV dropped some: match them back by position
            got = {(round(p.pt[0], 3), round(p.pt[1], 3)): i for i, p in enumerate(kps_out)}
            for j, p in zip(rest, kps, strict=True):
                i = got.get((round(p.pt[0], 3), round(p.pt[1], 3)))
                if i is not None and d_rest is not None:
                    out[j] = d_rest[i]
        else:
            out[rest] = d_rest
    return colmap_sift_u8(out), DescriptorStats(int(snapped.sum()), int(len(rest)))
