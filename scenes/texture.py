"""Plane textures: a seeded procedural texture rich in multi-scale detail, or a user photo.

The procedural texture is built so that SIFT and ORB find many distinctive features at every
scale a rendered view can show it at, including after the 5-6x foreshortening of an 80 degree
viewing angle: smooth colour variation (metres), large and medium shapes (decimetres to metres),
text-like glyph strokes, small blobs and dots (centimetres) and fine pixel noise. Everything is
placed at random, never on a grid, so no two parts of a texture (nor two planes with different
seeds) look alike -- repetitive patterns would give ambiguous matches.

Sizes are in metres on the plane, converted with `px_per_m`; the result is an 8-bit BGR image
whose pixel (0, 0) is the top-left of the plane's bounding box (see `scenes.render`).
The same (size, px_per_m, seed) always gives the same bytes.
"""

from __future__ import annotations

import string
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.io import load_color

_GLYPHS = string.ascii_uppercase + string.digits + "#%&@"
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)


def _colour(rng: np.random.Generator) -> tuple[int, int, int]:
    """A random BGR colour whose luminance is spread over the whole 8-bit range (gray contrast)."""
    lum = rng.uniform(15, 240)
    chroma = rng.normal(0.0, 45.0, 3)
    c = np.clip(lum + chroma - chroma.mean(), 0, 255)
    return int(c[0]), int(c[1]), int(c[2])


def _smooth_field(rng: np.random.Generator, w: int, h: int, cells: int) -> NDArray[np.float32]:
    """A smooth random colour field (w x h x 3, float32, zero mean) with about `cells` bumps across."""
    gw, gh = max(2, cells), max(2, round(cells * h / max(w, 1)))
    grid = rng.normal(0.0, 1.0, (gh, gw, 3)).astype(np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def _shapes(img: NDArray, rng: np.random.Generator, count: int, size_px: tuple[float, float]) -> None:
    """Draw `count` random filled/outlined rectangles, ellipses, polygons and strokes in place."""
    h, w = img.shape[:2]
    lo, hi = size_px
    for _ in range(count):
        kind = rng.integers(0, 5)
        cx, cy = rng.uniform(-0.05 * w, 1.05 * w), rng.uniform(-0.05 * h, 1.05 * h)
        a = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        b = a * rng.uniform(0.25, 1.0)
        col = _colour(rng)
        thick = -1 if rng.random() < 0.6 else max(1, int(round(a * rng.uniform(0.04, 0.15))))
        ang = float(rng.uniform(0, 180))
        if kind == 0:  # rotated rectangle
            box = cv2.boxPoints(((cx, cy), (a, b), ang))
            pts = np.round(box * 16).astype(np.int32)
            if thick < 0:
                cv2.fillPoly(img, [pts], col, cv2.LINE_AA, shift=4)
            else:
                cv2.polylines(img, [pts], True, col, thick, cv2.LINE_AA, shift=4)
        elif kind == 1:  # ellipse
            cv2.ellipse(img, (int(cx * 16), int(cy * 16)), (int(a * 8), int(b * 8)), ang, 0, 360,
                        col, thick, cv2.LINE_AA, shift=4)
        elif kind == 2:  # random polygon (3-6 corners)
            n = int(rng.integers(3, 7))
            t = np.sort(rng.uniform(0, 2 * np.pi, n))
            r = a * rng.uniform(0.3, 0.6, n)
            pts = np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], 1)
            pts = np.round(pts * 16).astype(np.int32)
            if thick < 0:
                cv2.fillPoly(img, [pts], col, cv2.LINE_AA, shift=4)
            else:
                cv2.polylines(img, [pts], True, col, thick, cv2.LINE_AA, shift=4)
        elif kind == 3:  # stroke: a polyline with a few bends
            n = int(rng.integers(2, 5))
            steps = rng.normal(0, a * 0.5, (n, 2)).cumsum(0)
            pts = np.round((steps + [cx, cy]) * 16).astype(np.int32)
            cv2.polylines(img, [pts], False, col, max(1, int(round(a * rng.uniform(0.03, 0.1)))),
                          cv2.LINE_AA, shift=4)
        else:  # ring of dots or a single disc
            rad = max(1.0, b * 0.5)
            cv2.circle(img, (int(cx * 16), int(cy * 16)), int(rad * 16), col, thick, cv2.LINE_AA, shift=4)


