"""The web viewer in a real browser: `benchmarks/screenshot_viewer.py` serves a recording with
`rerun --serve-web` and shoots it with headless Chromium (skipped where none is installed)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rerun")

REPO = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("screenshot_viewer", REPO / "benchmarks" / "screenshot_viewer.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def test_loading_screen_is_told_from_a_loaded_viewer(tmp_path):
    shot = _script()
    flat = np.full((500, 800, 3), 18, np.uint8)
    cv2.putText(flat, "Loading Application Bundle...", (250, 250), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (90, 90, 90), 1)
    cv2.imwrite(str(tmp_path / "loading.png"), flat)
    busy = (np.random.default_rng(0).random((500, 800, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "busy.png"), busy)
    assert not shot.looks_loaded(tmp_path / "loading.png") and shot.looks_loaded(tmp_path / "busy.png")
    assert not shot.looks_loaded(tmp_path / "missing.png")


@pytest.mark.slow
def test_web_viewer_screenshot_in_headless_chromium(tmp_path):
    """A recording of one pair, served and shot at 1280x800: the page gets past the loading
    screen (the software rasterizer takes tens of seconds) and shows the viewer's panels."""
    from matching.types import PairResult
    from recon.viz.rerun_log import Sink, find_viewer, log_single_pair

    shot = _script()
    if shot.find_browser() is None or find_viewer() is None:
        pytest.skip("no Chromium browser (apt-get install chromium) or no rerun executable")
    rng = np.random.default_rng(0)
    p0, p1 = tmp_path / "a.png", tmp_path / "b.png"
    cv2.imwrite(str(p0), (rng.random((240, 320, 3)) * 255).astype(np.uint8))
    cv2.imwrite(str(p1), (rng.random((240, 320, 3)) * 255).astype(np.uint8))
    k = rng.uniform(0, 230, (30, 2)).astype(np.float32)
    r = PairResult("test", k, k, np.stack([np.arange(30), np.arange(30)], 1).astype(np.int32),
                   np.zeros(30, np.float32), inlier_mask=np.arange(30) < 20)
    rrd = log_single_pair(Sink("save", str(tmp_path / "recording.rrd")), p0, p1, r)
    png = tmp_path / "viewer.png"
    assert shot.shoot(rrd, png, (1280, 800), log=lambda m: None)
    img = cv2.imread(str(png))
    assert img.shape[:2] == (800, 1280) and shot.looks_loaded(png)
