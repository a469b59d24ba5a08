"""COLMAP's covariant SIFT (affine shape estimation + domain-size pooling) through pycolmap, as
`Features` in this package's conventions.

What COLMAP's `high` preset extracts (`recon.eval.stock`): VLFeat's SIFT with
`estimate_affine_shape` (each keypoint's elliptical support adapted to the local structure) and
`domain_size_pooling` (descriptors pooled over several support sizes), COLMAP's other defaults
(first octave -1, peak threshold 0.0067, which is about OpenCV's contrast 0.02, not its 0.04).

Conventions, converted here (measured on rendered Gaussian blobs, tests/test_colmap_sift.py):

* position: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), this package (OpenCV) at
  (0, 0), so x_cv = x_colmap - 0.5. (OpenCV's own SIFT reports keypoints about +0.25 px off in
  x and y: it doubles the image with a half-pixel shift unless `enable_precise_upscale`;
  `matching.features.detect` subtracts that shift, `DetectorConfig.centre_keypoints`; COLMAP's
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

pycolmap holds the GIL while it extracts (a covariant extraction takes about 3 CPU s on an 800x600
image, 12 s at 1600x1067, 7.5 of them domain-size pooling), so in-process calls run one at a time
and stall every other Python thread meanwhile: two threads extracting take twice one's time.
Inside `extraction_processes(n)` extractions run in `n` spawned child processes instead (the
`recon` match stage opens it for its pair threads): the caller's thread waits without the GIL,
`n` extractions run side by side, and the output is bit-identical (the same code, single-threaded
in the child). The extractor is created per call. pycolmap is imported on first use, after cv2
(importing it first breaks OpenCV's PNG writes).
"""

from __future__ import annotations

import multiprocessing
import signal
import sys
import threading
import weakref
from collections.abc import Iterator
from concurrent.futures import CancelledError, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager

import numpy as np
from numpy.typing import NDArray

UNLIMITED = 1 << 20
"""COLMAP's feature budget when `max_features` is 0 (COLMAP needs a positive number;
its own default is 8192)."""
DESCRIPTOR_SCALE = 512.0
"""Unit-norm descriptors times this = OpenCV SIFT's L2 scale."""


def extraction_options(max_features: int = 0, pooling: bool = True, dsp_scales: int = 10,
                       affine: bool = True):  # -> pycolmap.FeatureExtractionOptions
    """COLMAP's CPU SIFT options: affine shape (unless not `affine`) and domain-size pooling
    (unless not `pooling`) on, L1-root descriptors, at most `max_features` (0 = unlimited), no
    downscaling (callers pass the working-resolution image); pooling over `dsp_scales` support
    sizes (COLMAP's default 10). Neither = COLMAP's default extraction ("colmap-sift-plain")."""
    import cv2  # noqa: F401  (cv2 before pycolmap: see the module doc)
    import pycolmap

    o = pycolmap.FeatureExtractionOptions()
    o.use_gpu = False
    o.num_threads = 1
    o.max_image_size = UNLIMITED  # never downscale here
    o.sift.max_num_features = int(max_features) if max_features else UNLIMITED
    o.sift.estimate_affine_shape = bool(affine)
    o.sift.domain_size_pooling = bool(pooling)
    o.sift.dsp_num_scales = int(dsp_scales)
    o.sift.normalization = pycolmap.Normalization.L1_ROOT
    return o


Frames = tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]
"""(keypoints (N, 2) px, sizes (N,) px, angles (N,) degrees, descriptors (N, 128) float32)."""


_pool: ProcessPoolExecutor | None = None
_pool_guard = threading.Lock()
# Threads by object, not by `threading.get_ident()`: the interpreter reuses a finished thread's
# ident, so a later thread (a Dask worker's, the next run's) would inherit a stale mark
_users: weakref.WeakSet[threading.Thread] = weakref.WeakSet()  # threads that extracted through the open block's children
_abandoned: weakref.WeakSet[threading.Thread] = weakref.WeakSet()  # ...of a block that ended with an exception: they stop
_in_process = threading.Lock()  # in this process pycolmap holds the GIL: one extraction at a time


