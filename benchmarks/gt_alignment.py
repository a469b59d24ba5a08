"""How well each ground-truth homography aligns its own pair: the floor under any matcher's
precision at sqrt(3) px.

Image 0 is warped into image 1 by the ground truth (anti-aliased along the directions it
compresses); around image 1's strongest SIFT keypoints inside the overlap, a 33x33 patch is
searched in the warped image within +-8 px by normalised cross-correlation (sub-pixel
parabola). A perfect ground truth gives shifts near 0; where the scene is not one plane or the
ground truth was clicked by hand, the shifts are what a *correct* match is measured against.
Prints a table and writes JSON:

    python benchmarks/gt_alignment.py ../shared/data --json benchmarks/results/gt_alignment.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from matching.geometry import homography_jacobian
from matching.io import load_gray
from matching.steep import antialias_blur
from recon.eval.bench_pairs import discover_pairs

HALF, SEARCH = 16, 8


def alignment_shifts(img0: np.ndarray, img1: np.ndarray, H_1_from_0: np.ndarray, n_points: int = 300) -> np.ndarray:
    """(K,) sub-pixel shifts (px of image 1) between image 1 and image 0 warped by H at image 1's
    strongest keypoints whose patch is textured and correlates (NCC >= 0.7)."""
    h1, w1 = img1.shape
    c0 = np.array([(img0.shape[1] - 1) / 2, (img0.shape[0] - 1) / 2])
    warped = cv2.warpPerspective(antialias_blur(img0, homography_jacobian(H_1_from_0, c0)), H_1_from_0, (w1, h1),
                                 flags=cv2.INTER_LINEAR)
    valid = cv2.warpPerspective(np.full(img0.shape, 255, np.uint8), H_1_from_0, (w1, h1), flags=cv2.INTER_NEAREST)
    valid = cv2.erode(valid, np.ones((2 * (HALF + SEARCH) + 3,) * 2, np.uint8))
    kps = sorted(cv2.SIFT_create().detect(img1, valid), key=lambda k: -k.response)[:n_points]
    shifts = []
    for k in kps:
        x, y = (int(round(v)) for v in k.pt)
        tmpl = img1[y - HALF:y + HALF + 1, x - HALF:x + HALF + 1].astype(np.float32)
        win = warped[y - HALF - SEARCH:y + HALF + SEARCH + 1, x - HALF - SEARCH:x + HALF + SEARCH + 1].astype(np.float32)
        if tmpl.shape != (2 * HALF + 1,) * 2 or win.shape != (2 * (HALF + SEARCH) + 1,) * 2 or tmpl.std() < 5:
            continue
        r = cv2.matchTemplate(win, tmpl, cv2.TM_CCOEFF_NORMED)
        _, peak, _, (px, py) = cv2.minMaxLoc(r)
        if peak < 0.7 or not (0 < px < 2 * SEARCH and 0 < py < 2 * SEARCH):
            continue
        def vertex(a: float, b: float, c: float) -> float:
            d = a - 2 * b + c
            return 0.0 if abs(d) < 1e-12 else 0.5 * (a - c) / d
        dx = px - SEARCH + vertex(r[py, px - 1], r[py, px], r[py, px + 1])
        dy = py - SEARCH + vertex(r[py - 1, px], r[py, px], r[py + 1, px])
        shifts.append(float(np.hypot(dx, dy)))
    return np.asarray(shifts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    rows = []
    print(f"{'pair':14s} {'patches':>7s} {'median shift px':>16s} {'within sqrt(3) px':>18s}")
    for p in discover_pairs(a.data_root):
        s = alignment_shifts(load_gray(p.path0), load_gray(p.path1), p.H_1_from_0)
        row = dict(pair=p.name, patches=int(len(s)), median_shift_px=float(np.median(s)) if len(s) else None,
                   within_sqrt3=float(np.mean(s < 3**0.5)) if len(s) else None)
        rows.append(row)
        med = "-" if row["median_shift_px"] is None else f"{row['median_shift_px']:.2f}"
        win = "-" if row["within_sqrt3"] is None else f"{100 * row['within_sqrt3']:.0f} %"
        print(f"{p.name:14s} {len(s):7d} {med:>16s} {win:>18s}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
