"""Keypoint detection and description (SIFT, ORB, COLMAP's covariant SIFT) with a typed config.

`Features` holds keypoints in the pixel frame of the image they were computed on (OpenCV
convention); callers map them to original-image coordinates (see `matching.views`).
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .matching_utils import KdForest

FOREST_BUDGET_BYTES = 512 << 20
"""Memory the shared k-d forests of all `Features` may hold (least recently used dropped first):
enough for about 50 originals of 15k SIFT descriptors, the whole of a 30-image scene at 1600 px;
a forest dropped is rebuilt on its next use, as every use built it before sharing."""
_FOREST_BYTES_PER_DESCRIPTOR = 700  # resident memory of a 4-tree forest, its data not counted (measured)
_FOREST_LOCK = threading.RLock()  # reentrant: a weakref callback may run inside a locked block
_FOREST_LRU: OrderedDict[tuple[int, int], tuple[weakref.ref, int]] = OrderedDict()
_forest_bytes = 0


def _forget_forest(key: tuple[int, int]) -> None:
    global _forest_bytes
    with _FOREST_LOCK:
        entry = _FOREST_LRU.pop(key, None)
        if entry is not None:
            _forest_bytes -= entry[1]
            owner = entry[0]()
            if owner is not None:
                owner.forests.pop(key[1], None)

DetectorName = Literal["sift", "orb", "colmap-sift", "colmap-sift-affine", "colmap-sift-plain"]
COLMAP_DETECTORS = ("colmap-sift", "colmap-sift-affine", "colmap-sift-plain")
"""The detectors computed by COLMAP (`matching.colmap_sift`), not OpenCV."""

OPENCV_SIFT_UPSCALE_SHIFT_PX = 0.25
"""How far OpenCV's SIFT (without `enable_precise_upscale`) places keypoints off the pixel-centre
frame, in x and in y, px of the detected image (`DetectorConfig.centre_keypoints`)."""


@dataclass(frozen=True)
class DetectorConfig:
    """Which detector and its budget."""

    name: DetectorName = "sift"
    """"sift" (OpenCV, float descriptors, L2), "orb" (binary, Hamming), "colmap-sift" (COLMAP's SIFT
    with affine shape estimation and domain-size pooling, `matching.colmap_sift`: RootSIFT float
    descriptors at OpenCV's L2 scale, comparable only with its own), "colmap-sift-affine" (the
    same without domain-size pooling: 40 % of its time) or "colmap-sift-plain" (neither: the
    keypoints and descriptors of COLMAP's default extraction, 25 % of "colmap-sift"'s time)."""
    max_features: int = 0
    """Feature budget; 0 = unlimited (SIFT and colmap-sift; ORB then keeps 1000)."""
    root_sift: bool = False
    """L1-normalise and square-root SIFT descriptors (Arandjelovic 2012); colmap-sift's always are."""
    contrast: float = 0.04
    """SIFT's contrast threshold (OpenCV's default 0.04; lower finds more, weaker keypoints); colmap-sift
    keeps COLMAP's peak threshold (0.0067, about OpenCV's 0.02)."""

    precise_upscale: bool = False
    """OpenCV SIFT only: `enable_precise_upscale` (its doubled first octave without the half-pixel
    shift that places keypoints 0.25 px off; docs/decisions.md)."""

    centre_keypoints: bool = True
    """OpenCV SIFT without `precise_upscale` only: subtract the 0.25 px its doubled first octave
    adds to every keypoint's x and y. OpenCV doubles the image with pixel corners aligned
    (x_up = 2 x + 0.5) but reports x_up / 2, so its keypoints sit +0.25 px off the pixel-centre
    frame that COLMAP's SIFT, the views' warps and the database use (measured on fountain_P11:
    +0.247 / +0.249 px against COLMAP's keypoints of the same image). Harmless within one pair
    (a constant shift the geometry absorbs), it is not where one image's observations mix
    detectors (the covariant originals and the views' SIFT in a scene) or views (the shift mapped
    back through a view of tilt t grows to 0.25 t px). Detections and descriptors are unchanged;
    False keeps OpenCV's positions (docs/decisions.md, "SIFT keypoints at pixel centres")."""

    dsp_scales: int = 10
    """colmap-sift only: the support sizes its domain-size pooling averages over (COLMAP's
    `dsp_num_scales`, default 10; fewer is cheaper: 5 takes 8.0 instead of 12.4 CPU s at 1600 px)."""

    @property
    def key(self) -> str:
        contrast = "" if self.contrast == 0.04 else f"c{self.contrast:g}"
        dsp = "" if self.dsp_scales == 10 or self.name != "colmap-sift" else f"d{self.dsp_scales}"
        precise = "p" if self.precise_upscale and self.name == "sift" else ""
        biased = "b" if self.shifted_by_upscale and not self.centre_keypoints else ""
        return f"{self.name}{self.max_features}{'r' if self.root_sift else ''}{contrast}{dsp}{precise}{biased}"

    @property
    def shifted_by_upscale(self) -> bool:
        """Whether the detector itself places keypoints +0.25 px off (OpenCV SIFT, plain upscale)."""
        return self.name == "sift" and not self.precise_upscale

    @property
    def norm(self) -> int:
        return cv2.NORM_HAMMING if self.name == "orb" else cv2.NORM_L2


