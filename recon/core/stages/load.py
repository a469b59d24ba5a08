"""Stage `load`: find and decode the photos, skip bad ones, downscale to the working size.

Needs: nothing. Makes: `scene` (usable images with their pixel digests; skipped files with
reasons) and `grays` (working-resolution 8-bit gray images). Key: none, it always runs: the
pixel digests it computes are the content identity every later key is built from.
Options: `load.max_size`, `workers` (decoding threads); `database.camera_mode` is checked here
against the image sizes so a bad choice fails before any matching.
"""

from __future__ import annotations

from typing import Any

from recon.core.context import Run
from recon.core.scene import find_image_dir, list_candidates, scan_scene
from recon.errors import UserError


class Load:
    name = "load"
    needs: tuple[str, ...] = ()
    makes = ("scene", "grays")

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        cfg = run.cfg
        candidates, _ = list_candidates(find_image_dir(run.root))
        advance = run.bar(len(candidates))
        scene, grays = scan_scene(run.root, max_size=cfg.load.max_size or None, workers=cfg.num_workers,
                                  on_image=lambda _name: advance())
        for w in scene.warnings:
            run.warn(w)
        run.report.skipped = [{"name": s.name, "reason": s.reason} for s in scene.skipped]
        run.report.num_images = len(scene.images)
        if len(scene.images) < 2:
            raise UserError(f"{scene.image_dir}: need at least 2 usable images, found {len(scene.images)}"
                            + (f" ({len(scene.skipped)} skipped: see warnings)" if scene.skipped else ""))
        sizes = sorted({(im.width, im.height) for im in scene.images})
        if cfg.database.camera_mode == "single" and len(sizes) > 1:
            raise UserError(f"--camera-mode single needs images of one size, found "
                            f"{', '.join(f'{w}x{h}' for w, h in sizes[:4])}; use auto or per-image")
        run.data.scene, run.data.grays = scene, grays
        return None
