"""Stage `database`: cameras, images, merged keypoints and raw matches in a COLMAP database.

Needs: `scene`, `store`, `pairs`, `merged`, `keypoints`. Makes: `image_ids` (COLMAP's id per image
name) and `num_keypoints`. Writes `OUT/cache/matches.db` (through `matches.db.tmp` and a
rename): cameras from EXIF (`database.camera_mode`), images, keypoints (+0.5 for COLMAP's pixel
centres), for the SIFT-based methods SIFT descriptors of the original photos at those keypoints
(`recon.core.descriptors`: what COLMAP's own matchers need to add photos later) and *all* the
matcher's matches, before verification (the verify stage works on a copy). See
`recon.core.database`.

Key: the camera mode and model, every image's name and pixel digest, the merged keypoints, the pairs and
their merged matches. Reused when unchanged and `matches.db` exists (the image ids, the camera
mode used and the images COLMAP could not read come back from the state record).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from recon.core.context import Run
from recon.core.database import CAMERA_MODELS, database_is_sound, import_scene_images, write_keypoints_and_matches
from recon.core.state import fingerprint

if TYPE_CHECKING:
    from matching.features import DetectorConfig
    from recon.config import MatchConfig

SQLITE_SIDE_FILES = ("-journal", "-wal", "-shm")


def remove_db(path: Path) -> None:
    """A database file and its sqlite side files, if present."""
    for p in [path, *(Path(f"{path}{s}") for s in SQLITE_SIDE_FILES)]:
        p.unlink(missing_ok=True)


def replace_db(tmp: Path, path: Path) -> None:
    """Rename a finished database (and any sqlite side file) over `path`."""
    for suffix in SQLITE_SIDE_FILES:  # a closed sqlite db leaves none; be safe
        side = Path(f"{tmp}{suffix}")
        if side.exists():
            os.replace(side, Path(f"{path}{suffix}"))
    os.replace(tmp, path)


def with_descriptors(run: Run) -> bool:
    """Whether this run's matcher is SIFT-based, so its database gets SIFT descriptors."""
    from recon.core.descriptors import SIFT_METHODS

    return (run.report.method or run.cfg.match.method) in SIFT_METHODS


def descriptor_detector(cfg: MatchConfig, num_images: int | None) -> DetectorConfig:
    """The OpenCV SIFT set of each original whose descriptors the database takes
    (`recon.core.descriptors`): the one the matcher has in the feature store already (a resumed
    run finds it in the feature cache). By default the reference decision's, OpenCV's default
    SIFT; under `--simulate needed` (or `auto` on a large scene: `simulate_mode` of
    `num_images`) with OpenCV's SIFT in the first pass, that pass's set (a lower contrast
    threshold: the default set's keypoints and more), which every image has, where the default
    set would be a second detection of every image that no pair simulates (unless that set is
    RootSIFT: the database roots plain descriptors itself)."""
    from matching.features import DetectorConfig
    from recon.core.stages.match import first_pass_overrides, make_matcher, simulate_mode

    if simulate_mode(cfg, num_images) == "needed" and cfg.first_pass_detector == "sift":
        det: DetectorConfig = make_matcher(cfg, extra=first_pass_overrides(cfg)).cfg.fine.originals_detector  # type: ignore[attr-defined]
        if not det.root_sift:
            return det
    return DetectorConfig("sift")


def write_sift_descriptors(run: Run, db_path: Path, ids: dict[str, int]) -> None:
    """SIFT descriptors of the original photos at each image's keypoints, one row per keypoint
    (`recon.core.descriptors`), as COLMAP's SIFT descriptors, from the originals' SIFT set in the
    feature store (`descriptor_detector`)."""
    import pycolmap

    from matching.viewfeatures import original_features
    from recon.core.descriptors import sift_descriptors

    d = run.data
    det = descriptor_detector(run.cfg.match, len(d.scene.images))
    db = pycolmap.Database.open(str(db_path))
    try:
        with pycolmap.DatabaseTransaction(db):
            for name, iid in ids.items():
                im = d.scene.image(name)
                desc, _ = sift_descriptors(d.store.image(name), d.keypoints[name], im.scale_xy,
                                           original_features(d.store, name, det))
                db.write_descriptors(iid, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, desc))
    finally:
        db.close()


class Database:
    name = "database"
    needs = ("scene", "store", "pairs", "merged", "keypoints")
    makes = ("image_ids", "num_keypoints")

    @staticmethod
    def path(run: Run) -> Path:
        return run.cache / "matches.db"

    def key(self, run: Run) -> str | None:
        d = run.data
        model = run.cfg.database.camera_model  # in the key only when not the default: older caches stay valid
        from matching.features import DetectorConfig

        det = descriptor_detector(run.cfg.match, len(d.scene.images))  # named only when not the default: older caches stay valid
        descriptors = ["sift-descriptors-1"] + ([det.key] if det != DetectorConfig("sift") else [])
        extra = ([model] if model != CAMERA_MODELS[0] else []) + (descriptors if with_descriptors(run) else [])
        return fingerprint("database", run.cfg.database.camera_mode, *extra,
                           [(im.name, im.digest) for im in d.scene.images],
                           *[d.keypoints[n] for n in d.scene.names], d.pairs, *d.merged.matches)

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        if not self.path(run).is_file() or not record.get("image_ids") or not database_is_sound(self.path(run)):
            return False  # a damaged database is rebuilt, even when its key matches
        self._done(run, {k: int(v) for k, v in record["image_ids"].items()}, record.get("camera_mode_used", ""),
                   list(record.get("missing", [])))
        return True

    def run(self, run: Run) -> dict[str, Any]:
        d, path = run.data, self.path(run)
        tmp = path.with_name(path.name + ".tmp")
        advance = run.bar(len(d.scene.names) + len(d.pairs))
        try:
            ids, used, missing = import_scene_images(tmp, run.image_dir, d.scene.names, run.cfg.database.camera_mode,
                                                     run.cfg.database.camera_model)
            write_keypoints_and_matches(tmp, ids, d.keypoints, d.pairs, d.merged.matches, on_item=lambda: advance())
            if with_descriptors(run):
                write_sift_descriptors(run, tmp, ids)
        except BaseException:
            remove_db(tmp)
            raise
        replace_db(tmp, path)
        self._done(run, ids, used, missing)
        return {"image_ids": ids, "camera_mode_used": used, "missing": missing}

    @staticmethod
    def _done(run: Run, ids: dict[str, int], used: str, missing: list[str]) -> None:
        run.data.image_ids = ids
        run.data.num_keypoints = {n: int(len(run.data.keypoints[n])) for n in run.data.scene.names if n in ids}
        run.report.camera_mode_used = used
        for n in missing:
            reason = "COLMAP could not read the image"
            run.report.skipped.append({"name": n, "reason": reason})
            run.warn(f"skipped {n}: {reason}")
