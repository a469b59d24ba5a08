"""Drawing matches: the two images side by side, inliers green, outliers red."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.types import PairResult


def draw_matches(img0: NDArray[np.uint8], img1: NDArray[np.uint8], result: PairResult,
                 max_lines: int = 400, seed: int = 0) -> NDArray[np.uint8]:
    """A BGR canvas with image 0 left, image 1 right and one line per match.

    Inliers (of the result's homography, or all matches when none was fitted) are green,
    outliers red; at most `max_lines` lines, a seeded subsample, so dense results stay legible.
    """
    def bgr(im: NDArray) -> NDArray[np.uint8]:
        return cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) if im.ndim == 2 else im

    a, b = bgr(img0), bgr(img1)
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1]:] = b
    if result.num_matches == 0:
        return canvas
    inl = result.inlier_mask if result.inlier_mask is not None else np.ones(result.num_matches, bool)
    idx = np.arange(result.num_matches)
    if len(idx) > max_lines:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_lines, replace=False))
    p0 = result.kpts0[result.matches[idx, 0]]
    p1 = result.kpts1[result.matches[idx, 1]] + np.array([a.shape[1], 0], np.float32)
    thick = max(1, round(h / 800))
    for ok in (False, True):  # outliers first, inliers drawn on top
        color = (60, 220, 60) if ok else (40, 40, 230)
        for q0, q1 in zip(p0[inl[idx] == ok], p1[inl[idx] == ok]):
            x0, y0 = (int(round(v)) for v in q0)
            x1, y1 = (int(round(v)) for v in q1)
            cv2.line(canvas, (x0, y0), (x1, y1), color, thick, cv2.LINE_AA)
            cv2.circle(canvas, (x0, y0), 2 * thick, color, -1, cv2.LINE_AA)
            cv2.circle(canvas, (x1, y1), 2 * thick, color, -1, cv2.LINE_AA)
    return canvas


def write_image_atomic(path: str | Path, img: NDArray[np.uint8]) -> None:
    """Encode by the file's extension and move into place (no half-written file on a kill)."""
    path = Path(path)
    ext = path.suffix.lower() or ".png"
    ok, buf = cv2.imencode(ext, img)
    if not ok:
        raise ValueError(f"{path}: cannot encode an image with extension {ext!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_bytes(buf.tobytes())
        os.replace(tmp, path)
    except BaseException as e:  # a full disk or Ctrl-C: no temporary file left behind
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError) and e.filename is None:
            e.filename = str(path)
        raise
