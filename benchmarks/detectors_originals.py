"""Each detector on the unwarped originals of the ground-truth pairs, no simulation: would a
covariant detector on its own be an escalation level? (issue 13, item 1; figures in
docs/decisions.md, "Covariant SIFT as an escalation level measured").

For each pair (default: the EVD pairs) and detector (OpenCV SIFT with RootSIFT, and COLMAP's
SIFT through pycolmap: plain, with affine shape, with affine shape and domain-size pooling) it
detects both originals, ratio-matches them at each `--ratios` and reports: keypoints, matches,
matches within sqrt(3) and 5 px of the ground truth, and the inliers of a 3 px RANSAC homography
with how many of those lie within 5 px (a level needs a right model, not only right matches).
Prints a table and writes JSON:

    python benchmarks/detectors_originals.py ../shared/data --json benchmarks/results/detectors-originals.json
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np

from matching.features import DetectorConfig, detect
from matching.io import load_gray
from matching.matching_utils import ransac_homography, ratio_match
from matching.metrics import reprojection_errors
from recon.eval.bench_pairs import discover_pairs

DETECTORS = ("sift", "colmap-sift-plain", "colmap-sift-affine", "colmap-sift")


def detector_config(name: str) -> DetectorConfig:
    """OpenCV SIFT with RootSIFT (what the covariant ones' descriptors are), or a COLMAP detector."""
    return DetectorConfig(name, root_sift=True) if name == "sift" else DetectorConfig(name)  # type: ignore[arg-type]


def one(img0: np.ndarray, img1: np.ndarray, H_gt: np.ndarray, det: str, ratios: list[float]) -> dict:
    """One detector on one pair: keypoints, seconds, and per ratio the counts of the module doc."""
    cfg = detector_config(det)
    t = time.perf_counter()
    fa, fb = detect(img0, cfg), detect(img1, cfg)
    row: dict = {"detector": det, "keypoints": [len(fa), len(fb)], "seconds": round(time.perf_counter() - t, 2)}
    for ratio in ratios:
        m, _ = ratio_match(fa.descriptors, fb.descriptors, cv2.NORM_L2, ratio, 0)
        p0, p1 = fa.kpts[m[:, 0]], fb.kpts[m[:, 1]]
        err = reprojection_errors(H_gt, p0, p1) if len(m) else np.zeros(0)
        H, inl = ransac_homography(p0, p1, 3.0, seed=0) if len(m) >= 4 else (None, np.zeros(len(m), bool))
        inl = inl if H is not None else np.zeros(len(m), bool)
        row[f"r{ratio:g}"] = {"matches": int(len(m)), "within_sqrt3": int((err <= math.sqrt(3)).sum()),
                              "within_5": int((err <= 5).sum()), "inliers": int(inl.sum()),
                              "inliers_within_5": int((err[inl] <= 5).sum())}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("--only", default="evd", help="pairs whose name contains this text (default: evd)")
    ap.add_argument("--detectors", default=",".join(DETECTORS))
    ap.add_argument("--ratios", default="0.8,0.9")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    ratios = [float(r) for r in args.ratios.split(",")]
    pairs = [p for p in discover_pairs(args.data_root) if args.only.lower() in p.name.lower()]
    if not pairs:
        raise SystemExit(f"{args.data_root}: no ground-truth pairs matching {args.only!r}")
    rows = []
    print(f"{'pair':12s} {'detector':20s} {'keypoints':>13s} {'s':>5s} | "
          + " | ".join(f"ratio {r:g}: matches / <=sqrt3 / <=5 px / H inliers (<=5 px)" for r in ratios))
    for pair in pairs:
        img0, img1 = load_gray(pair.path0), load_gray(pair.path1)
        for det in args.detectors.split(","):
            row = {"pair": pair.name, **one(img0, img1, pair.H_1_from_0, det, ratios)}
            rows.append(row)
            cells = " | ".join("{matches} / {within_sqrt3} / {within_5} / {inliers} ({inliers_within_5})".format(
                **row[f"r{r:g}"]) for r in ratios)
            print(f"{pair.name:12s} {det:20s} {row['keypoints'][0]:6d}/{row['keypoints'][1]:6d} "
                  f"{row['seconds']:5.1f} | {cells}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
