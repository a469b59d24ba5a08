"""The simulation grid and the affine warps of simulated views.

A view (t, phi, s) of an image I is the affine image  s * T_t * R(phi) * I :  rotate by the
longitude phi (degrees, counter-clockwise in the image's x-right / y-down frame as OpenCV's
`getRotationMatrix2D` does), compress x by 1/t (the camera tilt, latitude theta = arccos(1/t)),
then zoom by s; finally translate so the whole warped image lies on the canvas with its top-left
corner at (0, 0). `A_view_from_orig` (2x3) maps original pixels to view pixels, both in OpenCV's
pixel-centre convention, so keypoints map back exactly with its inverse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from .types import ViewParams

Interp = Literal["nearest", "linear", "lanczos", "area"]
_CV_INTERP = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR,
              "lanczos": cv2.INTER_LANCZOS4, "area": cv2.INTER_AREA}


@dataclass(frozen=True)
class GridConfig:
    """The paper's sampling (§III-B): t = a^k (k = 0..n), phi = j*b/t < 180 deg, s = 1 + k*ds."""

    a: float = math.sqrt(2.0)
    """Tilt ratio between grid levels (> 1)."""
    n: int = 5
    """Highest tilt index: tilts up to a^n (5.66 with the defaults)."""
    b: float = 72.0
    """Longitude step at t = 1, degrees; the step at tilt t is b / t."""
    ds: float = 0.5
    """Zoom step per tilt level: s = 1 + k*ds."""
    scale_mode: Literal["tied", "none", "cap"] = "tied"
    """"tied" is the paper's s = 1 + k*ds (one scale per tilt); "none" keeps s = 1 (the paper's
    ds = 0 ablation); "cap" is "tied" but limits the zoom so the view's area is at most
    `max_area_ratio` times the original's (the paper's zoom grows the simulated area as s^2/t,
    2.2x at k = 5)."""
    max_area_ratio: float = 1.0
    """The area cap of `scale_mode` "cap", as a multiple of the original's area."""
    min_tilt_index: int = 0
    """First tilt index of the grid (lets a level simulate only the steep part of the grid)."""

    def __post_init__(self) -> None:
        if self.a <= 1.0:
            raise ValueError("GridConfig.a must be > 1 (tilt ratio between grid levels)")
        if not 0.0 < self.b <= 180.0:
            raise ValueError("GridConfig.b must be in (0, 180] degrees")
        if self.n < 0 or self.ds < 0:
            raise ValueError("GridConfig.n and ds must be >= 0")


def tilts(cfg: GridConfig) -> list[float]:
    return [cfg.a**k for k in range(cfg.min_tilt_index, cfg.n + 1)]


def view_grid(cfg: GridConfig = GridConfig()) -> list[ViewParams]:
    """All simulated views, tilt by tilt: 3, 4, 5, 8, 10, 15 views (45) with the defaults."""
    views: list[ViewParams] = []
    for k in range(cfg.min_tilt_index, cfg.n + 1):
        t = cfg.a**k
        s = 1.0 if cfg.scale_mode == "none" else 1.0 + k * cfg.ds
        if cfg.scale_mode == "cap":
            s = min(s, math.sqrt(cfg.max_area_ratio * t))
        j = 0
        while j * cfg.b / t < 180.0 - 1e-9:
            views.append(ViewParams(t=round(t, 6), phi=round(j * cfg.b / t, 6), s=round(s, 6)))
            j += 1
    return views


def capped_view(view: ViewParams, size: tuple[int, int], max_area_ratio: float = 0.0,
                max_side: int = 0) -> ViewParams:
    """The view as actually rendered when its zoom is capped for speed: same (t, phi).

    `max_area_ratio` (> 0) caps the view's area at that multiple of the original's (zoom at
    most sqrt(ratio * t)); `max_side` (> 0) renders as if the original's longer side were at
    most that many pixels. Keypoints still map back exactly: the affine includes the zoom.
    """
    s = view.s
    if max_area_ratio > 0:
        s = min(s, math.sqrt(max_area_ratio * view.t))
    if max_side > 0 and max(size) > max_side:
        s *= max_side / float(max(size))
    return view if s == view.s else ViewParams(view.t, view.phi, round(s, 6))


def linear_part(view: ViewParams) -> NDArray[np.float64]:
    """2x2 matrix s * diag(1/t, 1) * R(phi) (R as OpenCV's getRotationMatrix2D, y down)."""
    c, sn = math.cos(math.radians(view.phi)), math.sin(math.radians(view.phi))
    R = np.array([[c, sn], [-sn, c]])
    return view.s * np.diag([1.0 / view.t, 1.0]) @ R


