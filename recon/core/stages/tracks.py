"""Stage `tracks`: per-pair matches into per-image keypoints shared across pairs.

Needs: `scene`, `pairs`, `results`. Makes: `merged` (`recon.core.tracks.MergedTracks`: the
merged matches of each pair) and `keypoints` (per image, full-resolution pixels). Keypoints of
one image closer than `tracks.merge_px` working-resolution pixels become one, so a 3D point
can be seen in more than two images. Key: none, it always runs (a fraction of a second); its
output is the content the database stage's key is built from.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon.core.context import Run
from recon.core.tracks import PairMatches, merge_tracks


class Tracks:
    name = "tracks"
    needs = ("scene", "pairs", "results")
    makes = ("merged", "keypoints")

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        merge_px = run.cfg.tracks.merge_px
        scene, data = run.data.scene, run.data
        radius = {im.name: merge_px / min(im.scale_xy) for im in scene.images}
        merged = merge_tracks([PairMatches(a, b, r.kpts0, r.kpts1, r.matches, r.distances)
                               for (a, b), r in zip(data.pairs, data.results, strict=True)], radius)
        data.merged = merged
        data.keypoints = {n: merged.keypoints.get(n, np.zeros((0, 2), np.float32)) for n in scene.names}
        run.report.merge = {**merged.stats.to_dict(), "merge_px": merge_px}
        return None
