"""Drawing matches: the two images side by side, inliers green, outliers red (cv2.drawMatches)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.types import PairResult


INLIER_BGR = (60, 220, 60)
OUTLIER_BGR = (40, 40, 230)


def draw_matches(img0: NDArray[np.uint8], img1: NDArray[np.uint8], result: PairResult,
                 max_lines: int = 400, seed: int = 0) -> NDArray[np.uint8]:
    """A BGR canvas with image 0 left, image 1 right and one line per match (cv2.drawMatches).

    Inliers (of the result's homography, or all matches when none was fitted) are green,
    outliers red, drawn first so inliers stay on top; at most `max_lines` lines, a seeded
    subsample, so dense results stay legible. The canvas is max(h0, h1) x (w0 + w1), as
    cv2.drawMatches lays it out; lines are max(1, round(h / 800)) px thick.
    """
    def bgr(im: NDArray) -> NDArray[np.uint8]:
        return cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) if im.ndim == 2 else im

    a, b = bgr(img0), bgr(img1)
    h = max(a.shape[0], b.shape[0])
    n = result.num_matches
    idx = np.arange(n)
    if n > max_lines:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_lines, replace=False))
    inl = (result.inlier_mask if result.inlier_mask is not None else np.ones(n, bool))[idx]
    kp0 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in result.kpts0[result.matches[idx, 0]]] if n else []
    kp1 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in result.kpts1[result.matches[idx, 1]]] if n else []
    dm = [cv2.DMatch(k, k, 0.0) for k in range(len(idx))]
    thick = max(1, round(h / 800))
    flags = cv2.DrawMatchesFlags_NOT_DRAW_SINGLE_POINTS
    canvas = None
    for ok, color in ((False, OUTLIER_BGR), (True, INLIER_BGR)):  # outliers first, inliers on top
        mask = (inl == ok).astype(np.uint8).tolist()
        canvas = cv2.drawMatches(a, kp0, b, kp1, dm, canvas, thick, matchColor=color, singlePointColor=color,
                                 matchesMask=mask, flags=flags if canvas is None
                                 else flags | cv2.DrawMatchesFlags_DRAW_OVER_OUTIMG)
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