def view_affine(size: tuple[int, int], view: ViewParams) -> tuple[NDArray[np.float64], tuple[int, int]]:
    """(A_view_from_orig 2x3, (width, height) of the view canvas) for an image of `size` (w, h).

    The translation puts the warped corners' bounding box at the origin, so no pixel is lost.
    """
    w, h = size
    L = linear_part(view)
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64)
    warped = corners @ L.T
    lo = warped.min(axis=0)
    hi = warped.max(axis=0)
    A = np.hstack([L, -lo[:, None]])
    out = (int(math.ceil(hi[0] - lo[0])) + 1, int(math.ceil(hi[1] - lo[1])) + 1)
    return A, out


def invert_affine(A: NDArray[np.float64]) -> NDArray[np.float64]:
    return cast(NDArray[np.float64], cv2.invertAffineTransform(A.astype(np.float64)))


def apply_affine(A: NDArray[np.float64], pts: NDArray) -> NDArray[np.float32]:
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    return (pts @ A[:, :2].T + A[:, 2]).astype(np.float32)


def map_to_original(kpts_view: NDArray, A_view_from_orig: NDArray[np.float64],
                    size: tuple[int, int]) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Keypoints of a view mapped back to the original image, and which fall inside it.

    Inside means within the original pixel grid [-0.5, w - 0.5) x [-0.5, h - 0.5) (pixel edges
    in OpenCV's centre convention); the caller drops the others.
    """
    pts = apply_affine(invert_affine(A_view_from_orig), kpts_view)
    w, h = size
    inside = (pts[:, 0] >= -0.5) & (pts[:, 0] < w - 0.5) & (pts[:, 1] >= -0.5) & (pts[:, 1] < h - 0.5)
    return pts, inside


@dataclass
class SimulatedView:
    """A warped image, its valid-pixel mask (255 inside the warped original) and its affine."""

    view: ViewParams
    image: NDArray[np.uint8]
    mask: NDArray[np.uint8]
    A_view_from_orig: NDArray[np.float64]


def antialias_sigma(view: ViewParams) -> float:
    """ASIFT's anti-aliasing blur along the compressed axis, 0.8*sqrt(r^2 - 1) with r = t/s.

    The view shrinks x by s/t; only a net shrink (t > s) aliases. The paper's zoom s >= 1 makes
    most of its views need no blur at all.
    """
    r = view.t / view.s
    return 0.8 * math.sqrt(r * r - 1.0) if r > 1.0 + 1e-9 else 0.0


HALVING_SIGMA = 0.8 * math.sqrt(3.0)
"""Blur (px) an image carries along x before `blur_compress_x` halves it: ASIFT's anti-aliasing
rule 0.8 sqrt(r^2 - 1) for r = 2."""

HALVING_MIN_TILT = 8.0
"""Views tilted less than this keep the exact blur: the paper's grid (t <= 5.66) gains little (at
most one halving) and stays bit-identical; the steep level's views (t = 8-22.6) and the two-sided
grid's t = 8 are where the wide blur cost most of the warp."""

ANTIALIAS_HALVING = True
"""`simulate`'s default for `halving` (module level so that a benchmark can time both ways)."""

FUSED_AXIS_WARP = True
"""`simulate`'s default for `fused`: a view with phi = 0 is blurred on the original and warped
once (module level so that a benchmark can time both ways)."""


def blur_compress_x(img: NDArray[np.uint8], sigma: float, t: float, halving: bool = True
                    ) -> tuple[NDArray[np.uint8], int]:
    """(`img` blurred along x by a Gaussian of `sigma` px, decimated along x by f; f): pixel
    column i of the result is column f i of `img` (centres), so x_img = f x_out.

    The exact blur costs about 6 sigma taps per pixel, and at the steep tilts (t = 8-22.6, sigma
    6-18 px) it was most of a view's warp although the compression by t then drops all but one
    column in t. With `halving`, while sigma >= `HALVING_SIGMA` f and 2 f <= t, the image is
    blurred until it carries `HALVING_SIGMA` current px and every other column is dropped; the
    rest of the variance is blurred at the last size. The variances add up to sigma^2, so the
    result is the same blur to within a few grey levels inside the view (uint8 rounding of each
    stage), at 2-8x less time for t >= 8 (docs/decisions.md, "Anti-aliasing by halving for the
    steep views").
    f = 1 (the exact blur) whenever sigma < `HALVING_SIGMA` (t / s < 2) or t < `HALVING_MIN_TILT`:
    every view of the paper's grid is unchanged."""
    V = sigma * sigma
    done = 0.0  # variance blurred so far, px^2 of `img`
    f = 1
    out = img
    while halving and t >= HALVING_MIN_TILT and 2 * f <= t and (HALVING_SIGMA * f) ** 2 <= V:
        add = math.sqrt(HALVING_SIGMA**2 - done / (f * f))  # current px; done <= (HALVING_SIGMA f / 2)^2
        out = cv2.GaussianBlur(out, (0, 0), sigmaX=add, sigmaY=0.01)
        done = (HALVING_SIGMA * f) ** 2
        out = np.ascontiguousarray(out[:, ::2])
        f *= 2
    rest = math.sqrt(max(V - done, 0.0)) / f
    if rest > 0.05:
        out = cv2.GaussianBlur(out, (0, 0), sigmaX=rest, sigmaY=0.01)
    return cast(NDArray[np.uint8], out), f


