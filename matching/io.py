"""Reading images and homographies from disk, with one-line errors for bad input.

Every image becomes an 8-bit single-channel array: grayscale, RGB(A) and 16-bit inputs are all
accepted (16-bit is rescaled by its bit depth, alpha is dropped), because SIFT and ORB in OpenCV
work on 8-bit gray. Images are read with `cv2.imdecode` from bytes so that paths with spaces and
non-ASCII characters work on every platform.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import InputError

MIN_IMAGE_SIDE = 32  # px; below this no detector finds anything useful


def _decode(path: Path, flags: int) -> NDArray:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, expected an image file")
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror or e})") from None
    if data.size == 0:
        raise InputError(f"{path}: empty file")
    img = cv2.imdecode(data, flags)
    if img is None:
        raise InputError(f"{path}: not a readable image (unknown format or corrupt data)")
    return img


def to_gray_u8(img: NDArray) -> NDArray[np.uint8]:
    """Any decoded image (gray, BGR, BGRA; 8/16-bit or float) as 8-bit gray."""
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        else:
            img = img[:, :, 0]
    if img.dtype != np.uint8:
        img = _to_u8(img)
    return np.ascontiguousarray(img)


def _to_u8(img: NDArray) -> NDArray[np.uint8]:
    """Integer images scale by their container's effective bit depth (the smallest 2^k - 1
    that holds the maximum: 16-bit data / 257, 12-bit data / 16.06), so an 8-bit image stored
    as 16-bit comes back exactly; float images scale by their own range."""
    f = img.astype(np.float32)
    if np.issubdtype(img.dtype, np.integer):
        top = float(max(int(img.max()), 255))
        full = float(2 ** int(np.ceil(np.log2(top + 1))) - 1)
        return np.clip(f * (255.0 / full) + 0.5, 0, 255).astype(np.uint8)
    lo, hi = float(np.nanmin(f)), float(np.nanmax(f))
    f = (f - lo) * (255.0 / (hi - lo)) if hi > lo else np.zeros_like(f)
    return np.clip(np.nan_to_num(f) + 0.5, 0, 255).astype(np.uint8)


def to_bgr_u8(img: NDArray) -> NDArray[np.uint8]:
    """Any decoded image as 8-bit 3-channel BGR (for drawing and colouring points)."""
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        return cast(NDArray[np.uint8], cv2.cvtColor(to_gray_u8(img), cv2.COLOR_GRAY2BGR))
    if img.dtype != np.uint8:
        img = _to_u8(img)
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(img)


def _check_size(path: Path, img: NDArray) -> None:
    h, w = img.shape[:2]
    if min(h, w) < MIN_IMAGE_SIDE:
        raise InputError(f"{path}: image is {w}x{h} px; each side must be at least {MIN_IMAGE_SIDE} px")


def load_gray(path: str | Path) -> NDArray[np.uint8]:
    """The image at `path` as 8-bit gray, or InputError naming the file."""
    img = _decode(Path(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    _check_size(Path(path), img)
    return to_gray_u8(img)


def load_color(path: str | Path) -> NDArray[np.uint8]:
    """The image at `path` as 8-bit BGR, or InputError naming the file."""
    img = _decode(Path(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    _check_size(Path(path), img)
    return to_bgr_u8(img)


def image_size(img: NDArray) -> tuple[int, int]:
    """(width, height) in px, the order of `PairResult.image_sizes` and COLMAP's cameras."""
    return int(img.shape[1]), int(img.shape[0])


def to_original_px(kpts: NDArray, scale_xy: tuple[float, float]) -> NDArray[np.float32]:
    """Working-resolution keypoints (OpenCV convention) -> the original's pixels, (N, 2) float32.

    `cv2.resize` maps pixel centres, so x_orig = (x_work + 0.5) / sx - 0.5 per axis, with
    (sx, sy) = working size / original size, the exact per-axis scale of the rounded working
    size (`resize_max`'s nominal scale is up to half a pixel off on the shorter side).
    """
    sx, sy = scale_xy
    k = np.asarray(kpts, np.float64).reshape(-1, 2)
    if sx == 1.0 and sy == 1.0:
        return k.astype(np.float32)
    out = np.empty_like(k)
    out[:, 0] = (k[:, 0] + 0.5) / sx - 0.5
    out[:, 1] = (k[:, 1] + 0.5) / sy - 0.5
    return out.astype(np.float32)


def work_from_original(scale_xy: tuple[float, float]) -> NDArray[np.float64]:
    """A with x_work = A @ x_orig (homogeneous, the pixel-centre convention of `to_original_px`)."""
    sx, sy = scale_xy
    return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]], np.float64)


def resize_max(img: NDArray, max_size: int | None) -> tuple[NDArray, float]:
    """Downscale so the longer side is at most `max_size` px (INTER_AREA).

    Returns (image, scale) with scale = working / original (1.0 when unchanged), so that
    original-pixel coordinates are working coordinates / scale (pixel-centre convention kept:
    x_orig = (x_work + 0.5) / scale - 0.5).
    """
    h, w = img.shape[:2]
    if not max_size or max(h, w) <= max_size:
        return img, 1.0
    scale = max_size / float(max(h, w))
    out = cv2.resize(img, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    return out, scale


def read_homography(path: str | Path) -> NDArray[np.float64]:
    """A 3x3 homography from a whitespace-separated text file, normalised so H[2, 2] = 1.

    Accepts the Oxford (`H1to2p`), HPatches (`H_1_2`) and EVD (`h/<n>.txt`) layouts: nine numbers
    in any line arrangement. Raises InputError naming the file when it is missing or malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such homography file")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError):
        raise InputError(f"{path}: not a text homography file") from None
    try:
        vals = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise InputError(f"{path}: malformed homography (expected 9 numbers)") from None
    if len(vals) != 9 or not np.all(np.isfinite(vals)):
        raise InputError(f"{path}: malformed homography (expected 9 finite numbers, got {len(vals)})")
    H = np.asarray(vals, np.float64).reshape(3, 3)
    if abs(H[2, 2]) < 1e-12 or abs(np.linalg.det(H)) < 1e-15:
        raise InputError(f"{path}: degenerate homography (singular or H[2,2] = 0)")
    return H / H[2, 2]
