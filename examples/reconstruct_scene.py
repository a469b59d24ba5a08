"""Render a small extreme-viewpoint scene and reconstruct it, from Python.

    .venv/bin/python examples/reconstruct_scene.py [OUT_DIR]

The same as `recon render-scene OUT/scene` followed by `recon run OUT/scene --out OUT/recon`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from recon.core.pipeline import RunConfig, run_scene
from scenes.render import render_scene


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/example")
    scene = render_scene(out / "scene", preset="corner", seed=0, overwrite=True)
    print(f"rendered {len(scene.image_paths)} images into {scene.out_dir}")
    report = run_scene(scene.out_dir, RunConfig.from_options(out=out / "recon", overwrite=True))
    print(f"registered {report.registered_images}/{report.num_images} images, "
          f"{report.num_points3D} points, mean track length {report.mean_track_length:.2f}")


if __name__ == "__main__":
    main()