def simulate(img: NDArray[np.uint8], view: ViewParams, interp: Interp = "nearest",
             antialias: bool = False, mask_erode_px: int = 3, halving: bool | None = None,
             fused: bool | None = None) -> SimulatedView:
    """Warp `img` into the view. With `antialias`, blur along the compressed axis first.

    Without anti-aliasing this is one `warpAffine`. With it, the image is first rotated and
    zoomed (same interpolation), blurred along x by `antialias_sigma` (`blur_compress_x`, by
    halving where the blur is wide, unless `halving` is False; None = `ANTIALIAS_HALVING`), then
    compressed along x by 1/t with the same interpolation, matching ASIFT's order of operations.
    A view with phi = 0 has nothing to rotate, so with `fused` (None = `FUSED_AXIS_WARP`) the
    original is blurred along x by sigma / s (a Gaussian commutes with the zoom: the same blur in
    the view's pixels) and warped once: a Lanczos `warpAffine` costs 64 taps a pixel, and the
    zoomed intermediate was 2/3 of a fine view's warp (docs/decisions.md, "One warp for the
    views without rotation").
    The mask marks pixels that come from the original, eroded by `mask_erode_px` so detectors
    do not fire on the canvas border.
    """
    h, w = img.shape[:2]
    A, (ow, oh) = view_affine((w, h), view)
    flag = _CV_INTERP[interp]
    sigma = antialias_sigma(view) if antialias else 0.0
    halve = ANTIALIAS_HALVING if halving is None else halving
    if view.t == 1.0 and view.phi == 0.0 and view.s < 1.0:  # a pure downscale: area-average it
        out = cv2.resize(img, (ow, oh), interpolation=cv2.INTER_AREA)
        A = np.array([[ow / w, 0.0, 0.5 * ow / w - 0.5], [0.0, oh / h, 0.5 * oh / h - 0.5]])
    elif sigma <= 0.0:
        out = cv2.warpAffine(img, A, (ow, oh), flags=flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    elif view.phi == 0.0 and (FUSED_AXIS_WARP if fused is None else fused):
        # A = [[s / t, 0, 0], [0, s, 0]]: the blur in original px, then one warp from the
        # (possibly decimated, x_orig = f x_tmp) blurred original
        tmp, f = blur_compress_x(img, sigma / view.s, view.t / view.s, halve)
        A_tmp = A.copy()
        A_tmp[0, 0] *= f
        out = cv2.warpAffine(tmp, A_tmp, (ow, oh), flags=flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    else:
        rot = ViewParams(t=1.0, phi=view.phi, s=view.s)
        A_rot, (rw, rh) = view_affine((w, h), rot)
        tmp = cv2.warpAffine(img, A_rot, (rw, rh), flags=flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        tmp, f = blur_compress_x(tmp, sigma, view.t, halve)
        # x' = x / t about pixel centres: compose into one affine from the original
        S = np.array([[1.0 / view.t, 0.0, 0.0], [0.0, 1.0, 0.0]])
        A2 = S @ np.vstack([A_rot, [0, 0, 1]])
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64) @ A2[:, :2].T + A2[:, 2]
        shift = -corners.min(axis=0)
        A = A2.copy()
        A[:, 2] += shift
        ow = int(math.ceil(corners[:, 0].max() - corners[:, 0].min())) + 1
        oh = int(math.ceil(corners[:, 1].max() - corners[:, 1].min())) + 1
        S_full = np.array([[f / view.t, 0.0, shift[0]], [0.0, 1.0, shift[1]]])  # from `tmp`'s decimated columns
        out = cv2.warpAffine(tmp, S_full, (ow, oh), flags=flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    ones = np.full((h, w), 255, np.uint8)
    mask = cv2.warpAffine(ones, A, (ow, oh), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if mask_erode_px > 0:
        mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * mask_erode_px + 1,) * 2))
    return SimulatedView(view, cast(NDArray[np.uint8], out), cast(NDArray[np.uint8], mask), A)
