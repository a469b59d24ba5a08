"""COLMAP's stock pipeline (SIFT extraction + SIFT matching) through pycolmap, as the baseline
for `recon run`: same images, same pair selection, same cameras, same incremental mapping.

`run_stock(scene_dir, out_dir, preset="default"|"high", pairs="exhaustive", max_size,
seed=0, camera_mode="auto")` runs the SAME orchestrator as `recon run`
(`recon.core.orchestrator.run_stages`) with COLMAP's own stages in place of ours and returns the
same `RunReport` (also `OUT/report.json`), with `method` "colmap-sift", `preset`, and the COLMAP
options used in `colmap_options` (`extraction`, `matching`, `verification`). It writes
`OUT/database.db`, `OUT/sparse/0` (when a model is found) and `OUT/report.json`, replacing its
own earlier files (no resuming: every run starts fresh).

Stages (see `recon.core.stages` for the shared ones):

* `load`, `pairs`: ours (unreadable, tiny and duplicate photos skipped the same way; the same
  pair list);
* `database` (`StockDatabase`): cameras and images exactly as `recon run` imports them
  (`recon.core.database.import_scene_images`: same camera model, same `--camera-mode auto`
  rule, same EXIF / 1.2 * max(w, h) focal prior), into `database.db.tmp`;
* `features` (`StockFeatures`): `pycolmap.extract_features`, which finds the images already
  there and only adds keypoints and descriptors (no new cameras, rigs or frames);
* `match` (`StockMatch`): `exhaustive` -> `pycolmap.match_exhaustive`; `sequential:K` and pairs
  files -> the same pair list written to `OUT/pairs.txt` and `pycolmap.match_image_pairs`, so
  the pairs are exactly those `recon run` matches (COLMAP's own sequential matcher would also
  add quadratic-overlap pairs). COLMAP matches and verifies in one call, so there is no
  separate `verify` stage (and no `tracks`: stock keypoints are per image already);
* `sfm`, `export`: ours (`recon.core.stages.sfm.mapping_options`: the same mapper options and
  pixel thresholds, COLMAP's full-resolution ones unless `sfm.scale_thresholds`, and the same
  final robust adjustment, `recon.core.sfm.final_bundle_adjustment`; COLMAP's SIFT
  runs on the image downscaled to `max_size` and writes keypoints in full-resolution pixels,
  exactly like our matcher), without points.ply.

Presets. `default`: COLMAP's SIFT defaults with `FeatureExtractionOptions.max_image_size =
max_size`. `high`: also `sift.estimate_affine_shape` and `sift.domain_size_pooling` (COLMAP's
covariant-detector path: slower, more robust to viewpoint change) and
`FeatureMatchingOptions.guided_matching` (a second matching pass constrained by the estimated
two-view geometry). pycolmap 4 moved `max_image_size` from SiftExtractionOptions to
FeatureExtractionOptions and `guided_matching` from SiftMatchingOptions to FeatureMatchingOptions.
Two-view verification is COLMAP's default (`TwoViewGeometryOptions()`, 4 px RANSAC threshold at
full resolution) with the RANSAC seeded.

Error contract (the same as `recon run`): an unusable scene or a bad argument raises InputError
/ UserError; a run that finds no model returns a report with status "no_model" and a message.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pycolmap

from matching.errors import InputError
from recon.config import DEFAULT_MAX_SIZE, RunConfig, SfmConfig
from recon.core.context import Run
from recon.core.database import import_scene_images, read_keypoints_opencv, read_verified
from recon.core.observer import RunObserver, as_observer
from recon.core.orchestrator import run_stages
from recon.core.outdir import remove_outputs
from recon.core.report import PairRow, RunReport, options_dict
from recon.core.stages import Export, Load, Pairs, Sfm
from recon.core.stages.database import remove_db, replace_db
from recon.core.state import StageState
from recon.core.tracks import distinct_correspondences, track_stats
from recon.errors import UserError

Preset = Literal["default", "high"]
PRESETS: tuple[str, ...] = ("default", "high")
METHOD = "colmap-sift"
STOCK_OUTPUTS = ("database.db", "database.db.tmp", "database.db-journal", "database.db-wal", "database.db-shm",
                 "database.db.tmp-journal", "database.db.tmp-wal", "database.db.tmp-shm",
                 "sparse", "pairs.txt", "report.json")


# options ----------------------------------------------------------------------------------------
def extraction_options(preset: str = "default", max_size: int = DEFAULT_MAX_SIZE, num_threads: int = -1
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


def _threads(run: Run) -> int:
    return int(run.cfg.workers) if run.cfg.workers > 0 else -1  # COLMAP: -1 = all cores


def _db_tmp(run: Run) -> Path:
    return run.db_path.with_name(run.db_path.name + ".tmp")


# helpers ----------------------------------------------------------------------------------------
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


# stages -----------------------------------------------------------------------------------------
class _Always:
    """A stage without a key: it always runs."""

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False


class StockDatabase(_Always):
    """Cameras and images exactly as `recon run` imports them, into `database.db.tmp`."""

    name = "database"
    needs = ("scene",)
    makes = ("image_ids",)

    def run(self, run: Run) -> None:
        tmp = _db_tmp(run)
        remove_db(tmp)
        ids, used, missing = import_scene_images(tmp, run.image_dir, run.data.scene.names, run.cfg.database.camera_mode)
        run.data.image_ids = ids
        run.report.camera_mode_used = used
        for n in missing:
            run.report.skipped.append({"name": n, "reason": "COLMAP could not read the image"})
            run.warn(f"skipped {n}: COLMAP could not read the image")
        return None


class StockFeatures(_Always):
    """COLMAP's SIFT extraction (`pycolmap.extract_features`) of the imported images."""

    name = "features"
    needs = ("scene", "image_ids")
    makes: tuple[str, ...] = ()

    def __init__(self, preset: str) -> None:
        self.preset = preset

    def run(self, run: Run) -> None:
        eo = extraction_options(self.preset, run.cfg.load.max_size, _threads(run))
        run.report.colmap_options["extraction"] = options_dict(eo)
        names = [n for n in run.data.scene.names if n in run.data.image_ids]
        pycolmap.extract_features(str(_db_tmp(run)), str(run.image_dir), image_names=names,
                                  camera_mode=pycolmap.CameraMode.AUTO,  # images exist: unused
                                  extraction_options=eo, device=pycolmap.Device.cpu)
        return None