def _child_init(min_log_level: int | None) -> None:
    """A child of `extraction_processes`: Ctrl-C and SIGTERM are the parent's to handle (it kills
    the children when its block ends early), cv2 is imported before pycolmap (module doc), and
    COLMAP logs at the parent's level (`recon.log.quiet_colmap` keeps it to fatal messages)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import cv2  # noqa: F401
    import pycolmap

    if min_log_level is not None:
        pycolmap.logging.minloglevel = min_log_level


@contextmanager
def _signal_mask_kept() -> Iterator[None]:
    """Restore the calling thread's signal mask after the block. Python's multiprocessing starts
    its resource tracker the first time a spawn-context lock is made or a child is spawned, and
    then *unblocks* SIGINT and SIGTERM in the calling thread (`resource_tracker.ensure_running`);
    the `recon` program blocks SIGTERM in every thread (`recon._signals`), and a thread that
    lets it through hands it to the C failure handler pycolmap installs (a stack dump, exit -15)."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextmanager
def extraction_processes(n: int) -> Iterator[None]:
    """While the block runs, `detect_colmap_sift` extracts in `n` spawned child processes (see the
    module doc); n <= 0, a block already open, or a daemonic process (a Dask worker, which may not
    have children) keep extracting in this process. The children start on the first extraction;
    they are shut down when the block ends, and killed at once when it ends with an exception
    (Ctrl-C): the threads that were extracting through them then get `CancelledError` instead of
    extracting again in this process, so an interrupted run neither waits for nor repeats them."""
    global _pool
    with _pool_guard:
        own = n > 0 and _pool is None and not multiprocessing.current_process().daemon
        if own:
            _users.clear()
            _abandoned.clear()
            parent_colmap = sys.modules.get("pycolmap")
            level = int(parent_colmap.logging.minloglevel) if parent_colmap is not None else None
            with _signal_mask_kept():
                _pool = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_child_init, initargs=(level,))
        pool = _pool
    if not own:
        yield
        return
    assert pool is not None
    finished = False
    try:
        yield
        finished = True
    finally:
        with _pool_guard:
            _pool = None
            if not finished:
                _abandoned.update(_users)
        if not finished:
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                proc.kill()
        pool.shutdown(wait=finished, cancel_futures=True)


def detect_colmap_sift(img: NDArray[np.uint8], max_features: int = 0, mask: NDArray[np.uint8] | None = None,
                       pooling: bool = True, dsp_scales: int = 10, affine: bool = True) -> Frames:
    """COLMAP's covariant SIFT of `img` (8-bit gray), in OpenCV's pixel convention (see the module
    doc): keypoints, sizes, angles and descriptors, which `matching.features.detect` wraps as
    `Features` (this module does not import it: `features` imports this one). `mask` (uint8,
    nonzero = valid) keeps the keypoints whose nearest pixel is valid (COLMAP has no detection mask).
    Thread-safe: in a child process inside `extraction_processes`, else one at a time here (a
    child that dies takes the call back into this process)."""
    gray = np.ascontiguousarray(img, dtype=np.uint8)
    if gray.ndim != 2:
        raise ValueError(f"colmap-sift: expected a gray image (H, W), got shape {gray.shape}")
    me = threading.current_thread()
    with _pool_guard:
        pool = _pool
        if pool is not None:
            _users.add(me)
    if pool is not None:
        try:
            with _signal_mask_kept():  # the first submit spawns the children
                future = pool.submit(_extract, gray, max_features, mask, pooling, dsp_scales, affine)
            return future.result()
        except (BrokenProcessPool, RuntimeError, CancelledError):  # a dead child, or the block closing
            pass
    if me in _abandoned:
        raise CancelledError("covariant SIFT extraction abandoned: the run was interrupted")
    with _in_process:
        return _extract(gray, max_features, mask, pooling, dsp_scales, affine)


def _extract(gray: NDArray[np.uint8], max_features: int, mask: NDArray[np.uint8] | None, pooling: bool,
             dsp_scales: int, affine: bool = True) -> Frames:
    """`detect_colmap_sift`'s work, in whichever process runs it."""
    import pycolmap

    extractor = pycolmap.FeatureExtractor.create(extraction_options(max_features, pooling, dsp_scales, affine),
                                                 pycolmap.Device.cpu)
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
