"""COLMAP's covariant SIFT (affine shape estimation + domain-size pooling) through pycolmap, as
`Features` in this package's conventions.

What COLMAP's `high` preset extracts (`recon.eval.stock`): VLFeat's SIFT with
`estimate_affine_shape` (each keypoint's elliptical support adapted to the local structure) and
`domain_size_pooling` (descriptors pooled over several support sizes), COLMAP's other defaults
(first octave -1, peak threshold 0.0067, which is about OpenCV's contrast 0.02, not its 0.04).

Conventions, converted here (measured on rendered Gaussian blobs, tests/test_colmap_sift.py):

* position: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), this package (OpenCV) at
  (0, 0), so x_cv = x_colmap - 0.5. (OpenCV's own SIFT reports keypoints about +0.25 px off in
  x and y: it doubles the image with a half-pixel shift unless `enable_precise_upscale`; COLMAP's
  are unbiased.)
* size: OpenCV's `KeyPoint.size` is a diameter, about 2x COLMAP's scale (sigma), so size = 2 * scale;
  angle: degrees of COLMAP's orientation (radians, same y-down sense as OpenCV's), in [0, 360).
  The affine shape itself is not kept (`Features` has no field for it; nothing downstream uses it).
* descriptors: COLMAP's L1-root normalisation (RootSIFT, unit L2 norm), returned by COLMAP as
  uint8 of the unit descriptor x 512; here float at L2 norm 512, the scale of OpenCV's SIFT and
  of `DetectorConfig.root_sift`, so ratio tests and descriptor distances keep their meaning.
  They are NOT comparable with OpenCV's descriptors (affine adaptation and domain-size pooling
  change them: graf 1-2, 21 correct matches across the two against 1737 within COLMAP's), so they
  are only matched against features of this same detector (`fine.FineConfig.original_detector`).

pycolmap holds the GIL while it extracts (a covariant extraction of an 800x600 image takes a few
seconds), and the extractor is created per call; calls are serialised by the caller's SIFT gate
(`matching.features.detect`). pycolmap is imported on first use, after cv2 (importing it first
breaks OpenCV's PNG writes).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

UNLIMITED = 1 << 20
"""COLMAP's feature budget when `max_features` is 0 (COLMAP needs a positive number;
its own default is 8192)."""
DESCRIPTOR_SCALE = 512.0
"""Unit-norm descriptors times this = OpenCV SIFT's L2 scale."""


def extraction_options(max_features: int = 0):  # -> pycolmap.FeatureExtractionOptions
    """COLMAP's CPU SIFT options: affine shape and domain-size pooling on, L1-root descriptors, at
    most `max_features` (0 = unlimited), no downscaling (callers pass the working-resolution image)."""
    import cv2  # noqa: F401  (cv2 before pycolmap: see the module doc)
    import pycolmap

    o = pycolmap.FeatureExtractionOptions()
    o.use_gpu = False
    o.num_threads = 1
    o.max_image_size = UNLIMITED  # never downscale here
    o.sift.max_num_features = int(max_features) if max_features else UNLIMITED
    o.sift.estimate_affine_shape = True
    o.sift.domain_size_pooling = True
    o.sift.normalization = pycolmap.Normalization.L1_ROOT
    return o


Frames = tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]
"""(keypoints (N, 2) px, sizes (N,) px, angles (N,) degrees, descriptors (N, 128) float32)."""


def detect_colmap_sift(img: NDArray[np.uint8], max_features: int = 0, mask: NDArray[np.uint8] | None = None) -> Frames:
    """COLMAP's covariant SIFT of `img` (8-bit gray), in OpenCV's pixel convention (see the module
    doc): keypoints, sizes, angles and descriptors, which `matching.features.detect` wraps as
    `Features` (this module does not import it: `features` imports this one). `mask` (uint8,
    nonzero = valid) keeps the keypoints whose nearest pixel is valid (COLMAP has no detection mask)."""
    import pycolmap

    gray = np.ascontiguousarray(img, dtype=np.uint8)
    if gray.ndim != 2:
        raise ValueError(f"colmap-sift: expected a gray image (H, W), got shape {gray.shape}")
    extractor = pycolmap.FeatureExtractor.create(extraction_options(max_features), pycolmap.Device.cpu)
    kps, descs = extractor.extract_from_uint8_array(gray)
    frames = np.asarray(pycolmap.keypoints_to_matrix(kps), np.float32).reshape(-1, 4)  # x, y, scale, orientation
    # COLMAP stores unit-norm descriptors x 512 as uint8 (no component reaches 255 after L1-root);
    # renormalise the rounded values to exactly OpenCV's L2 scale
    desc = np.asarray(descs.data, np.float32).reshape(len(frames), -1) if len(frames) else np.zeros((0, 128), np.float32)
    desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12) * DESCRIPTOR_SCALE
    kpts = (frames[:, :2] - 0.5).astype(np.float32)
    keep = np.ones(len(frames), bool)
    if mask is not None and len(frames):
        h, w = mask.shape[:2]
        xy = np.clip(np.rint(kpts).astype(np.int64), 0, [w - 1, h - 1])
        keep = mask[xy[:, 1], xy[:, 0]] > 0
    return (kpts[keep], (2.0 * frames[keep, 2]).astype(np.float32),
            np.mod(np.degrees(frames[keep, 3]), 360.0).astype(np.float32),
            np.ascontiguousarray(desc[keep], np.float32))