class StockMatch(_Always):
    """COLMAP's SIFT matching and two-view verification (one call), then the pair rows."""

    name = "match"
    needs = ("scene", "pairs", "image_ids")
    makes = ("verified", "num_keypoints")

    def __init__(self, preset: str) -> None:
        self.preset = preset

    def run(self, run: Run) -> None:
        ids, db_tmp = run.data.image_ids, _db_tmp(run)
        mo, vo = matching_options(self.preset, _threads(run)), verification_options(run.cfg.seed)
        run.report.colmap_options.update(matching=options_dict(mo), verification=options_dict(vo))
        pairs = [(a, b) for a, b in run.data.pairs if a in ids and b in ids]
        if run.cfg.pairs.spec == "exhaustive":
            pycolmap.match_exhaustive(str(db_tmp), matching_options=mo,
                                      pairing_options=pycolmap.ExhaustivePairingOptions(),
                                      verification_options=vo, device=pycolmap.Device.cpu)
        else:
            if "expand:" in run.cfg.pairs.spec:
                run.warn(f"--pairs {run.cfg.pairs.spec}: stock COLMAP matches the proposed pairs only "
                         f"(match-graph expansion is recon's)")
            pairs, warnings = _write_pairs_file(run.out / "pairs.txt", pairs)
            for w in warnings:
                run.warn(w)
            po = pycolmap.ImportedPairingOptions()
            po.match_list_path = str(run.out / "pairs.txt")
            pycolmap.match_image_pairs(str(db_tmp), matching_options=mo, pairing_options=po,
                                       verification_options=vo, device=pycolmap.Device.cpu)
        replace_db(db_tmp, run.db_path)
        run.data.pairs = pairs
        run.data.verified = read_verified(run.db_path)
        nk, raw = _read_db_counts(run.db_path, ids, pairs)
        run.data.num_keypoints = nk
        kpts = {n: read_keypoints_opencv(run.db_path, i) for n, i in ids.items()}
        rows, inliers = [], []
        for (a, b), n_raw in zip(pairs, raw, strict=True):
            ia, ib = ids[a], ids[b]
            n_in, conf, inl = run.data.verified.get((min(ia, ib), max(ia, ib)), (0, "", np.zeros((0, 2), np.uint32)))
            if ia > ib:
                inl = inl[:, ::-1]
            inliers.append(inl)
            rows.append(PairRow(image0=a, image1=b, raw_matches=n_raw, merged_matches=n_raw,
                                verified_inliers=int(n_in), two_view_config=conf,
                                distinct_inliers=distinct_correspondences(kpts[a], kpts[b], inl)))
        run.report.pairs = rows
        run.report.pairs_computed = len(rows)
        run.report.num_keypoints = nk
        run.report.tracks = {
            "graph": track_stats(nk, pairs, inliers),
            "note": "connected components of COLMAP's verified match graph before SfM (stock SIFT "
                    "keypoints are per image, so tracks span several images without merging)",
        }
        if not any(r.verified_inliers > 0 for r in rows):
            run.warn("no pair passed geometric verification (too few or inconsistent matches)")
        return None


def stock_stages(preset: str) -> list[Any]:
    """The stages of the stock comparison, in order (see module doc)."""
    return [Load(), Pairs(), StockDatabase(), StockFeatures(preset), StockMatch(preset), Sfm(),
            Export(ply=False, who="stock COLMAP")]


# the run ----------------------------------------------------------------------------------------
def run_stock(scene_dir: str | Path, out_dir: str | Path, preset: Preset = "default", pairs: str = "exhaustive",
              max_size: int = DEFAULT_MAX_SIZE, seed: int = 0, camera_mode: str = "auto", workers: int = 0,
              observer: RunObserver | Sequence[RunObserver] | None = None, progress: bool = False,
              sfm: SfmConfig | None = None) -> RunReport:
    """Reconstruct `scene_dir` with COLMAP's own SIFT pipeline into `out_dir` (see module doc).

    `workers`: COLMAP threads (0 = all cores). `observer`: the run's events, as for `run_scene`.
    `sfm`: the mapping options (default: `recon run`'s; `recon compare` passes ours).
    Our own files in `out_dir` (database.db, sparse/, pairs.txt, report.json) are replaced.
    """
    if preset not in PRESETS:
        raise UserError(f"stock preset {preset!r}: choose one of {', '.join(PRESETS)}")
    cfg = RunConfig.from_options(out=out_dir, pairs=pairs, max_size=max_size, seed=seed, camera_mode=camera_mode,
                                 workers=workers, progress=progress)
    if sfm is not None:
        cfg.sfm = sfm
    root = Path(scene_dir).expanduser()
    if not root.is_dir():
        raise InputError(f"{root}: no such scene folder")
    root = root.resolve()
    out = Path(out_dir).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    remove_outputs(out, STOCK_OUTPUTS)
    report = RunReport(scene=str(root), out=str(out), config=cfg.to_dict(), method=METHOD, preset=preset)
    run = Run(cfg, root, out, report, as_observer(observer), StageState(None))
    return run_stages(run, stock_stages(preset))
