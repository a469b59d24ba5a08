"""Match pictures (recon.viz.vis.draw_matches, on cv2.drawMatches): layout, colours, line limit."""

from __future__ import annotations

import numpy as np

from matching.types import PairResult
from recon.viz.vis import INLIER_BGR, OUTLIER_BGR, draw_matches


def _result(k0, k1, inliers) -> PairResult:
    n = len(k0)
    return PairResult("test", np.asarray(k0, np.float32), np.asarray(k1, np.float32),
                      np.stack([np.arange(n), np.arange(n)], 1).astype(np.int32), np.zeros(n, np.float32),
                      inlier_mask=None if inliers is None else np.asarray(inliers, bool))


def test_layout_and_colours():
    img0 = np.full((300, 400, 3), 10, np.uint8)
    img1 = np.full((200, 250), 20, np.uint8)  # gray and smaller: padded below, converted to BGR
    # two horizontal matches far apart: an inlier at y = 50, an outlier at y = 150
    r = _result([[100, 50], [100, 150]], [[100, 50], [100, 150]], [True, False])
    out = draw_matches(img0, img1, r)
    assert out.shape == (300, 650, 3) and out.dtype == np.uint8
    assert (out[250, 10] == 10).all() and (out[100, 410] == 20).all() and (out[250, 600] == 0).all()
    mid_in, mid_out = out[50, 300], out[150, 300]  # halfway between (100, y) and (400 + 100, y)
    assert np.abs(mid_in.astype(int) - INLIER_BGR).max() < 30
    assert np.abs(mid_out.astype(int) - OUTLIER_BGR).max() < 30
    # no inlier mask: every match is drawn as an inlier
    out_all = draw_matches(img0, img1, _result([[100, 150]], [[100, 150]], None))
    assert np.abs(out_all[150, 300].astype(int) - INLIER_BGR).max() < 30


def test_line_limit_and_no_matches():
    img = np.zeros((400, 1000, 3), np.uint8)
    ys = np.arange(5.0, 395.0, 2.0)  # 195 horizontal matches, 2 rows apart
    k = np.stack([np.full_like(ys, 500.0), ys], 1)
    rows = [np.count_nonzero(draw_matches(img, img, _result(k, k, None), max_lines=m)[:, 1000].max(axis=1) > 0)
            for m in (20, 400)]  # rows touched in the column halfway along every line
    assert 20 <= rows[0] <= 60 and rows[1] >= 195  # 20 of 195 lines (anti-aliased: 1-3 rows each); all
    empty = draw_matches(img, img, _result(np.zeros((0, 2)), np.zeros((0, 2)), None))
    assert empty.shape == (400, 2000, 3) and not empty.any()


def test_legend_names_colours_counts_and_the_line_limit():
    from recon.viz.vis import legend_text

    img = np.zeros((300, 500, 3), np.uint8)
    ys = np.arange(5.0, 295.0, 2.0)  # 145 matches, every third an outlier
    k = np.stack([np.full_like(ys, 250.0), ys], 1)
    inl = np.arange(len(ys)) % 3 != 0
    r = _result(k, k, inl)
    text = legend_text(r, 100)
    assert text == f"inliers {inl.sum()} (green)   outliers {(~inl).sum()} (red)   lines: 100 of 145 (sampled)"
    assert legend_text(r, 145).endswith("lines: all 145")
    plain, with_legend = draw_matches(img, img, r, max_lines=100), draw_matches(img, img, r, max_lines=100, legend=True)
    band = with_legend.shape[0] - plain.shape[0]
    assert with_legend.shape[1] == plain.shape[1] and 10 < band < 60
    np.testing.assert_array_equal(with_legend[band:], plain)  # the picture below the band is unchanged
    top = with_legend[:band].reshape(-1, 3).astype(int)  # the band shows green and red text
    assert (np.abs(top - INLIER_BGR).max(axis=1) < 40).sum() > 20
    assert (np.abs(top - OUTLIER_BGR).max(axis=1) < 40).sum() > 20