@dataclass
class Features:
    """Keypoints (N, 2) float32 px, their size (px) and angle (deg), descriptors (N, D),
    detector responses (N,) and local affine frames (N, 2, 2; `matching.mser`), each None when
    unknown."""

    kpts: NDArray[np.float32]
    sizes: NDArray[np.float32]
    angles: NDArray[np.float32]
    descriptors: NDArray  # uint8 (ORB, 32 bytes) or float32 (SIFT, 128)
    responses: NDArray[np.float32] | None = None
    frames: NDArray[np.float64] | None = None
    forests: dict[int, KdForest] = field(default_factory=dict, init=False, repr=False, compare=False)
    """The k-d forests of these descriptors built so far, by seed (`forest`; not pickled)."""

    def __len__(self) -> int:
        return int(len(self.kpts))

    def forest(self, seed: int = 0) -> KdForest:
        """The FLANN k-d forest of these (float) descriptors for `seed`, built on first use and
        kept with them: an original's features live in the feature store, so every pair and view
        that searches them shares one forest (`matching_utils.KdForest`). Thread-safe."""
        global _forest_bytes
        key = (id(self), int(seed))
        with _FOREST_LOCK:
            forest = self.forests.get(int(seed))
            if forest is not None:
                _FOREST_LRU.move_to_end(key)
                return forest
            forest = self.forests[int(seed)] = KdForest(self.descriptors, seed)
            size = len(self) * _FOREST_BYTES_PER_DESCRIPTOR
            _FOREST_LRU[key] = (weakref.ref(self, lambda _: _forget_forest(key)), size)
            _forest_bytes += size
            while _forest_bytes > FOREST_BUDGET_BYTES and len(_FOREST_LRU) > 1:
                _forget_forest(next(iter(_FOREST_LRU)))
            return forest

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "forests": {}}  # an OpenCV index does not pickle; it is rebuilt on use

    def subset(self, keep: NDArray[np.bool_] | NDArray[np.intp]) -> Features:
        resp = None if self.responses is None else self.responses[keep]
        frames = None if self.frames is None else self.frames[keep]
        return Features(self.kpts[keep], self.sizes[keep], self.angles[keep], self.descriptors[keep], resp, frames)

    @property
    def nbytes(self) -> int:
        extra = 0 if self.frames is None else self.frames.nbytes
        return int(self.kpts.nbytes + self.sizes.nbytes + self.angles.nbytes + self.descriptors.nbytes + extra)

    @staticmethod
    def concat(parts: list[Features]) -> Features:
        """The features of `parts` one after the other (non-empty list); responses and frames are
        kept when every part has them."""
        resp = None if any(p.responses is None for p in parts) else np.concatenate([p.responses for p in parts])
        frames = None if any(p.frames is None for p in parts) else np.concatenate([p.frames for p in parts])
        return Features(np.concatenate([p.kpts for p in parts]), np.concatenate([p.sizes for p in parts]),
                        np.concatenate([p.angles for p in parts]), np.concatenate([p.descriptors for p in parts]),
                        resp, frames)

    @staticmethod
    def empty(dim: int = 128, dtype=np.float32) -> Features:
        return Features(np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                        np.zeros(0, np.float32), np.zeros((0, dim), dtype))


def strongest(f: Features, n: int) -> Features:
    """The `n` features with the largest detector response (all of them when n = 0), in their
    original order (the first `n` when responses are unknown)."""
    if not n or len(f) <= n:
        return f
    if f.responses is None:
        return f.subset(np.arange(n))
    return f.subset(np.sort(np.argsort(-f.responses, kind="stable")[:n]))


def make_detector(cfg: DetectorConfig) -> cv2.Feature2D:
    """A fresh OpenCV detector (they are not thread-safe to share, so one per call); colmap-sift
    has none (`detect` calls `matching.colmap_sift`)."""
    if cfg.name == "sift":
        return cv2.SIFT.create(nfeatures=cfg.max_features, contrastThreshold=cfg.contrast,
                               enable_precise_upscale=bool(cfg.precise_upscale))
    if cfg.name == "orb":
        # fastThreshold lowered from 20 so low-contrast simulated views still yield keypoints
        return cv2.ORB.create(nfeatures=cfg.max_features or 1000, fastThreshold=10)
    if cfg.name in COLMAP_DETECTORS:
        raise ValueError(f"{cfg.name} is not an OpenCV detector: call matching.features.detect")
    raise ValueError(f"unknown detector {cfg.name!r}; choose 'sift', 'orb' or one of {', '.join(COLMAP_DETECTORS)}")


