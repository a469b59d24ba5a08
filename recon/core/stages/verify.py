"""Stage `verify`: COLMAP's two-view geometry decides which matches are right.

Needs: `scene`, `pairs`, `results`, `merged`, `image_ids`. Makes: `verified` (per image-id
pair: inlier count, two-view configuration, inlier matches). Copies `OUT/cache/matches.db` to
`OUT/database.db.tmp`, runs `pycolmap.geometric_verification` there (F / E / H model
selection, seeded RANSAC, `verify_options`) and renames it to `OUT/database.db`, the database
the mapper reads. Then fills the report's per-pair rows and the track statistics of the
verified match graph.

Key: the database stage's key and every two-view option (pycolmap's `todict()`, which holds the
seed). Reused when unchanged and `database.db` can be read.
"""

from __future__ import annotations

import shutil
from typing import Any

import numpy as np
import pycolmap

from recon.config import RunConfig
from recon.core.context import Run
from recon.core.database import database_is_sound, read_verified, two_view_options, verify
from recon.core.report import PairRow, options_dict
from recon.core.sfm import threshold_scale
from recon.core.stages.database import Database, remove_db, replace_db
from recon.core.state import fingerprint
from recon.core.tracks import confirmed_counts, distinct_correspondences, track_stats


def verify_options(cfg: RunConfig, px_scale: float) -> pycolmap.TwoViewGeometryOptions:
    """Two-view options for raw wide-baseline matches (`recon.core.database.two_view_options`):
    the threshold in working px scaled to full resolution (`px_scale`, capped at 3), seeded."""
    return two_view_options(cfg.seed, max_error_px=cfg.verify.max_error_px * threshold_scale(px_scale),
                            min_num_inliers=cfg.verify.min_num_inliers)


class Verify:
    name = "verify"
    needs = ("scene", "pairs", "results", "cached", "merged", "keypoints", "image_ids")
    makes = ("verified",)

    def key(self, run: Run) -> str | None:
        options = options_dict(verify_options(run.cfg, run.px_scale()))
        run.report.colmap_options["verification"] = options
        return fingerprint("verify", run.keys.get("database"), options)

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        if not run.db_path.is_file() or not database_is_sound(run.db_path):
            return False  # a damaged database is rebuilt, even when its key matches
        try:
            run.data.verified = read_verified(run.db_path)
        except Exception:  # an unreadable database is rebuilt, never trusted
            return False
        run.report.database_reused = True
        self._rows(run)
        return True

    def run(self, run: Run) -> dict[str, Any]:
        tmp = run.db_path.with_name(run.db_path.name + ".tmp")
        advance = run.bar(None)
        try:
            remove_db(tmp)
            shutil.copyfile(Database.path(run), tmp)
            verify(tmp, verify_options(run.cfg, run.px_scale()), num_threads=run.cfg.num_workers)
        except BaseException:
            remove_db(tmp)
            raise
        replace_db(tmp, run.db_path)
        advance(done=True)
        run.data.verified = read_verified(run.db_path)
        self._rows(run)
        return {}

    @staticmethod
    def _rows(run: Run) -> None:
        """The report's pair rows and the track statistics of the verified graph."""
        d, ids = run.data, run.data.image_ids
        rows, inliers = [], []
        for (a, b), r, mm, cached in zip(d.pairs, d.results, d.merged.matches, d.cached, strict=True):
            ia, ib = ids.get(a), ids.get(b)
            n_in, conf, inl = 0, "", np.zeros((0, 2), np.uint32)
            if ia is not None and ib is not None:
                key = (min(ia, ib), max(ia, ib))
                if key in d.verified:
                    n_in, conf, inl = d.verified[key]
                    if ia > ib:  # COLMAP stores the pair with the smaller id first
                        inl = inl[:, ::-1]
            inliers.append(inl)
            bv = r.best_view
            rows.append(PairRow(
                image0=a, image1=b, reference=None if r.reference is None else (a if r.reference == 0 else b),
                best_view=None if bv is None else {"t": bv.t, "phi": bv.phi, "s": bv.s},
                raw_matches=r.num_matches, merged_matches=int(len(mm)), verified_inliers=int(n_in),
                distinct_inliers=distinct_correspondences(d.keypoints[a], d.keypoints[b], inl) if len(inl) else 0,
                two_view_config=conf, cached=bool(cached), seconds=float(r.timings.get("total", 0.0)), reason=r.reason,
                path=r.path, path_reason=r.path_reason, planned_path=r.planned_path, finishing=r.finishing))
        confirmed = confirmed_counts(d.keypoints, d.pairs, inliers)
        for row, n_conf in zip(rows, confirmed, strict=True):
            row.confirmed_inliers = n_conf
        run.report.pairs = rows
        nk = {n: len(d.keypoints[n]) for n in d.scene.names}
        any_inliers = any(len(m) for m in inliers)
        run.report.tracks = {
            "merged": track_stats(nk, d.pairs, inliers),
            "unmerged": {"num_tracks": int(sum(len(m) for m in inliers)),
                         "mean_length": 2.0 if any_inliers else 0.0, "max_length": 2 if any_inliers else 0},
            "raw_merged": track_stats(nk, d.pairs, d.merged.matches),
            "note": "connected components of the verified match graph before SfM; 'unmerged' = every "
                    "pair keeps its own keypoints (each match is its own track of length 2)",
        }
        if not any_inliers:
            run.warn("no pair passed geometric verification (too few or inconsistent matches)")
