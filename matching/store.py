"""FeatureStore: per-image features computed once and shared by every pair the image is in.

Entries are keyed by (image name, what was computed), e.g. ("a.jpg", "orb1000@t2.000_p36.00_s2.00_nn").
`get_or_compute` is thread-safe and computes each key exactly once even when several pair tasks
ask for it at the same moment (a per-key lock), so pairs can run in a thread pool. With a
`cache_dir`, entries also persist as `.npz` files named by a hash of the image content and the
key, so an interrupted run resumes without recomputing; files are written to a temporary name
and renamed, so a kill never leaves a half-written cache entry.

The disk cache is an optimisation, never a reason for a pair to fail: when a write fails (a full
disk, a read-only cache folder) the temporary file is removed, the error is kept in
`persist_error` and later entries stay in memory only. (The caller's own writes, e.g. the
pipeline's pair cache, then report the full disk and stop the run.)
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .features import Features

CACHE_VERSION = "3"
"""Part of every disk cache entry's name and stored key; bumped when what a key computes changes
(2: OpenCV SIFT keypoints at pixel centres, `DetectorConfig.centre_keypoints`; 3: a view with
phi = 0 blurred on the original and warped once, `views.FUSED_AXIS_WARP`), so entries of an
older version are recomputed, never reused."""


class FeatureStore:
    """Images by name and everything computed from them, computed once."""

    def __init__(self, cache_dir: str | Path | None = None):
        self.cache_dir = Path(cache_dir) if cache_dir else None
        if self.cache_dir:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
        self._images: dict[str, NDArray[np.uint8]] = {}
        self._digests: dict[str, str] = {}
        self._entries: dict[tuple[str, str], object] = {}
        self._locks: dict[tuple[str, str], threading.Lock] = {}
        self._guard = threading.Lock()
        self.hits = 0
        self.misses = 0
        self.persist_error: OSError | None = None  # the first failed cache write (persisting then stops)

    # images -------------------------------------------------------------------------------
    def add_image(self, name: str, gray: NDArray[np.uint8]) -> None:
        """Register an 8-bit gray image under `name` (replacing one of the same name)."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"{name}: FeatureStore expects 8-bit gray images")
        with self._guard:
            self._images[name] = gray
            self._digests[name] = hashlib.sha1(gray.tobytes() + str(gray.shape).encode()).hexdigest()[:16]
            for k in [k for k in self._entries if k[0] == name]:
                del self._entries[k]

    def image(self, name: str) -> NDArray[np.uint8]:
        return self._images[name]

    def __contains__(self, name: str) -> bool:
        return name in self._images

    @property
    def names(self) -> list[str]:
        return list(self._images)

    def drop_image(self, name: str) -> None:
        """Forget an image and its in-memory entries (disk cache is kept)."""
        with self._guard:
            self._images.pop(name, None)
            for k in [k for k in self._entries if k[0] == name]:
                del self._entries[k]

    # entries ------------------------------------------------------------------------------
    def keys(self, name: str) -> list[str]:
        """The keys of `name`'s entries held in memory (what has been computed or loaded)."""
        with self._guard:
            return [key for (n, key) in self._entries if n == name]

    def get_or_compute(self, name: str, key: str, compute: Callable[[], Features],
                       persist: bool = True) -> Features:
        """The entry (name, key), computing it with `compute()` only the first time."""
        k = (name, key)
        with self._guard:
            if k in self._entries:
                self.hits += 1
                return self._entries[k]  # type: ignore[return-value]
            lock = self._locks.setdefault(k, threading.Lock())
        with lock:
            with self._guard:
                if k in self._entries:
                    self.hits += 1
                    return self._entries[k]  # type: ignore[return-value]
            feats = self._load(name, key) if persist else None
            if feats is None:
                feats = compute()
                if persist:
                    self._save(name, key, feats)
                with self._guard:
                    self.misses += 1
            else:
                with self._guard:
                    self.hits += 1
            with self._guard:
                self._entries[k] = feats
            return feats

    def _path(self, name: str, key: str) -> Path | None:
        if self.cache_dir is None:
            return None
        digest = self._digests[name]
        h = hashlib.sha1(_versioned(key).encode()).hexdigest()[:12]
        return self.cache_dir / digest[:2] / f"{digest}_{h}.npz"

    def _load(self, name: str, key: str) -> Features | None:
        p = self._path(name, key)
        if p is None or not p.exists():
            return None
        try:
            with np.load(p) as z:
                if str(z["key"]) != _versioned(key):
                    return None
                resp = z["responses"] if "responses" in z.files else None
                frames = z["frames"] if "frames" in z.files else None
                return Features(z["kpts"], z["sizes"], z["angles"], z["descriptors"], resp, frames)
        except Exception:  # a damaged cache file is recomputed, never trusted
            return None

    def _save(self, name: str, key: str, f: Features) -> None:
        p = self._path(name, key)
        if p is None or self.persist_error is not None:
            return
        tmp = p.with_name(f"{p.stem}.{os.getpid()}.{threading.get_ident()}.tmp.npz")
        extra: dict[str, Any] = {} if f.responses is None else {"responses": f.responses}
        if f.frames is not None:
            extra["frames"] = f.frames
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            np.savez(tmp, key=np.array(_versioned(key)), kpts=f.kpts, sizes=f.sizes, angles=f.angles,
                     descriptors=f.descriptors, **extra)
            os.replace(tmp, p)
        except OSError as e:  # see module doc: keep computing in memory
            if e.filename is None:
                e.filename = str(p)
            with self._guard:
                if self.persist_error is None:
                    self.persist_error = e
        finally:
            if tmp.exists():
                try:
                    tmp.unlink()
                except OSError:
                    pass


def _versioned(key: str) -> str:
    """The key as stored on disk: `CACHE_VERSION`-prefixed."""
    return f"v{CACHE_VERSION}:{key}"