SIFT_PIXEL_BUDGET = 1_200_000
"""Input pixels that the OpenCV SIFT detections running at once in this process may add up to
(one detection is always admitted, whatever its size): two 800x640 images or views (1.02 Mpx)
run side by side, a 1024x768 image or a 1600 px photo runs alone. OpenCV's SIFT doubles its
input and keeps ~11 float layers of it (~235 bytes per input pixel: ~120 MB at 800x640, ~400 MB
at 1600x1067), so the budget bounds that working memory to about 280 MB. It is multi-threaded
inside, but its serial parts leave the second core idle: with the target's detection started
during the coarse search (`matcher.prefetch_originals`) and the fine views detected side by
side, graf's pairs take 0.62-0.84 s instead of 0.71-1.01 s (1.6 Mpx, three at once, measured
the same; docs/decisions.md, "SIFT detections side by side within a pixel budget")."""


class PixelGate:
    """Admits work while the pixels of the work running stay within `budget_px`; one piece is
    always admitted, so no input is refused however large. Thread-safe."""

    def __init__(self, budget_px: int):
        self.budget_px = max(0, int(budget_px))
        self._used = 0
        self._running = 0
        self._cond = threading.Condition()

    @contextmanager
    def hold(self, pixels: int) -> Iterator[None]:
        """Run the `with` block once `pixels` more fit the budget (or nothing else runs)."""
        px = max(0, int(pixels))
        with self._cond:
            while self._running and self._used + px > self.budget_px:
                self._cond.wait()
            self._used += px
            self._running += 1
        try:
            yield
        finally:
            with self._cond:
                self._used -= px
                self._running -= 1
                self._cond.notify_all()


_sift_gate = PixelGate(SIFT_PIXEL_BUDGET)


def set_sift_pixel_budget(pixels: int) -> None:
    """How many input pixels the SIFT detections running at once may add up to (default
    `SIFT_PIXEL_BUDGET`; 0 = one detection at a time, as before 2026-12-06). Detections already
    running finish under the gate they entered."""
    global _sift_gate
    _sift_gate = PixelGate(pixels)


def detect(img: NDArray[np.uint8], cfg: DetectorConfig, mask: NDArray[np.uint8] | None = None) -> Features:
    """Detect and describe `img` (8-bit gray). `mask` (uint8, nonzero = valid) limits detection."""
    if cfg.name in COLMAP_DETECTORS:
        from .colmap_sift import detect_colmap_sift

        # no SIFT gate: detect_colmap_sift runs one at a time in this process (pycolmap holds the
        # GIL), or side by side in child processes (`colmap_sift.extraction_processes`)
        kpts, sizes, angles, desc = detect_colmap_sift(img, cfg.max_features, mask,
                                                       pooling=cfg.name == "colmap-sift", dsp_scales=cfg.dsp_scales,
                                                       affine=cfg.name != "colmap-sift-plain")
        return Features(kpts, sizes, angles, desc) if len(kpts) else Features.empty(128, np.float32)
    det = make_detector(cfg)
    if cfg.name == "sift":
        with _sift_gate.hold(img.shape[0] * img.shape[1]):
            kps, desc = det.detectAndCompute(img, mask)
    else:
        kps, desc = det.detectAndCompute(img, mask)
    f = from_keypoints(kps, desc, 32 if cfg.name == "orb" else 128, np.uint8 if cfg.name == "orb" else np.float32)
    if cfg.shifted_by_upscale and cfg.centre_keypoints and len(f):
        f.kpts -= np.float32(OPENCV_SIFT_UPSCALE_SHIFT_PX)
    if cfg.name == "sift" and cfg.root_sift and len(f):
        d = f.descriptors / np.maximum(f.descriptors.sum(axis=1, keepdims=True), 1e-7)
        f.descriptors = np.sqrt(d) * 512.0  # keep OpenCV's L2 scale (~512) for Eq. 1 and ratios
    return f


def from_keypoints(kps, desc, dim: int, dtype) -> Features:
    """Features from OpenCV's keypoints and descriptors (empty, of `dim` x `dtype`, when none)."""
    if desc is None or not kps:
        return Features.empty(dim, dtype)
    return Features(
        np.array([k.pt for k in kps], np.float32).reshape(-1, 2),
        np.array([k.size for k in kps], np.float32),
        np.array([k.angle for k in kps], np.float32),
        np.ascontiguousarray(desc.astype(dtype, copy=False)),
        np.array([k.response for k in kps], np.float32),
    )
