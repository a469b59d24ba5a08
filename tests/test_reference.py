"""Reference selection (Eq. 1 and the robust variant) on a pair rendered by zooming a real image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from matching.features import DetectorConfig, detect
from matching.reference import ReferenceConfig, choose_reference, paper_coefficient


def test_paper_coefficient_sign_follows_segment_lengths():
    a = np.array([[0, 0], [10, 0], [10, 10]], np.float32)
    d = np.zeros(3, np.float32)
    assert paper_coefficient(a * 2, a, d) > 0  # source segments longer: source is more detailed
    assert paper_coefficient(a, a * 2, d) < 0
    # descriptor distances weight the terms down (1 - (d_i + d_i+1) / 1000)
    assert paper_coefficient(a * 2, a, np.full(3, 250, np.float32)) == pytest.approx(0.5 * paper_coefficient(a * 2, a, d))


def _zoom_pair(img: np.ndarray, zoom: float) -> tuple[np.ndarray, np.ndarray]:
    """(far, near): the whole image, and its centre crop enlarged by `zoom` (a closer camera)."""
    h, w = img.shape
    cw, ch = int(w / zoom), int(h / zoom)
    x0, y0 = (w - cw) // 2, (h - ch) // 2
    near = cv2.resize(img[y0:y0 + ch, x0:x0 + cw], (w, h), interpolation=cv2.INTER_CUBIC)
    return img, near


@pytest.mark.requires_shared("oxford/graf/img1.png")
@pytest.mark.parametrize("mode", ["robust", "paper"])
def test_closer_camera_becomes_the_reference(shared_data, mode):
    img = cv2.imread(str(shared_data / "oxford" / "graf" / "img1.png"), cv2.IMREAD_GRAYSCALE)
    far, near = _zoom_pair(img, 1.8)
    det = DetectorConfig("sift")
    f_far, f_near = detect(far, det), detect(near, det)
    cfg = ReferenceConfig(mode=mode)
    assert choose_reference(f_far, f_near, cfg).reference == 1
    assert choose_reference(f_near, f_far, cfg).reference == 0
    if mode == "robust":
        d = choose_reference(f_far, f_near, cfg)
        assert d.scale_1_from_0 == pytest.approx(1.8, rel=0.05)


@pytest.mark.requires_shared("oxford/graf/img1.png")
def test_unrelated_images_leave_the_reference_undecided(shared_data):
    img = cv2.imread(str(shared_data / "oxford" / "graf" / "img1.png"), cv2.IMREAD_GRAYSCALE)
    noise = (np.random.default_rng(0).random(img.shape) * 255).astype(np.uint8)
    noise = cv2.GaussianBlur(noise, (0, 0), 2.0)
    det = DetectorConfig("sift")
    d = choose_reference(detect(img, det), detect(noise, det), ReferenceConfig())
    assert d.reference is None
    assert "undecided" in d.reason
