"""`matching.registry.match_images`, the library's one-call entry point (README, "From Python")."""

from __future__ import annotations

import numpy as np

from matching.io import load_gray
from matching.registry import match_images


def test_match_images_downscaled_returns_the_originals_frame(corner_scene):
    """Two views of the rendered corner (480 x 360) matched at `max_size=240`: the result is
    the same matcher's, in the originals' pixels (points span beyond the 240 px working size,
    sizes are the originals'), and agrees with matching at full size on the homography's
    mapping to within a few px."""
    a, b = (load_gray(corner_scene / "images" / f"view_{k:02d}.png") for k in (0, 1))
    full = match_images(a, b, seed=0)
    half = match_images(a, b, max_size=240, seed=0)
    assert half.image_sizes == ((480, 360), (480, 360)) and half.num_inliers >= 30
    p0, p1 = half.matched_points()
    assert p0[:, 0].max() > 300 and p1[:, 0].max() > 300
    assert full.H_1_from_0 is not None and half.H_1_from_0 is not None
    q = np.c_[p0, np.ones(len(p0))] @ full.H_1_from_0.T
    err = np.linalg.norm(q[:, :2] / q[:, 2:] - p1, axis=1)
    assert np.median(err) < 3.0, np.percentile(err, [50, 90])
    assert match_images(a, b, max_size=0, seed=0).num_inliers == full.num_inliers  # 0 = full resolution
