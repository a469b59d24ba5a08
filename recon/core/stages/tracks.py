"""Stage `tracks`: per-pair matches into per-image keypoints shared across pairs.

Needs: `scene`, `pairs`, `results`. Makes: `merged` (`recon.core.tracks.MergedTracks`: the
merged matches of each pair) and `keypoints` (per image, full-resolution pixels). Keypoints of
one image closer than `tracks.merge_px` working-resolution pixels become one, so a 3D point
can be seen in more than two images. With `tracks.consistent` (the default) the matches that
would chain two keypoints of one image into one track are then dropped, most trusted first
(`recon.core.tracks.consistent_tracks`; trust = fitting the pair's fundamental matrix within
`tracks.trust_px`, `epipolar_inliers`). With `tracks.refine` (the default) every consistent
track's observations are then re-localised against its anchor observation by patch alignment
(`recon.core.track_refine`; the images come from the feature store). Key: none, it always runs
(seconds to a minute); its output is the content the database stage's key is built from.
`report.merge` gets the merge counts, the dropped conflicts, the share of observations in
inconsistent tracks before the check and the refinement's counts (`track_refine`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from matching.refine import RefineConfig
from recon.core.context import Run
from recon.core.sfm import threshold_scale
from recon.core.track_refine import refine_tracks
from recon.core.tracks import PairMatches, consistent_tracks, epipolar_inliers, merge_tracks, track_stats


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
        nk = {n: len(k) for n, k in merged.keypoints.items()}
        before = track_stats(nk, merged.pairs, merged.matches)["inconsistent_share"]
        if run.cfg.tracks.consistent:
            max_error_px = run.cfg.tracks.trust_px * threshold_scale(run.px_scale())  # as the verify stage
            merged = consistent_tracks(merged, epipolar_inliers(merged, max_error_px, run.cfg.seed),
                                       run.cfg.tracks.conflict_order)
        refine_stats = None
        if run.cfg.tracks.consistent and run.cfg.tracks.refine and data.store is not None:
            images = {im.name: data.store.image(im.name) for im in scene.images if im.name in merged.keypoints}
            scales = {im.name: im.scale_xy for im in scene.images}
            keypoints, refine_stats = refine_tracks(merged, images, scales,
                                                    RefineConfig(robust_rounds=run.cfg.tracks.refine_robust_rounds),
                                                    workers=max(1, run.cfg.num_workers), progress=_bar(run, "refine"))
            merged = dataclasses.replace(merged, keypoints=keypoints)
        data.merged = merged
        data.keypoints = {n: merged.keypoints.get(n, np.zeros((0, 2), np.float32)) for n in scene.names}
        run.report.merge = {**merged.stats.to_dict(), "merge_px": merge_px, "consistent": run.cfg.tracks.consistent,
                            "inconsistent_share_merged": before,
                            "track_refine": refine_stats.to_dict() if refine_stats else None}
        return None


def _bar(run: Run, part: str) -> Callable[[int, int], None]:
    """A `progress(done, total)` callback drawing the stage's bar, made at the first call (when
    the total is known)."""
    state: dict[str, Any] = {}

    def progress(done: int, total: int) -> None:
        if "advance" not in state:
            state["advance"], state["done"] = run.bar(total, part), 0
        state["advance"](done - state["done"])
        state["done"] = done

    return progress
