"""Rendered tilt pairs (`scenes.tilt`) and their benchmark (`recon bench tilt`): exact homographies,
foreshortening by the tilt, and solved counts that tell the matchers apart."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from recon.cli import main
from recon.eval.bench_tilt import TextureSpec, run_tilt_bench, tilt_summary, tilt_views
from scenes.texture import procedural_texture
from scenes.tilt import TiltView, render_tilt_pair

SIZE = (480, 360)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return procedural_texture(8.0, 6.0, 120.0, 0)  # 960 x 720 px: twice SIZE


def _sift_errors(img0, img1, H) -> np.ndarray:
    """Distances (px) between SIFT matches' points in image 1 and their image-0 points mapped by H."""
    sift = cv2.SIFT_create()
    k0, d0 = sift.detectAndCompute(img0, None)
    k1, d1 = sift.detectAndCompute(img1, None)
    good = [m for m, n in cv2.BFMatcher().knnMatch(d0, d1, k=2) if m.distance < 0.7 * n.distance]
    p0 = np.float32([k0[m.queryIdx].pt for m in good]).reshape(-1, 1, 2)
    p1 = np.float32([k1[m.trainIdx].pt for m in good]).reshape(-1, 2)
    return np.linalg.norm(cv2.perspectiveTransform(p0, H).reshape(-1, 2) - p1, axis=1)


def test_the_homography_maps_the_frontal_view_onto_the_oblique_one(texture):
    img0, img1, H = render_tilt_pair(texture, TiltView(50.0, 30.0, 15.0), SIZE)
    err = _sift_errors(img0, img1, H)
    assert len(err) >= 50
    assert np.median(err) < 0.5  # sub-pixel: the renderer and H agree
    shifted = np.array([[1, 0, 2.0], [0, 1, 0], [0, 0, 1]]) @ H  # H off by 2 px
    assert np.median(_sift_errors(img0, img1, shifted)) > 1.5


def test_the_frontal_view_is_the_texture_unmirrored_and_the_oblique_one_foreshortened_by_the_tilt(texture):
    img0, img1, H = render_tilt_pair(texture, TiltView(75.0), SIZE)
    gray = cv2.resize(cv2.cvtColor(texture, cv2.COLOR_BGR2GRAY), SIZE, interpolation=cv2.INTER_AREA)
    assert np.abs(img0.astype(float) - gray).mean() < 2.0
    assert np.abs(img0.astype(float) - gray[:, ::-1]).mean() > 20.0
    J = _jacobian(H, (SIZE[0] - 1) / 2.0, (SIZE[1] - 1) / 2.0)  # at the image centre: the plane's centre
    s = np.linalg.svd(J, compute_uv=False)
    assert s[0] / s[1] == pytest.approx(1.0 / math.cos(math.radians(75.0)), rel=0.02)
    assert (img1 == 128).mean() > 0.5  # most of the oblique frame is background


def _jacobian(H, x, y, eps=0.5) -> np.ndarray:
    def f(px, py):
        v = H @ [px, py, 1.0]
        return v[:2] / v[2]
    return np.stack([(f(x + eps, y) - f(x - eps, y)) / (2 * eps), (f(x, y + eps) - f(x, y - eps)) / (2 * eps)],
                    axis=1)


def test_the_same_texture_and_view_give_the_same_bytes(texture):
    a = render_tilt_pair(texture, TiltView(70.0, 45.0), SIZE)
    b = render_tilt_pair(texture, TiltView(70.0, 45.0), SIZE)
    c = render_tilt_pair(texture, TiltView(70.0, 50.0), SIZE)
    assert a[1].tobytes() == b[1].tobytes() != c[1].tobytes()


def test_the_extra_affine_matcher_solves_a_75_degree_view_that_plain_sift_does_not(tmp_path):
    from matching.registry import get_matcher

    views = tilt_views([75.0], [30.0])
    matchers = {m: get_matcher(m, seed=0) for m in ("extra-affine", "sift")}
    rows = run_tilt_bench(tmp_path, [TextureSpec("procedural-0", seed=0)], views, list(matchers), matchers,
                          json_path=tmp_path / "rows.json", progress=False)
    by = {r["method"]: r for r in rows}
    assert by["extra-affine"]["precision"] >= 0.9 and by["extra-affine"]["correct"] >= 100
    assert by["sift"]["correct"] < 20
    assert by["extra-affine"]["tilt"] == pytest.approx(3.864, abs=1e-3)
    assert (tmp_path / "procedural-0" / "75deg_az30_roll20" / "1.png").is_file()
    assert len(json.loads((tmp_path / "rows.json").read_text())) == 2
    summary = {s["method"]: s for s in tilt_summary(rows)}
    assert summary["extra-affine"]["solved"] == 1 and summary["sift"]["solved"] == 0


@pytest.mark.parametrize("args", [["--textures", "nowhere.png"], ["--textures", "procedural:x"],
                                  ["--angles", "95"], ["--angles", "a,b"], ["--zooms", "0"], ["--noise", "-1"],
                                  ["--jpeg", "101"], ["--gain", "inf"], ["--methods", "bogus"]])
def test_bad_options_are_one_line_errors(tmp_path, capsys, args):
    assert main(["bench", "tilt", "--out", str(tmp_path / "o"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("recon: error:") and "\n" not in err
    assert not (tmp_path / "o").exists()
