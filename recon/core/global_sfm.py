"""Global SfM (GLOMAP in pycolmap 4) on the pipeline's database: `--mapper global`.

`run_global(db_path, image_dir, options)` takes the same inputs as `recon.core.sfm.
run_incremental` and returns the same `sfm.SfmResult` (largest model, number of models, sizes),
so the pipeline switches mappers with one call. Global mapping estimates all rotations at once
(rotation averaging over the verified two-view geometries), then all camera positions and points
(global positioning), then bundle-adjusts and retriangulates; it has no registration order, so
`SfmResult.growth` is empty and `on_update(reconstruction)` is called on each of GLOMAP's
model updates instead of each registration.

pycolmap 4.2.1 API used: `GlobalPipelineOptions` (top level: `min_num_matches`,
`multiple_models`, `min_model_size`, `random_seed`, `num_threads`, `image_path`,
`decompose_relative_pose`; `.mapper` = GlobalMapperOptions with `.rotation_averaging`,
`.global_positioning`, `.bundle_adjustment` (refine focal / principal point / extra params),
`.retriangulation`), `GlobalPipeline(options, database, ReconstructionManager)` with
`add_callback(GlobalPipelineCallback.MODEL_UPDATE_CALLBACK, fn)` and `run()`;
`pycolmap.global_mapping(database_path, image_path, output_path, options)` is the same pipeline
but writes every model to disk, which the pipeline does itself (`sfm.write_model_atomic`).

Focal lengths: GLOMAP's rotation averaging and positioning trust the two-view geometries
relative poses, which need intrinsics; photos without EXIF focal length get only a guess
(1.2 * max(w, h), `recon.core.database`). With `calibrate=True` and any camera lacking a
focal prior, `pycolmap.calibrate_view_graph` first estimates focal lengths from the
fundamental matrices and re-estimates the relative poses. It rewrites the two-view geometries,
so it runs on a temporary copy of the database: the pipeline's database (and a later
incremental run on it) stays as written. It is off by default because it is scene-dependent
(benchmarks/results/mappers.json): on castle_P30 (our run at 1000 px, no EXIF focal) GLOMAP
registered 30/30 with a 13.9 deg median relative rotation error without it and 0.41 deg with
it (incremental: 0.46 deg), but on nearly planar rendered facades (a degenerate configuration
for self-calibration) it lost one of facade-extreme's 4 views and, on a 6-view facade, estimated
a 74 px focal length for a 288 px camera (error 0.09 -> 18 deg).

Which mapper (measured, benchmarks/results/mappers.json, seed 0, one thread): global is as
accurate or slightly better than incremental on fountain_P11 (0.226 / 0.237 deg median relative
rotation error), facade-extreme (0.114 / 0.145) and facade-wide (0.084 / 0.107), but fails on
castle_P30 (13.9 / 0.46 deg) unless calibrated; incremental is the only one accurate on all
four, so it stays the default for wide-baseline scenes.

Options (`global_options`), chosen to match `sfm.mapping_options` where both have the knob:
`min_num_matches` 15, `multiple_models` with `min_model_size` 3, the seed everywhere, focal
length and distortion refined but not the principal point, and no GPU (none here; GLOMAP's
GPU solvers are only used above 50 images anyway). The number of threads is the caller's: like
incremental bundle adjustment, several threads may change the last digits.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import pycolmap

from recon.core.sfm import SfmResult

UpdateHook = Callable[[pycolmap.Reconstruction], None]


def global_options(seed: int = 0, num_threads: int = -1) -> pycolmap.GlobalPipelineOptions:
    """GlobalPipelineOptions for our databases (see module doc)."""
    o = pycolmap.GlobalPipelineOptions()
    o.min_num_matches = 15
    o.multiple_models = True
    o.min_model_size = 3
    o.random_seed = int(seed)
    o.num_threads = int(num_threads)
    m = o.mapper
    m.random_seed = int(seed)
    m.num_threads = int(num_threads)
    m.rotation_averaging.random_seed = int(seed)
    m.global_positioning.random_seed = int(seed)
    m.global_positioning.use_gpu = False
    m.retriangulation.random_seed = int(seed)
    ba = m.bundle_adjustment
    ba.refine_focal_length = True
    ba.refine_principal_point = False
    ba.refine_extra_params = True
    ba.ceres.use_gpu = False
    return o


def options_summary(o: pycolmap.GlobalPipelineOptions) -> dict:
    """The options we set, for the report."""
    m = o.mapper
    return dict(mapper="global", min_num_matches=o.min_num_matches, multiple_models=o.multiple_models,
                min_model_size=o.min_model_size, random_seed=o.random_seed,
                ba_refine_focal_length=m.bundle_adjustment.refine_focal_length,
                ba_refine_principal_point=m.bundle_adjustment.refine_principal_point,
                ba_refine_extra_params=m.bundle_adjustment.refine_extra_params,
                max_rotation_error_deg=m.rotation_averaging.max_rotation_error_deg,
                max_angular_reproj_error_deg=m.max_angular_reproj_error_deg)


def needs_calibration(db_path: str | Path) -> bool:
    """True when some camera of the database has no prior focal length (no EXIF focal)."""
    db = pycolmap.Database.open(str(db_path))
    try:
        return any(not c.has_prior_focal_length for c in db.read_all_cameras())
    finally:
        db.close()


def calibrate_copy(db_path: str | Path, work_dir: str | Path, seed: int = 0) -> Path:
    """A copy of the database in `work_dir` with `pycolmap.calibrate_view_graph` applied."""
    copy = Path(work_dir) / "database.calibrated.db"
    shutil.copyfile(db_path, copy)
    o = pycolmap.ViewGraphCalibrationOptions()
    o.random_seed = int(seed)
    pycolmap.calibrate_view_graph(str(copy), o)
    return copy


def run_global(db_path: str | Path, image_dir: str | Path, options: pycolmap.GlobalPipelineOptions | None = None,
               on_update: UpdateHook | None = None, calibrate: bool = False) -> SfmResult:
    """Run global mapping on a database; return the largest model (or None) like `run_incremental`.

    Sets `options.image_path` (point colours). `calibrate`: estimate focal lengths first when a
    camera has no prior (on a temporary copy next to the database; see module doc). Nothing
    else is written to disk. An exception from `on_update` is recorded in
    `SfmResult.hook_error` and the hook is not called again.
    """
    opts = options or global_options()
    if calibrate and needs_calibration(db_path):
        with tempfile.TemporaryDirectory(prefix=".calibrate-", dir=Path(db_path).parent) as tmp:
            return _run_global(calibrate_copy(db_path, tmp, opts.random_seed), image_dir, opts, on_update)
    return _run_global(db_path, image_dir, opts, on_update)


def _run_global(db_path: str | Path, image_dir: str | Path, opts: pycolmap.GlobalPipelineOptions,
                on_update: UpdateHook | None) -> SfmResult:
    opts.image_path = str(image_dir)
    opts.mapper.image_path = str(image_dir)
    manager = pycolmap.ReconstructionManager()
    hook_errors: list[str] = []

    def hook() -> None:
        if on_update is None or hook_errors or manager.size() == 0:
            return
        try:
            on_update(manager.get(manager.size() - 1))
        except Exception as e:  # a failing sink must never cost the model
            hook_errors.append(f"{type(e).__name__}: {e}")

    db = pycolmap.Database.open(str(db_path))
    try:
        pipeline = pycolmap.GlobalPipeline(opts, db, manager)
        pipeline.add_callback(pycolmap.GlobalPipelineCallback.MODEL_UPDATE_CALLBACK, hook)
        pipeline.run()
    finally:
        db.close()
    recs = [manager.get(i) for i in range(manager.size())]
    recs = [r for r in recs if r.num_reg_images() > 0]
    recs.sort(key=lambda r: (r.num_reg_images(), r.num_points3D()), reverse=True)
    return SfmResult(recs[0] if recs else None, len(recs), [int(r.num_reg_images()) for r in recs], [],
                     hook_errors[0] if hook_errors else None)


MAPPERS: tuple[str, ...] = ("incremental", "global")


def run_mapper(mapper: str, db_path: str | Path, image_dir: str | Path, seed: int = 0, num_threads: int = 1,
               px_scale: float = 1.0, calibrate: bool = False) -> SfmResult:
    """`incremental` (`sfm.run_incremental` with `sfm.mapping_options`) or `global` (`run_global`).

    ValueError naming the choices for anything else. For the pipeline's `--mapper` switch and
    the benchmarks; the pipeline passes its own hooks to the two functions directly.
    """
    from recon.core import sfm

    if mapper == "incremental":
        return sfm.run_incremental(db_path, image_dir, sfm.mapping_options(seed, num_threads, px_scale))
    if mapper == "global":
        return run_global(db_path, image_dir, global_options(seed, num_threads), calibrate=calibrate)
    raise ValueError(f"--mapper {mapper!r}: choose one of {', '.join(MAPPERS)}")
