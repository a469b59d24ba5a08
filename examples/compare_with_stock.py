"""Compare the extra-affine pipeline with COLMAP's stock matching on a rendered wide-baseline
scene, from Python, and record both models in one Rerun file.

    .venv/bin/python examples/compare_with_stock.py [OUT_DIR]

The same as `recon render-scene OUT/scene --preset facade-extreme` followed by
`recon compare OUT/scene --out OUT/compare --stock-presets default,high`; open the recording
with `recon view OUT/compare`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from recon.eval.compare import compare_scene, load_gt
from recon.viz.compare_rerun import COMPARE_RECORDING, log_comparison
from recon.viz.rerun_log import Sink
from scenes.render import render_scene


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/example-compare")
    scene = render_scene(out / "scene", preset="facade-extreme", seed=0, overwrite=True)
    res = compare_scene(scene.out_dir, out / "compare", presets=("default", "high"))
    for name, m in res["methods"].items():
        rot = m.get("rel_rot_err_deg_median")
        print(f"{name:14s} registered {m['registered_images']}/{m['num_images']}, "
              f"rotation error {'-' if rot is None else f'{rot:.2f} deg'}, "
              f"{m.get('inliers_per_pair_mean', 0):.0f} verified inliers per pair")
    gt, _, _ = load_gt(scene.out_dir)
    saved = log_comparison(Sink("save", str(out / "compare" / COMPARE_RECORDING)), res, gt)
    print(f"recording: {saved}")


if __name__ == "__main__":
    main()
