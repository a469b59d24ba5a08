"""`recon.eval.gt_planes`: exact correspondences in the rendered scenes."""

from __future__ import annotations

import json

import cv2
import numpy as np

from recon.eval.gt import GtCamera, read_colmap_text
from recon.eval.gt_planes import (
    Rect,
    correct_counts,
    correct_error_median,
    correct_matches,
    rects_from_scene,
    transfer,
    transfer_errors,
)
from scenes.render import centred_K, look_at_pose


def _camera(centre, target=(0.0, 0.0, 1.0)) -> GtCamera:
    return GtCamera(centred_K((640, 480), 500.0), look_at_pose(np.asarray(centre, float), np.asarray(target, float)),
                    (640, 480))


def _project(cam: GtCamera, X) -> np.ndarray:
    x = (np.asarray(X) @ cam.R.T + cam.t) @ cam.K.T
    return x[:, :2] / x[:, 2:3]


def _rect(origin, u, v) -> Rect:
    n = np.cross(u, v)
    return Rect(np.asarray(origin, float), np.asarray(u, float), np.asarray(v, float), n / np.linalg.norm(n))


def test_transfer_is_exact_and_respects_occlusion_and_back_faces():
    """A wall (front +y) seen by two cameras: transfer reproduces the projections of points on it;
    a post standing in front of part of it hides those points from camera 1 (NaN there); a plane
    seen from behind is not drawn, so it neither hides nor catches rays."""
    wall = _rect((3.0, 0.0, 0.0), (-6.0, 0.0, 0.0), (0.0, 0.0, 3.0))  # u x v = +y
    post = _rect((2.0, 2.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 3.0))  # faces +y, 2 m in front of the wall
    back = _rect((-3.0, 3.0, 0.0), (6.0, 0.0, 0.0), (0.0, 0.0, 3.0))  # faces -y: the cameras see its back
    cam0, cam1 = _camera((-2.0, 8.0, 1.5)), _camera((4.0, 7.0, 1.5))
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-2.5, 2.5, 400), np.zeros(400), rng.uniform(0.2, 2.8, 400)]
    x0, x1 = _project(cam0, X), _project(cam1, X)

    only_wall = transfer([wall, back], cam0, cam1, x0)
    np.testing.assert_allclose(only_wall, x1, atol=1e-6)

    with_post = transfer([wall, post, back], cam0, cam1, x0)
    # what camera 0 sees of the wall but camera 1 sees of the post
    d1 = X - cam1.center
    s = (2.0 - cam1.center[1]) / d1[:, 1]
    hit = cam1.center + s[:, None] * d1
    hidden1 = (hit[:, 0] >= 1.0) & (hit[:, 0] <= 2.0)
    d0 = X - cam0.center
    s0 = (2.0 - cam0.center[1]) / d0[:, 1]
    hidden0 = ((cam0.center + s0[:, None] * d0)[:, 0] >= 1.0) & ((cam0.center + s0[:, None] * d0)[:, 0] <= 2.0)
    assert hidden1.sum() > 20 and (hidden1 & ~hidden0).sum() > 10
    vis = ~hidden0 & ~hidden1
    np.testing.assert_allclose(with_post[vis], x1[vis], atol=1e-6)
    assert np.isnan(with_post[hidden1 & ~hidden0]).all()

    ok = correct_matches([wall], cam0, cam1, x0, x1 + [1.0, 1.0], np.sqrt(3.0))  # 1.41 px off: correct
    assert ok.all()
    assert not correct_matches([wall], cam0, cam1, x0, x1 + [2.0, 0.0], np.sqrt(3.0)).any()


def test_rendered_neighbours_sift_inliers_land_on_the_transfer(rendered_scene):
    """The renderer's conventions and the transfer agree: on two corner views 17 deg apart,
    SIFT matches that fit one fundamental matrix land on the exact transfer (median error a
    fraction of a pixel, nearly all within sqrt(3) px), while the same matches with their
    targets shuffled almost never do."""
    scene = rendered_scene("corner")
    rects = rects_from_scene(json.loads((scene / "gt" / "scene.json").read_text()))
    cams = read_colmap_text(scene / "gt")
    a, b = sorted(cams)[:2]
    im0, im1 = (cv2.imread(str(scene / "images" / n), cv2.IMREAD_GRAYSCALE) for n in (a, b))
    sift = cv2.SIFT.create()
    k0, d0 = sift.detectAndCompute(im0, None)
    k1, d1 = sift.detectAndCompute(im1, None)
    knn = cv2.BFMatcher().knnMatch(d0, d1, k=2)
    good = [m for m, n in knn if m.distance < 0.75 * n.distance]
    p0 = np.float64([k0[m.queryIdx].pt for m in good])
    p1 = np.float64([k1[m.trainIdx].pt for m in good])
    cv2.setRNGSeed(0)
    _, mask = cv2.findFundamentalMat(p0, p1, cv2.FM_RANSAC, 1.0, 0.999)
    inl = mask.ravel().astype(bool)
    p0, p1 = p0[inl], p1[inl]
    assert len(p0) > 100
    err = np.linalg.norm(transfer(rects, cams[a], cams[b], p0) - p1, axis=1)
    assert np.nanmedian(err) < 0.5
    assert correct_matches(rects, cams[a], cams[b], p0, p1, np.sqrt(3.0)).mean() > 0.9
    shuffled = p1[np.random.default_rng(0).permutation(len(p1))]
    assert correct_matches(rects, cams[a], cams[b], p0, shuffled, np.sqrt(3.0)).mean() < 0.05


def test_transfer_errors_need_a_database_and_planes(tmp_path, rendered_scene):
    """No run folder, a run without its database, or a scene without planes: no count (None),
    never a count read from whatever database.db sits in the working directory."""
    scene = rendered_scene("corner")
    assert transfer_errors(None, scene) is None
    assert transfer_errors("", scene) is None
    assert transfer_errors(tmp_path, scene) is None  # no database.db there
    (tmp_path / "database.db").write_bytes(b"")
    assert transfer_errors(tmp_path, tmp_path) is None  # no gt/scene.json


def test_correct_counts_and_median_error_ignore_wrong_and_untransferable_matches():
    errors = {("a", "b"): np.array([0.1, 0.3, 5.0, np.inf]), ("a", "c"): np.array([0.2, 1.7]), ("b", "c"): np.array([9.0])}
    assert correct_counts(errors) == {("a", "b"): 2, ("a", "c"): 2, ("b", "c"): 0}
    assert correct_counts(errors, 0.25) == {("a", "b"): 1, ("a", "c"): 1, ("b", "c"): 0}
    assert correct_error_median(errors) == 0.25  # median of 0.1, 0.3, 0.2, 1.7
    assert correct_error_median({("b", "c"): np.array([9.0])}) is None and correct_counts(None) is None
