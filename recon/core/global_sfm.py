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

Options (`global_options`), chosen to match `sfm.mapping_options` where both have the knob:
`min_num_matches` 15, `multiple_models` with `min_model_size` 3, the seed everywhere, focal
length and distortion refined but not the principal point, and no GPU (none here; GLOMAP's
GPU solvers are only used above 50 images anyway). The number of threads is the caller's: like
incremental bundle adjustment, several threads may change the last digits.
"""

from __future__ import annotations

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


def run_global(db_path: str | Path, image_dir: str | Path, options: pycolmap.GlobalPipelineOptions | None = None,
               on_update: UpdateHook | None = None) -> SfmResult:
    """Run global mapping on a database; return the largest model (or None) like `run_incremental`.

    Sets `options.image_path` (point colours). Nothing is written to disk. An exception from
    `on_update` is recorded in `SfmResult.hook_error` and the hook is not called again.
    """
    opts = options or global_options()
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
               px_scale: float = 1.0) -> SfmResult:
    """`incremental` (`sfm.run_incremental` with `sfm.mapping_options`) or `global` (`run_global`).

    ValueError naming the choices for anything else. For the pipeline's `--mapper` switch and
    the benchmarks; the pipeline passes its own hooks to the two functions directly.
    """
    from recon.core import sfm

    if mapper == "incremental":
        return sfm.run_incremental(db_path, image_dir, sfm.mapping_options(seed, num_threads, px_scale))
    if mapper == "global":
        return run_global(db_path, image_dir, global_options(seed, num_threads))
    raise ValueError(f"--mapper {mapper!r}: choose one of {', '.join(MAPPERS)}")
