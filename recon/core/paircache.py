"""The per-pair result cache: `OUT/cache/pairs/<key>.npz`, one atomic file per matched pair.

A pair's key hashes the matcher's identity (its config, thread counts left out), both images'
pixel digests and working sizes, so a changed image or option never reuses a stale result.
Results are stored in full-resolution pixels, keeping only matched keypoints (compact). A
damaged or older-version file is recomputed, never trusted. A failed write (a full disk,
Ctrl-C) removes its temporary file and raises an OSError naming the cache file, so the run
stops with "no space left on device writing PATH" instead of reporting pairs as failed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import threading
from pathlib import Path

import numpy as np

from matching.types import CoarseScore, PairResult, ViewParams
from recon.core.jsonio import replaced_atomically
from recon.core.scene import SceneImage

# 2: OpenCV SIFT keypoints at pixel centres (matching.features.DetectorConfig.centre_keypoints);
# 3: one warp for the views with phi = 0 (matching.views.FUSED_AXIS_WARP)
PAIR_CACHE_VERSION = "3"


def result_to_full_res(r: PairResult, im0: SceneImage, im1: SceneImage) -> PairResult:
    """The same result in full-resolution pixels (`PairResult.in_original_frame`), keeping only
    matched keypoints (compact)."""
    m = np.asarray(r.matches, np.int64).reshape(-1, 2)
    used0 = np.unique(m[:, 0]) if len(m) else np.zeros(0, np.int64)
    used1 = np.unique(m[:, 1]) if len(m) else np.zeros(0, np.int64)
    mm = (np.stack([np.searchsorted(used0, m[:, 0]), np.searchsorted(used1, m[:, 1])], 1).astype(np.int32)
          if len(m) else np.zeros((0, 2), np.int32))
    compact = dataclasses.replace(r, kpts0=np.asarray(r.kpts0).reshape(-1, 2)[used0],
                                  kpts1=np.asarray(r.kpts1).reshape(-1, 2)[used1], matches=mm,
                                  distances=np.asarray(r.distances, np.float32).reshape(-1),
                                  best_views=list(r.best_views))
    return compact.in_original_frame(((im0.work_width, im0.work_height), (im1.work_width, im1.work_height)),
                                     ((im0.width, im0.height), (im1.width, im1.height)))


def save_pair_result(path: Path, r: PairResult) -> None:
    """Atomic .npz of a (full-resolution, compact) PairResult (see module doc for failures)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    views = np.array([[v.t, v.phi, v.s] for v in r.best_views], np.float64).reshape(-1, 3)
    coarse = np.array([[c.view.t, c.view.phi, c.view.s, c.matches, c.inliers, c.score]
                       for c in r.coarse_scores], np.float64).reshape(-1, 6)
    meta = dict(method=r.method, reference=r.reference, reference_reason=r.reference_reason,
                f0=r.f0, f1=r.f1, escalation=r.escalation, reason=r.reason, timings=r.timings,
                path=r.path, path_reason=r.path_reason, planned_path=r.planned_path, verified=r.verified,
                finishing=r.finishing, image_sizes=r.image_sizes, version=PAIR_CACHE_VERSION)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.npz")
    with replaced_atomically(path, tmp):
        np.savez(tmp, kpts0=np.asarray(r.kpts0, np.float32), kpts1=np.asarray(r.kpts1, np.float32),
                 matches=np.asarray(r.matches, np.int32), distances=np.asarray(r.distances, np.float32),
                 views=views, coarse=coarse,
                 H=(np.zeros((0, 3)) if r.H_1_from_0 is None else np.asarray(r.H_1_from_0)),
                 inlier_mask=(np.zeros(0, bool) if r.inlier_mask is None else np.asarray(r.inlier_mask, bool)),
                 has_mask=np.array(r.inlier_mask is not None), meta=np.array(json.dumps(meta)))


def load_pair_result(path: Path) -> PairResult | None:
    """The cached PairResult, or None when absent or unreadable (then it is recomputed)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("version") != PAIR_CACHE_VERSION:
                return None
            H = z["H"]
            sizes = meta.get("image_sizes")
            return PairResult(
                method=meta["method"], kpts0=z["kpts0"], kpts1=z["kpts1"], matches=z["matches"],
                distances=z["distances"], reference=meta.get("reference"),
                reference_reason=meta.get("reference_reason", ""), f0=meta.get("f0"), f1=meta.get("f1"),
                best_views=[ViewParams(float(t), float(p), float(s)) for t, p, s in z["views"]],
                coarse_scores=[CoarseScore(ViewParams(float(t), float(p), float(s)), int(m), int(i), float(sc))
                               for t, p, s, m, i, sc in (z["coarse"] if "coarse" in z.files else [])],
                H_1_from_0=H if H.shape == (3, 3) else None,
                inlier_mask=z["inlier_mask"] if bool(z["has_mask"]) else None,
                escalation=meta.get("escalation", ""), reason=meta.get("reason", ""),
                path=meta.get("path", ""), path_reason=meta.get("path_reason", ""),
                planned_path=meta.get("planned_path", ""), verified=int(meta.get("verified", -1)),
                finishing=meta.get("finishing", ""), timings=meta.get("timings", {}),
                image_sizes=tuple(tuple(s) for s in sizes) if sizes else None,  # type: ignore[arg-type]
            )
    except Exception:  # a damaged cache file is recomputed, never trusted
        return None


def pair_cache_key(matcher_id: str, im0: SceneImage, im1: SceneImage) -> str:
    h = hashlib.sha1()
    for part in (PAIR_CACHE_VERSION, matcher_id, im0.digest, f"{im0.work_width}x{im0.work_height}",
                 im1.digest, f"{im1.work_width}x{im1.work_height}"):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:24]
