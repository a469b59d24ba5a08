"""COLMAP's stock pipeline (SIFT extraction + SIFT matching) through pycolmap, as the baseline
for `recon run`: same images, same pair selection, same cameras, same incremental mapping.

`run_stock(scene_dir, out_dir, preset="default"|"high", pairs="exhaustive", max_size=1600,
seed=0, camera_mode="auto")` returns a report dict with the keys of `recon run`'s report.json
where they apply (see `recon.core.report.RunReport`) plus `method`, `preset`, `verified_pairs`,
`inliers_per_pair_mean` / `_median`, `num_keypoints_mean` and the COLMAP options used, and writes
`OUT/database.db`, `OUT/sparse/0` (when a model is found) and `OUT/report.json`.

What is shared with `recon run` (so only the features and matches differ):

* images: `recon.core.scene.scan_scene` (unreadable, tiny and duplicate photos skipped the same way);
* cameras: `recon.core.database.import_scene_images` fills the database first (same camera model,
  same `--camera-mode auto` rule, same EXIF / 1.2 * max(w, h) focal prior);
  `pycolmap.extract_features` then finds the images already there and only adds keypoints and
  descriptors (no new cameras, rigs or frames);
* pairs: `recon.core.pairs` (`exhaustive` -> `pycolmap.match_exhaustive`; `sequential:K` and pairs
  files -> the same pair list written to `OUT/pairs.txt` and `pycolmap.match_image_pairs`, so
  the pairs are exactly those `recon run` matches. COLMAP's own sequential matcher would also
  add quadratic-overlap pairs);
* mapping: `recon.core.sfm.mapping_options` with the same working-to-full-resolution `px_scale`
  (COLMAP's SIFT runs on the image downscaled to `max_size` and writes keypoints in full-
  resolution pixels, exactly like our matcher), `recon.core.sfm.run_incremental`.

Presets. `default`: COLMAP's SIFT defaults with `FeatureExtractionOptions.max_image_size =
max_size`. `high`: also `sift.estimate_affine_shape` and `sift.domain_size_pooling` (COLMAP's
covariant-detector path: slower, more robust to viewpoint change) and
`FeatureMatchingOptions.guided_matching` (a second matching pass constrained by the estimated
two-view geometry). pycolmap 4 moved `max_image_size` from SiftExtractionOptions to
FeatureExtractionOptions and `guided_matching` from SiftMatchingOptions to FeatureMatchingOptions.

Two-view verification is COLMAP's default (`TwoViewGeometryOptions()`, 4 px RANSAC threshold at
full resolution) with the RANSAC seeded; matching and verification are one call in COLMAP, so they
are one stage (`match`) here.

A run that finds no model is not an error: the report has status "no_model" and a message. A
COLMAP failure (an exception from pycolmap) gives status "failed" with the message. Only a
missing scene folder or a bad argument raises (InputError / UserError / ValueError).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pycolmap

from matching.errors import InputError

from recon.core import sfm
from matching.memory import PeakRss
from recon.errors import UserError
from recon.core.database import CAMERA_MODES, import_scene_images, read_verified
from recon.core.pairs import make_pairs, parse_pairs_spec
from recon.core.outdir import remove_outputs
from recon.core.pipeline import _Stages
from recon.core.progress import quiet_colmap
from recon.core.report import PairRow, RunReport, write_json_atomic
from recon.core.scene import scan_scene
from recon.core.tracks import track_stats

Preset = Literal["default", "high"]
PRESETS: tuple[str, ...] = ("default", "high")
METHOD = "colmap-sift"
STOCK_OUTPUTS = ("database.db", "database.db.tmp", "database.db-journal", "database.db-wal", "database.db-shm",
                 "database.db.tmp-journal", "database.db.tmp-wal", "database.db.tmp-shm",
                 "sparse", "pairs.txt", "report.json")


# options ----------------------------------------------------------------------------------------
def extraction_options(preset: str = "default", max_size: int = 1600, num_threads: int = -1
                       ) -> pycolmap.FeatureExtractionOptions:
    o = pycolmap.FeatureExtractionOptions()
    o.max_image_size = int(max_size) if max_size else -1  # 0 = full resolution, as in recon run
    o.num_threads = int(num_threads)
    o.use_gpu = False
    if preset == "high":
        o.sift.estimate_affine_shape = True
        o.sift.domain_size_pooling = True
    return o


def matching_options(preset: str = "default", num_threads: int = -1) -> pycolmap.FeatureMatchingOptions:
    o = pycolmap.FeatureMatchingOptions()
    o.num_threads = int(num_threads)
    o.use_gpu = False
    if preset == "high":
        o.guided_matching = True
    return o


def verification_options(seed: int = 0) -> pycolmap.TwoViewGeometryOptions:
    o = pycolmap.TwoViewGeometryOptions()  # COLMAP's defaults ...
    o.ransac.random_seed = int(seed)  # ... seeded
    return o


def options_summary(eo: pycolmap.FeatureExtractionOptions, mo: pycolmap.FeatureMatchingOptions,
                    vo: pycolmap.TwoViewGeometryOptions) -> dict[str, Any]:
    return dict(
        max_image_size=eo.max_image_size, max_num_features=eo.sift.max_num_features,
        estimate_affine_shape=eo.sift.estimate_affine_shape, domain_size_pooling=eo.sift.domain_size_pooling,
        peak_threshold=eo.sift.peak_threshold, max_ratio=mo.sift.max_ratio, max_distance=mo.sift.max_distance,
        cross_check=mo.sift.cross_check, guided_matching=mo.guided_matching,
        max_num_matches=mo.max_num_matches, ransac_max_error=vo.ransac.max_error,
        min_num_inliers=vo.min_num_inliers, ransac_random_seed=vo.ransac.random_seed,
    )


# helpers ----------------------------------------------------------------------------------------
def _remove_own_outputs(out: Path) -> None:
    remove_outputs(out, STOCK_OUTPUTS)


def _write_pairs_file(path: Path, pairs: list[tuple[str, str]]) -> tuple[list[tuple[str, str]], list[str]]:
    """COLMAP's pairs list (one `name0 name1` per line). COLMAP splits lines at spaces, so pairs
    naming an image with whitespace in its name cannot be imported: dropped with a warning."""
    ok = [(a, b) for a, b in pairs if not any(c.isspace() for c in a + b)]
    warnings = []
    if len(ok) < len(pairs):
        warnings.append(f"dropped {len(pairs) - len(ok)} pair(s) naming images with spaces in their names "
                        f"(COLMAP's pairs list cannot hold them)")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text("".join(f"{a} {b}\n" for a, b in ok), encoding="utf-8")
    os.replace(tmp, path)
    return ok, warnings


def _read_db_counts(db_path: Path, ids: dict[str, int], pairs: list[tuple[str, str]]
                    ) -> tuple[dict[str, int], list[int]]:
    """({name: number of keypoints}, raw matches per pair) from the database."""
    db = pycolmap.Database.open(str(db_path))
    try:
        nk = {n: int(db.num_keypoints_for_image(i)) if db.exists_keypoints(i) else 0 for n, i in ids.items()}
        raw = []
        for a, b in pairs:
            ia, ib = ids.get(a), ids.get(b)
            if ia is None or ib is None or not db.exists_matches(ia, ib):
                raw.append(0)
            else:
                raw.append(int(len(db.read_matches(ia, ib))))
    finally:
        db.close()
    return nk, raw


# the run ----------------------------------------------------------------------------------------
def run_stock(scene_dir: str | Path, out_dir: str | Path, preset: Preset = "default", pairs: str = "exhaustive",
              max_size: int = 1600, seed: int = 0, camera_mode: str = "auto", workers: int = 0,
              on_stage: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Reconstruct `scene_dir` with COLMAP's own SIFT pipeline into `out_dir` (see module doc).

    `workers`: COLMAP threads (0 = all cores). `on_stage(name)` is called as each stage starts.
    Our own files in `out_dir` (database.db, sparse/, pairs.txt, report.json) are replaced.
    """
    if preset not in PRESETS:
        raise ValueError(f"stock preset {preset!r}: choose one of {', '.join(PRESETS)}")
    if camera_mode not in CAMERA_MODES:
        raise UserError(f"camera mode {camera_mode!r}: choose one of {', '.join(CAMERA_MODES)}")
    if not isinstance(max_size, int) or (max_size != 0 and max_size < 64):
        raise UserError(f"max size {max_size}: use 0 (full resolution) or at least 64 px")
    try:
        spec = parse_pairs_spec(pairs)
    except ValueError as e:
        raise UserError(str(e)) from None
    t_start = time.perf_counter()
    threads = int(workers) if workers > 0 else -1
    root = Path(scene_dir).expanduser()
    if not root.is_dir():
        raise InputError(f"{root}: no such scene folder")
    root = root.resolve()
    out = Path(out_dir).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    _remove_own_outputs(out)

    config = dict(method=METHOD, preset=preset, pairs=str(spec), max_size=max_size, seed=seed,
                  camera_mode=camera_mode, workers=workers, out=str(out))
    report = RunReport(scene=str(root), out=str(out), config=config)
    eo, mo, vo = extraction_options(preset, max_size, threads), matching_options(preset, threads), verification_options(seed)
    extra: dict[str, Any] = dict(method=METHOD, preset=preset, colmap_options=options_summary(eo, mo, vo),
                                 verified_pairs=0, inliers_per_pair_mean=0.0, inliers_per_pair_median=0.0,
                                 num_keypoints_mean=0.0, peak_growth_mb=None)
    stages = _Stages()
    db_path, db_tmp = out / "database.db", out / "database.db.tmp"
    rec = None

    def stage(name: str):
        if on_stage is not None:
            on_stage(name)
        return stages(name)

    def finish(status: str, message: str = "") -> dict[str, Any]:
        report.status, report.message = status, message
        report.stages = {k: round(v, 3) for k, v in stages.times.items()}
        report.seconds_total = round(time.perf_counter() - t_start, 3)
        d = report.to_dict()
        d.update(extra)
        write_json_atomic(out / "report.json", d)
        return d

    with PeakRss() as mem, quiet_colmap():
        try:
            # load: the same usable images as recon run ------------------------------------------
            with stage("load"):
                scene, grays = scan_scene(root, max_size=max_size or None, workers=max(1, os.cpu_count() or 1))
                del grays
            report.skipped = [{"name": s.name, "reason": s.reason} for s in scene.skipped]
            report.warnings.extend(scene.warnings)
            report.num_images = len(scene.images)
            if len(scene.images) < 2:
                report.peak_mb = round(mem.total_mb or 0.0, 1)
                return finish("no_model", f"{scene.image_dir}: need at least 2 usable images, found {len(scene.images)}")
            names = scene.names
            pair_list, pw = make_pairs(spec, names)
            report.warnings.extend(pw)

            # database: cameras and images exactly as recon run imports them ---------------------
            with stage("database"):
                ids, used_mode, missing = import_scene_images(db_tmp, scene.image_dir, names, camera_mode)
            report.camera_mode_used = used_mode
            for n in missing:
                report.skipped.append({"name": n, "reason": "COLMAP could not read the image"})
                report.warnings.append(f"skipped {n}: COLMAP could not read the image")
            names = [n for n in names if n in ids]

            with stage("extract"):
                pycolmap.extract_features(str(db_tmp), str(scene.image_dir), image_names=names,
                                          camera_mode=pycolmap.CameraMode.AUTO,  # images exist: unused
                                          extraction_options=eo, device=pycolmap.Device.cpu)

            with stage("match"):  # COLMAP matches and verifies in one call
                if spec.kind == "exhaustive":
                    pair_list = [(a, b) for a, b in pair_list if a in ids and b in ids]
                    pycolmap.match_exhaustive(str(db_tmp), matching_options=mo,
                                              pairing_options=pycolmap.ExhaustivePairingOptions(),
                                              verification_options=vo, device=pycolmap.Device.cpu)
                else:
                    pair_list = [(a, b) for a, b in pair_list if a in ids and b in ids]
                    pair_list, w = _write_pairs_file(out / "pairs.txt", pair_list)
                    report.warnings.extend(w)
                    po = pycolmap.ImportedPairingOptions()
                    po.match_list_path = str(out / "pairs.txt")
                    pycolmap.match_image_pairs(str(db_tmp), matching_options=mo, pairing_options=po,
                                               verification_options=vo, device=pycolmap.Device.cpu)
            os.replace(db_tmp, db_path)

            # pair rows: raw matches and COLMAP's verified inliers --------------------------------
            verified = read_verified(db_path)
            nk, raw = _read_db_counts(db_path, ids, pair_list)
            rows, inliers = [], []
            for (a, b), n_raw in zip(pair_list, raw):
                ia, ib = ids[a], ids[b]
                n_in, conf, inl = verified.get((min(ia, ib), max(ia, ib)), (0, "", np.zeros((0, 2), np.uint32)))
                if ia > ib:
                    inl = inl[:, ::-1]
                inliers.append(inl)
                rows.append(PairRow(image0=a, image1=b, raw_matches=n_raw, merged_matches=n_raw,
                                    verified_inliers=int(n_in), config=conf))
            report.pairs = rows
            report.pairs_computed = len(rows)
            counts = [r.verified_inliers for r in rows if r.verified_inliers > 0]
            extra.update(verified_pairs=len(counts),
                         inliers_per_pair_mean=float(np.mean(counts)) if counts else 0.0,
                         inliers_per_pair_median=float(np.median(counts)) if counts else 0.0,
                         num_keypoints_mean=float(np.mean(list(nk.values()))) if nk else 0.0,
                         num_keypoints=nk)
            report.tracks = {
                "graph": track_stats(nk, pair_list, inliers),
                "note": "connected components of COLMAP's verified match graph before SfM (stock SIFT "
                        "keypoints are per image, so tracks span several images without merging)",
            }
            if not counts:
                report.warnings.append("no pair passed geometric verification (too few or inconsistent matches)")

            # sfm: the same incremental mapping options as recon run ------------------------------
            px_scale = float(np.mean([1.0 / min(im.scale_xy) for im in scene.images if im.name in ids]))
            opts = sfm.mapping_options(seed, sfm.MAPPING_THREADS, px_scale)
            report.sfm_options = sfm.options_summary(opts)
            with stage("sfm"):
                res = sfm.run_incremental(db_path, scene.image_dir, opts)
            rec = res.reconstruction
            report.num_models, report.model_sizes = res.num_models, res.model_sizes
            report.sfm_growth = res.growth

            with stage("export"):
                report.set_model(sfm.model_stats(rec), sfm.registered_names(rec))
                if rec is not None and rec.num_points3D() > 0:
                    sfm.write_model_atomic(rec, out / "sparse" / "0")
        except (InputError, UserError):
            raise
        except Exception as e:  # a COLMAP failure is a result of the baseline, not a crash
            for p in (db_tmp,):
                p.unlink(missing_ok=True)
            report.peak_mb = round(mem.total_mb or 0.0, 1)
            return finish("failed", f"COLMAP failed: {type(e).__name__}: {e}")
    report.peak_mb = round(mem.total_mb or 0.0, 1)
    extra["peak_growth_mb"] = None if mem.peak_mb is None else round(mem.peak_mb, 1)
    if rec is None or rec.num_points3D() == 0:
        n_ok = int(extra["verified_pairs"])
        return finish("no_model", f"stock COLMAP found no model ({n_ok} of {len(report.pairs)} pairs passed "
                                  f"geometric verification, and incremental mapping could not initialise a "
                                  f"model from them); the database and report are kept in {out}")
    unregistered = [n for n in names if n not in set(report.registered)]
    if unregistered:
        shown = ", ".join(unregistered[:5]) + (" ..." if len(unregistered) > 5 else "")
        report.warnings.append(f"{len(unregistered)} of {len(names)} images not registered: {shown}")
    return finish("ok")
