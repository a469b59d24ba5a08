"""Drawing matches: the two images side by side, inliers green, outliers red (cv2.drawMatches),
with an optional legend band on top: colours, counts and how many of the lines are drawn."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.types import PairResult

INLIER_BGR = (60, 220, 60)
OUTLIER_BGR = (40, 40, 230)


def sample_matches(n: int, max_lines: int, seed: int = 0) -> NDArray[np.int64]:
    """Indices of the matches to draw: all of them, or a seeded sorted subsample of `max_lines`."""
    idx = np.arange(n)
    if n > max_lines:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_lines, replace=False))
    return idx


def legend_text(result: PairResult, shown: int) -> str:
    """"inliers 250 (green)  outliers 50 (red)  lines: 200 of 300" for the legend band."""
    n = result.num_matches
    n_in = int(result.inlier_mask.sum()) if result.inlier_mask is not None else n
    text = f"inliers {n_in} (green)   outliers {n - n_in} (red)"
    return text + (f"   lines: {shown} of {n} (sampled)" if shown < n else f"   lines: all {n}")


def add_legend(canvas: NDArray[np.uint8], text: str) -> NDArray[np.uint8]:
    """`canvas` with a dark band on top holding `text` (height and font scale with the width)."""
    w = canvas.shape[1]
    scale = max(0.4, min(1.2, w / 1400))
    band_h = int(round(34 * scale)) + 8
    band = np.full((band_h, w, 3), 30, np.uint8)
    x = 8
    for part, color in _legend_parts(text):
        cv2.putText(band, part, (x, band_h - int(12 * scale) - 2), cv2.FONT_HERSHEY_SIMPLEX, scale, color,
                    max(1, round(scale * 2)), cv2.LINE_AA)
        x += cv2.getTextSize(part, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, round(scale * 2)))[0][0]
    return np.vstack([band, canvas])


def _legend_parts(text: str) -> list[tuple[str, tuple[int, int, int]]]:
    """The legend text cut into coloured pieces: the inlier part green, the outlier part red."""
    head, _, tail = text.partition("   outliers")
    out, _, lines = ("outliers" + tail).partition("   lines")
    parts = [(head + "   ", INLIER_BGR), (out + "   ", OUTLIER_BGR)]
    return parts + ([("lines" + lines, (230, 230, 230))] if lines else [])


def draw_matches(img0: NDArray[np.uint8], img1: NDArray[np.uint8], result: PairResult,
                 max_lines: int = 400, seed: int = 0, legend: bool = False) -> NDArray[np.uint8]:
    """A BGR canvas with image 0 left, image 1 right and one line per match (cv2.drawMatches).

    Inliers (of the result's homography, or all matches when none was fitted) are green,
    outliers red, drawn first so inliers stay on top; at most `max_lines` lines, a seeded
    subsample, so dense results stay legible. The canvas is max(h0, h1) x (w0 + w1), as
    cv2.drawMatches lays it out; lines are max(1, round(h / 800)) px thick. With `legend`, a
    band on top names the colours and gives the counts and how many lines are drawn.
    """
    def bgr(im: NDArray) -> NDArray[np.uint8]:
        return cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) if im.ndim == 2 else im

    a, b = bgr(img0), bgr(img1)
    h = max(a.shape[0], b.shape[0])
    n = result.num_matches
    idx = sample_matches(n, max_lines, seed)
    inl = (result.inlier_mask if result.inlier_mask is not None else np.ones(n, bool))[idx]
    kp0 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in result.kpts0[result.matches[idx, 0]]] if n else []
    kp1 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in result.kpts1[result.matches[idx, 1]]] if n else []
    dm = [cv2.DMatch(k, k, 0.0) for k in range(len(idx))]
    thick = max(1, round(h / 800))
    flags = cv2.DrawMatchesFlags_NOT_DRAW_SINGLE_POINTS
    canvas: Any = None
    for ok, color in ((False, OUTLIER_BGR), (True, INLIER_BGR)):  # outliers first, inliers on top
        mask = (inl == ok).astype(np.uint8).tolist()
        canvas = cv2.drawMatches(a, kp0, b, kp1, dm, canvas, thick, matchColor=color, singlePointColor=color,
                                 matchesMask=mask, flags=flags if canvas is None
                                 else flags | cv2.DrawMatchesFlags_DRAW_OVER_OUTIMG)
    return add_legend(canvas, legend_text(result, len(idx))) if legend else canvas


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