def _glyphs(img: NDArray, rng: np.random.Generator, count: int, height_px: tuple[float, float]) -> None:
    """Draw `count` short random strings (text-like strokes) of glyph height in `height_px`."""
    h, w = img.shape[:2]
    for _ in range(count):
        text = "".join(rng.choice(list(_GLYPHS), int(rng.integers(1, 6))))
        font = _FONTS[int(rng.integers(0, len(_FONTS)))]
        gh = float(np.exp(rng.uniform(np.log(height_px[0]), np.log(height_px[1]))))
        base = cv2.getTextSize("H", font, 1.0, 1)[0][1]
        scale = gh / max(base, 1)
        thick = max(1, int(round(gh * rng.uniform(0.06, 0.16))))
        org = (int(rng.uniform(-0.05 * w, w)), int(rng.uniform(0, 1.05 * h)))
        cv2.putText(img, text, org, font, scale, _colour(rng), thick, cv2.LINE_AA)


def procedural_texture(width_m: float, height_m: float, px_per_m: float, seed: int) -> NDArray[np.uint8]:
    """A seeded multi-scale colour texture for a `width_m` x `height_m` plane (metres).

    The image is round(width_m * px_per_m) x round(height_m * px_per_m) px, 8-bit BGR.
    Feature scales are set in metres so that textures at different resolutions look alike:
    shapes from 1.5 m down to 4 cm, glyphs from 60 cm down to 5 cm, pixel noise on top.
    """
    w = max(8, int(round(width_m * px_per_m)))
    h = max(8, int(round(height_m * px_per_m)))
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x7E57])
    area = width_m * height_m  # m^2
    m = float(px_per_m)

    base = np.array(_colour(rng), np.float32)
    field = 128.0 + 0.35 * (base - 128.0) + 38.0 * _smooth_field(rng, w, h, max(2, int(width_m / 1.5)))
    img = np.clip(field, 0, 255).astype(np.uint8)

    def n(per_m2: float) -> int:
        return max(1, int(round(per_m2 * area)))

    _shapes(img, rng, n(0.5), (0.6 * m, 2.0 * m))  # large: metres
    _shapes(img, rng, n(3.0), (0.18 * m, 0.6 * m))  # medium: decimetres
    _glyphs(img, rng, n(1.2), (0.12 * m, 0.6 * m))
    _shapes(img, rng, n(10.0), (max(2.0, 0.04 * m), max(3.0, 0.18 * m)))  # small: centimetres
    _glyphs(img, rng, n(2.0), (max(4.0, 0.05 * m), max(6.0, 0.12 * m)))

    noise = rng.normal(0.0, 10.0, (h, w, 1)).astype(np.float32)
    noise = cv2.GaussianBlur(noise, (0, 0), 0.7)[..., None] * 1.6 + rng.normal(0.0, 4.0, (h, w, 1)).astype(np.float32)
    out = np.clip(img.astype(np.float32) + noise, 0, 255)
    return np.ascontiguousarray(out.astype(np.uint8))


def photo_texture(path: str | Path, width_px: int, height_px: int, reuse: int = 0) -> NDArray[np.uint8]:
    """The photo at `path` cropped to the plane's aspect ratio and resized to `width_px` x `height_px`.

    The crop is centred ("cover" fit, aspect preserved). `reuse` = how many planes already got
    this photo: reuses are mirrored (odd) and cropped from a different 70% window (>= 2) so that
    two planes never carry an identical texture (SIFT is not mirror-invariant). Raises
    `matching.errors.InputError` naming the file when it is missing or unreadable.
    """
    img = load_color(path)
    ih, iw = img.shape[:2]
    if reuse >= 2:  # a different sub-window per reuse, deterministic
        k = (reuse // 2 - 1) % 4
        cw, ch = int(iw * 0.7), int(ih * 0.7)
        x0 = 0 if k in (0, 2) else iw - cw
        y0 = 0 if k in (0, 1) else ih - ch
        img, iw, ih = img[y0:y0 + ch, x0:x0 + cw], cw, ch
    target = width_px / float(height_px)
    if iw / ih > target:  # too wide: crop the sides
        cw = max(1, int(round(ih * target)))
        x0 = (iw - cw) // 2
        img = img[:, x0:x0 + cw]
    else:
        ch = max(1, int(round(iw / target)))
        y0 = (ih - ch) // 2
        img = img[y0:y0 + ch]
    interp = cv2.INTER_AREA if img.shape[1] > width_px else cv2.INTER_CUBIC
    img = cv2.resize(img, (width_px, height_px), interpolation=interp)
    if reuse % 2 == 1:
        img = img[:, ::-1]
    return np.ascontiguousarray(img)
