"""Match two photos with the extra-affine matcher from Python and inspect its decisions.

    .venv/bin/python examples/match_pair.py IMG_A IMG_B [H_A_TO_B | --3d]

Prints the reference choice, the best simulated views, the number of verified matches, the
precision against a ground-truth homography when one is given, and per-stage timings. The
default preset ends with a homography (a planar scene); `--3d` is the preset for two photos of
a 3D scene (`variant="3d"`: fundamental-matrix verification, covariant SIFT on the originals).
"""

from __future__ import annotations

import sys

from matching.io import load_gray, read_homography
from matching.metrics import precision
from matching.registry import match_images


def main() -> None:
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    pair3d = sys.argv[3:] == ["--3d"]
    H_path = None if pair3d or len(sys.argv) == 3 else sys.argv[3]
    result = match_images(load_gray(sys.argv[1]), load_gray(sys.argv[2]), method="extra-affine",
                          variant="3d" if pair3d else "default")
    print(f"reference: image {result.reference} ({result.reference_reason})")
    for v in result.best_views:
        print(f"fine view: t={v.t:.2f} phi={v.phi:.1f} deg s={v.s:.2f}")
    best_coarse = max(result.coarse_scores, key=lambda c: c.score, default=None)
    if best_coarse is not None:
        print(f"coarse: {len(result.coarse_scores)} views, best has {best_coarse.inliers} ORB inliers")
    print(f"matches: {result.num_matches}, verified: {result.num_inliers}, escalation: {result.escalation or 'none'}")
    if result.reason:
        print(f"note: {result.reason}")
    if H_path is not None:
        rep = precision(result, read_homography(H_path))
        print(f"precision: {rep.precision:.2%} ({rep.correct}/{rep.points})")
    print("timings: " + ", ".join(f"{k}={v:.2f}s" for k, v in result.timings.items()))


if __name__ == "__main__":
    main()
