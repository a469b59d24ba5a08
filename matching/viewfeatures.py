"""Features of an image's original and of its simulated views, cached in the FeatureStore.

Every keypoint here is in *original-image* pixels (OpenCV convention): a view's keypoints are
detected in the warped image and mapped back with the view's affine, so features of different
views of one image (and of every pair the image is in) live in one frame and are cached once
per (image, detector, view, interpolation) key. The coarse search, the fine stage, the guided
rounds and the escalation levels all read features through these functions.
"""

from __future__ import annotations

from concurrent.futures import Executor

import cv2
import numpy as np
from numpy.typing import NDArray

from .features import DetectorConfig, Features, detect
from .store import FeatureStore
from .types import ViewParams
from .views import Interp, map_to_original, simulate


def original_features(store: FeatureStore, name: str, det: DetectorConfig) -> Features:
    """Features of the unwarped image (cached as `<det>@orig`)."""
    return store.get_or_compute(name, f"{det.key}@orig", lambda: detect(store.image(name), det))


def decision_features(store: FeatureStore, name: str, det: DetectorConfig, scale: float) -> Features:
    """Features of the original downscaled by `scale` (area interpolation; cached as
    `<det>@orig_x<scale>`), keypoints and sizes in full-resolution pixels (pixel-centre frame:
    x = (x_small + 0.5) / f - 0.5 per axis, f the exact ratio of the rounded sizes). `scale` >= 1
    is `original_features`. For the reference decision (`ReferenceConfig.decision_scale`)."""
    if scale >= 1.0:
        return original_features(store, name, det)

    def compute() -> Features:
        img = store.image(name)
        h, w = img.shape[:2]
        ws, hs = max(1, round(w * scale)), max(1, round(h * scale))
        f = detect(cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA), det)
        factor = np.array([ws / w, hs / h], np.float32)
        f.kpts = ((f.kpts + 0.5) / factor - 0.5).astype(np.float32)
        f.sizes = (f.sizes / float(np.sqrt(factor[0] * factor[1]))).astype(np.float32)
        return f

    return store.get_or_compute(name, f"{det.key}@orig_x{scale:g}", compute)


def away_from_canvas_edge(kpts_view: NDArray, sizes: NDArray, mask: NDArray,
                          size_factor: float = 0.5) -> NDArray[np.bool_]:
    """Keypoints (in view pixels) whose support region stays inside the warped image.

    The warped original sits on a black canvas; its edge is a strong artificial contrast that
    SIFT and ORB fire on at every scale, producing keypoints that match other views' edges.
    A keypoint is kept when its distance to the canvas is over `size_factor` x its size
    (its support diameter in px); `kpts_view` are view pixels.
    """
    dist = cv2.distanceTransform((mask > 0).astype(np.uint8), cv2.DIST_L2, 3)
    h, w = mask.shape
    xy = np.clip(np.rint(kpts_view).astype(np.int64), 0, [w - 1, h - 1])
    return dist[xy[:, 1], xy[:, 0]] > np.maximum(3.0, size_factor * sizes)


def view_features(store: FeatureStore, name: str, view: ViewParams, det: DetectorConfig,
                  interp: Interp, antialias: bool) -> Features:
    """Features of one simulated view, keypoints mapped back to the original image frame.

    Keypoints that map outside the original, or sit on the canvas edge, are dropped. The
    identity view is the original (`original_features`).
    """
    if view.is_identity:
        return original_features(store, name, det)
    key = f"{det.key}@{view.key}_{interp}{'_aa' if antialias else ''}"

    def compute() -> Features:
        img = store.image(name)
        sv = simulate(img, view, interp, antialias)
        f = detect(sv.image, det, sv.mask)
        keep = away_from_canvas_edge(f.kpts, f.sizes, sv.mask)
        kpts, inside = map_to_original(f.kpts, sv.A_view_from_orig, (img.shape[1], img.shape[0]))
        f.kpts = kpts
        return f.subset(inside & keep)

    return store.get_or_compute(name, key, compute)


def pooled_features(store: FeatureStore, name: str, views: list[ViewParams], det: DetectorConfig,
                    interp: Interp, pool: Executor | None) -> tuple[Features, NDArray[np.int32]]:
    """All `views`' features of one image (anti-aliased), keypoints in the original frame, and
    each feature's view index; the views run on `pool` when given."""
    def one(v: ViewParams) -> Features:
        return view_features(store, name, v, det, interp, True)

    parts = list(pool.map(one, views)) if pool is not None else [one(v) for v in views]
    view_idx = np.concatenate([np.full(len(f), i, np.int32) for i, f in enumerate(parts)])
    return Features.concat(parts), view_idx
