"""Homography geometry in pixels: the local affine of a homography, its area scale, and how much
larger one image shows the scene than the other.

Conventions: points are (x, y) pixels, OpenCV convention (see `matching.types`); `H_1_from_0`
maps image-0 pixels to image-1 pixels, x1 ~ H [x0, y0, 1]. Sizes are (width, height).
`scale_1_from_0` is the one relative-scale quantity of the project: the reference choice
(`matching.reference`, every case) and the ground-truth check (`matching.metrics.gt_reference`)
both read it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray


def homography_jacobian(H: NDArray[np.float64], pt: ArrayLike) -> NDArray[np.float64]:
    """2x2 Jacobian of the homography `H` at `pt` (x, y) in pixels: its local affine."""
    x, y = (float(v) for v in np.asarray(pt, np.float64).ravel()[:2])
    q = H @ np.array([x, y, 1.0])
    w = q[2]
    return (H[:2, :2] * w - np.outer(q[:2], H[2, :2])) / (w * w)


def local_scale(H: ArrayLike, at_xy: ArrayLike) -> float:
    """|det J| of the homography H at the point (x, y): the local area scale of the mapping.

    For x' = (A x + t) / w with w = g.x + h33, det J = det(H) / w^3 (invariant to the scale of
    H). Below 1: a small patch around (x, y) shrinks when mapped; above 1: it grows.
    Returns inf when (x, y) maps to infinity.
    """
    H = np.asarray(H, np.float64)
    x, y = (float(v) for v in np.asarray(at_xy, np.float64).ravel()[:2])
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    if abs(w) < 1e-15:
        return math.inf
    return float(abs(np.linalg.det(H) / w**3))


def image_centre(size: tuple[int, int]) -> tuple[float, float]:
    """Centre of a (width, height) image in OpenCV pixel coordinates."""
    w, h = size
    return ((w - 1) / 2.0, (h - 1) / 2.0)


def scale_1_from_0(H_1_from_0: ArrayLike, size0: tuple[int, int]) -> float:
    """How much larger image 1 shows the scene than image 0, as a linear factor, at image 0's centre.

    sqrt(local_scale(H_1_from_0, centre of image 0)), `size0` = (width, height) of image 0.
    Above 1: a patch at image 0's centre grows when mapped into image 1, so image 1 resolves
    the surface with more pixels (its camera is closer or more frontal); below 1: image 0 does.
    NaN when the centre maps to infinity or H is degenerate (no scale to read).
    """
    area = local_scale(H_1_from_0, image_centre(size0))
    return math.sqrt(area) if math.isfinite(area) and area > 0 else math.nan
