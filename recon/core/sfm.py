"""Incremental SfM with pycolmap, tuned for few, wide-baseline views; model and point cloud output.

pycolmap 4 API used here (checked against 4.2.1): `pycolmap.IncrementalPipeline(options,
database, reconstruction_manager)` with `add_callback(IncrementalPipelineCallback.
INITIAL_IMAGE_PAIR_REG_CALLBACK / NEXT_IMAGE_REG_CALLBACK, fn)` and `run()` fills the
`ReconstructionManager` (`size()`, `get(i)`) with every model, including the one being built
when a callback fires (so a callback can read the live model: `pycolmap.incremental_mapping`
does the same but its callbacks get no arguments and it writes every model to disk);
`options.image_path` is where point colours are read from. The mapper's own options live in
`IncrementalPipelineOptions.mapper` (IncrementalMapperOptions:
`init_min_tri_angle`, `abs_pose_min_num_inliers`, ...) and the triangulator's in
`.triangulation` (IncrementalTriangulatorOptions). `Reconstruction.write(dir)` writes the
binary model; `compute_mean_track_length()`, `compute_mean_reprojection_error()`,
`num_reg_images()`, `num_points3D()` summarise it.

Why these options (COLMAP's defaults assume many images with small baselines):

* `mapper.init_min_tri_angle` 16 -> 8 deg and `init_min_num_inliers` 100 -> 50: the mapper
  tries the best-matched pairs first and starts from the first that passes; when the models it
  builds leave images out, COLMAP's pipeline itself reruns with the inliers halved, then the
  angle halved, twice (here down to 2 deg / 12), so a handful of photos taken far apart, or a
  capture of only narrow pairs, still initialises. At 4 deg (until 2026-12-03) a near-planar
  pair of internet photos with many matches and a 6.8 deg angle started sacre_coeur's first
  model, which collapsed; whether a later model recovered all ten photos depended on the seed
  and on sub-pixel keypoint changes (3 of 10 registered with one track-refinement setting). At
  8 deg the databases measured map as well or better, better than at COLMAP's 16 deg on the
  two-group renders, but for one seed of one (sacre_coeur under `--simulate needed`: 5 of 10
  photos in its largest model, 9 of 10 with the structure-less fallback below), which
  `map_with_retries` catches (docs/decisions.md, "Initial pair at 8 deg").
* `mapper.abs_pose_min_num_inliers` 30 -> 15, `abs_pose_min_inlier_ratio` 0.25 -> 0.15: a new
  view far from the others sees fewer of the existing 3D points.
* `min_num_matches` 15 (pairs with fewer verified matches are ignored) and `min_model_size`
  10 -> 3: when the view graph splits, later models of 3+ images are kept too (COLMAP always
  keeps the first model and caps the threshold at 0.8 * #images).
* `multiple_models` True: when the view graph falls apart the pipeline keeps reconstructing the
  rest instead of stopping; we keep the largest model (most registered images, then most points).
* `ba_refine_focal_length` / `ba_refine_extra_params` True, `ba_refine_principal_point` False:
  EXIF focal lengths are only a prior (and absent photos get 1.2 * max(w, h)), the principal
  point is not observable from a few views.
* `triangulation.ignore_two_view_tracks` stays True (COLMAP's default): merged keypoints give
  real multi-view tracks (see `recon.core.tracks`), so two-view-only points are not needed.
  Except for a scene of exactly two images (`allow_two_view_model`): there every track has two
  views, so with the default the initial pair triangulates nothing and the mapper can never
  initialise ("needs a third view"). With two-view tracks kept, the mapper builds the model from
  the verified relative pose of the pair (essential / fundamental matrix, COLMAP's own two-view
  geometry) and triangulates its inliers; scale is arbitrary, as for any model without GPS.
  `run_incremental` applies this by itself when the database holds exactly two images. Two
  views barely constrain the focal length, so the model is as good as the focal prior: with an
  EXIF focal length the relative rotation of a rendered pair 20 deg apart is within 0.5 deg of
  the truth; without one (prior 1.2 * max(w, h), here 33 % too long) it is off by 6 deg.
* thresholds in pixels (`init_max_error`, `abs_pose_max_error`, `filter_max_reproj_error`,
  triangulation reprojection errors) are multiplied by `px_scale`, the working-to-full-resolution
  factor (capped at 3). The pipeline (ours and the stock comparison alike) passes 1, COLMAP's
  values in full-resolution px as COLMAP's own pipeline applies them, unless
  `sfm.scale_thresholds`: scaling them let observations 4-7.7 px off stay in the model on 3072 px
  photos and measured worse (`recon.config.SfmConfig.scale_thresholds`).
* `structure_less_registration_fallback` True -> False (COLMAP 3.x's behaviour; COLMAP 4
  registers an image that sees too few 3D points from its 2D-2D correspondences instead): in
  every database of the benchmarks (real scenes, both pipelines, the difficulty curve, the
  rendered scenes) the fallback ran only in one mapping, sacre_coeur under `--simulate needed`
  with seed 0, where a model started from a weak triplet had already lost its points: it
  registered four more images that way and one structure-less RANSAC took 7.7 s, the failed
  mapping 8.6-15.3 s against 0.3-0.7 s without it (retried either way, 10 of 10 with seed 1;
  docs/decisions.md, "Structure-less registration off"). `sfm.structure_less_fallback` turns it on.
* `random_seed`: seeds every RANSAC in the mapper; bundle adjustment with several threads can
  still differ in the last digits (Ceres sums in thread order), so results are reproducible
  for a fixed seed up to float noise, and bit-exact only with `num_threads=1`.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from recon.log import colmap_verbose

# One thread for mapping: multi-threaded bundle adjustment can vary with machine load (one
# rendered 480 px scene once gave no model under heavy load), and on fountain_P11 one thread
# took 3.88 s against 3.79 s with two, for the identical model.
MAPPING_THREADS = 1


def allow_two_view_model(o: pycolmap.IncrementalPipelineOptions) -> pycolmap.IncrementalPipelineOptions:
    """Let incremental mapping build a model of just two images (see module doc): keep the
    two-view tracks, which are all a two-image scene has. Returns `o` (changed in place)."""
    o.triangulation.ignore_two_view_tracks = False
    return o


def threshold_scale(px_scale: float) -> float:
    """Factor from working px to the database's full-resolution px for COLMAP's pixel thresholds:
    the working-to-full-resolution factor `px_scale`, at least 1 and capped at 3 (module doc)."""
    return float(min(max(px_scale, 1.0), 3.0))


def mapping_options(seed: int = 0, num_threads: int = -1, px_scale: float = 1.0, num_images: int | None = None,
                    structure_less_fallback: bool = False) -> pycolmap.IncrementalPipelineOptions:
    """IncrementalPipelineOptions for a small wide-baseline scene (see module doc); with
    `num_images == 2` also `allow_two_view_model`; `structure_less_fallback` turns COLMAP's
    structure-less registration back on (off here, see module doc)."""
    f = threshold_scale(px_scale)
    o = pycolmap.IncrementalPipelineOptions()
    o.min_num_matches = 15
    o.multiple_models = True
    o.min_model_size = 3  # COLMAP also caps it at 0.8 * #images and always keeps the first model
    o.extract_colors = True
    o.num_threads = int(num_threads)
    o.random_seed = int(seed)
    o.ba_refine_focal_length = True
    o.ba_refine_principal_point = False
    o.ba_refine_extra_params = True
    o.structure_less_registration_fallback = bool(structure_less_fallback)
    m = o.mapper
    m.init_min_tri_angle = 8.0
    m.init_min_num_inliers = 50
    m.init_max_error = 4.0 * f
    m.abs_pose_min_num_inliers = 15
    m.abs_pose_min_inlier_ratio = 0.15
    m.abs_pose_max_error = 12.0 * f
    m.filter_max_reproj_error = 4.0 * f
    m.random_seed = int(seed)
    m.num_threads = int(num_threads)
    t = o.triangulation
    t.merge_max_reproj_error = 4.0 * f
    t.complete_max_reproj_error = 4.0 * f
    t.random_seed = int(seed)
    if num_images == 2:
        allow_two_view_model(o)
    return o


def options_summary(o: pycolmap.IncrementalPipelineOptions) -> dict:
    """The options we change, for the report."""
    m, t = o.mapper, o.triangulation
    return dict(min_num_matches=o.min_num_matches, multiple_models=o.multiple_models,
                min_model_size=o.min_model_size, random_seed=o.random_seed,
                init_min_tri_angle=m.init_min_tri_angle, init_min_num_inliers=m.init_min_num_inliers,
                init_max_error=m.init_max_error, abs_pose_min_num_inliers=m.abs_pose_min_num_inliers,
                abs_pose_min_inlier_ratio=m.abs_pose_min_inlier_ratio, abs_pose_max_error=m.abs_pose_max_error,
                filter_max_reproj_error=m.filter_max_reproj_error,
                tri_merge_max_reproj_error=t.merge_max_reproj_error,
                tri_complete_max_reproj_error=t.complete_max_reproj_error,
                ba_refine_focal_length=o.ba_refine_focal_length,
                ba_refine_principal_point=o.ba_refine_principal_point,
                ba_refine_extra_params=o.ba_refine_extra_params,
                ignore_two_view_tracks=t.ignore_two_view_tracks)


@dataclass
class SfmResult:
    reconstruction: pycolmap.Reconstruction | None
    num_models: int
    model_sizes: list[int]  # registered images per model, largest first
    growth: list[dict] = field(default_factory=list)  # one GrowthStep.to_dict() per registration
    hook_error: str | None = None  # the first exception raised by on_step (later steps were not reported)


@dataclass(frozen=True)
class GrowthStep:
    """The model right after one registration step of incremental mapping.

    `step` counts registration events over the whole run (0 = the initial pair), `model` is the
    index of the model being built (a new one starts when the view graph falls apart),
    `image` is the image just registered (for the initial pair: the second image of the pair;
    `images` lists every image registered in this model so far, in registration order).
    `initial_pair` names both images of the model's initial pair on its first step, else None.
    """
    step: int
    model: int
    image: str
    images: tuple[str, ...]
    registered_images: int
    num_points3D: int
    initial_pair: tuple[str, str] | None = None

    def to_dict(self) -> dict:
        return dict(step=self.step, model=self.model, image=self.image, registered_images=self.registered_images,
                    num_points3D=self.num_points3D,
                    initial_pair=list(self.initial_pair) if self.initial_pair else None)


StepHook = Callable[[GrowthStep, pycolmap.Reconstruction], None]


def run_incremental(db_path: str | Path, image_dir: str | Path, options: pycolmap.IncrementalPipelineOptions,
                    on_step: StepHook | None = None) -> SfmResult:
    """Run incremental mapping on a database; return the largest model (or None) and its growth.

    Uses `pycolmap.IncrementalPipeline` with our own `ReconstructionManager` rather than
    `pycolmap.incremental_mapping`, whose callbacks take no arguments: after the initial pair and
    after every further registration, `on_step(step, reconstruction)` receives the live model
    (read it inside the hook, it changes afterwards) so callers can show the reconstruction
    growing. An exception from the hook is recorded in `SfmResult.hook_error` and the hook is
    not called again: mapping always finishes. Sets `options.image_path` (point colours).
    Nothing is written to disk here (see `write_model_atomic`). A database of exactly two
    images gets `allow_two_view_model` (else no model could ever be found).
    """
    opts = options
    opts.image_path = str(image_dir)  # for extract_colors
    manager = pycolmap.ReconstructionManager()
    growth: list[dict] = []
    order: dict[int, list[str]] = {}  # model index -> image names in registration order
    hook_errors: list[str] = []

    def hook() -> None:
        idx = manager.size() - 1
        rec = manager.get(idx)
        reg = list(rec.reg_image_ids())
        names = order.setdefault(idx, [])
        known = set(names)
        names += [rec.image(i).name for i in sorted(reg) if rec.image(i).name not in known]
        first = not known and len(names) >= 2  # the model's first step: its initial pair
        step = GrowthStep(step=len(growth), model=idx, image=names[-1] if names else "", images=tuple(names),
                          registered_images=len(reg), num_points3D=int(rec.num_points3D()),
                          initial_pair=(names[0], names[1]) if first else None)
        growth.append(step.to_dict())
        if on_step is not None and not hook_errors:
            try:
                on_step(step, rec)
            except Exception as e:  # e.g. a logging sink gone: never worth losing the model; no more calls
                hook_errors.append(f"{type(e).__name__}: {e}")

    db = pycolmap.Database.open(str(db_path))
    try:
        if db.num_images() == 2:
            allow_two_view_model(opts)
        pipeline = pycolmap.IncrementalPipeline(opts, db, manager)
        pipeline.add_callback(pycolmap.IncrementalPipelineCallback.INITIAL_IMAGE_PAIR_REG_CALLBACK, hook)
        pipeline.add_callback(pycolmap.IncrementalPipelineCallback.NEXT_IMAGE_REG_CALLBACK, hook)
        pipeline.run()
    finally:
        db.close()
    recs = [(i, manager.get(i)) for i in range(manager.size())]
    recs = [(i, r) for i, r in recs if r.num_reg_images() > 0]
    recs.sort(key=lambda ir: (ir[1].num_reg_images(), ir[1].num_points3D()), reverse=True)
    best = recs[0][1] if recs else None
    return SfmResult(best, len(recs), [int(r.num_reg_images()) for _, r in recs], growth,
                     hook_errors[0] if hook_errors else None)


RETRY_MAX_IMAGES = 100
"""`map_with_retries` retries only scenes whose verified pair graph connects at most this many
images: a retry repeats the whole mapping, seconds on small scenes, minutes on a capture of
hundreds of photos, where a missing frame or two costs less than doubling the run."""


def connected_images(db_path: str | Path, min_num_matches: int) -> int:
    """Images in the largest component of the database's verified pair graph, pairs of at least
    `min_num_matches` inlier matches (the mapper ignores the others): what one model can hold."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    db = pycolmap.Database.open(str(db_path))
    try:
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    pairs = [pycolmap.pair_id_to_image_pair(pid) for pid, n in zip(pair_ids, counts) if n >= min_num_matches]
    if not pairs:
        return 0
    ids = {i: k for k, i in enumerate(sorted({int(i) for pair in pairs for i in pair}))}
    u = np.array([ids[int(a)] for a, _ in pairs])
    v = np.array([ids[int(b)] for _, b in pairs])
    graph = coo_matrix((np.ones(len(u), np.int8), (u, v)), shape=(len(ids), len(ids)))
    _, label = connected_components(graph, directed=False)
    return int(np.bincount(label).max())


def map_with_retries(db_path: str | Path, image_dir: str | Path,
                     options_for_seed: Callable[[int], pycolmap.IncrementalPipelineOptions], seed: int,
                     retries: int, on_step: StepHook | None = None) -> tuple[SfmResult, list[dict]]:
    """`run_incremental` with `options_for_seed(seed)`; while its largest model leaves out images
    that the verified pairs connect to it (`connected_images`), up to `retries` more mappings
    with seeds `seed + 1`, `seed + 2`, ... (retries do not call `on_step`). Returns the model
    registering the most images (then the most points; the first on a tie) and one summary per
    mapping ({seed, model_sizes, registered, points, chosen}).

    Why: on a few photos with unknown focal lengths the mapper can start from a pair whose
    geometry is nearly a homography and grow a model that collapses; which pair and whether a
    later model recovers depends on RANSAC draws (sacre_coeur under `--simulate needed`: models of
    5 and 3 photos with seed 0, 10 of 10 with seeds 1 to 11; docs/decisions.md, "Mapper retries"). The
    result stays deterministic for a fixed seed. Scenes of more than `RETRY_MAX_IMAGES` connected
    images are not retried."""
    options = options_for_seed(seed)
    first = run_incremental(db_path, image_dir, options, on_step)
    best, best_index = first, 0
    attempts = [_attempt(first, seed)]
    if retries > 0:
        reachable = connected_images(db_path, options.min_num_matches)
        k = 0
        while k < retries and reachable <= RETRY_MAX_IMAGES and _quality(best)[0] < reachable:
            k += 1
            res = run_incremental(db_path, image_dir, options_for_seed(seed + k))
            attempts.append(_attempt(res, seed + k))
            if _quality(res) > _quality(best):
                best, best_index = res, k
    attempts[best_index]["chosen"] = True
    return best, attempts


def _quality(res: SfmResult) -> tuple[int, int]:
    """(registered images, points) of the result's model; (0, 0) without one."""
    rec = res.reconstruction
    return (0, 0) if rec is None else (int(rec.num_reg_images()), int(rec.num_points3D()))


def _attempt(res: SfmResult, seed: int) -> dict:
    registered, points = _quality(res)
    return {"seed": int(seed), "model_sizes": list(res.model_sizes), "registered": registered, "points": points,
            "chosen": False}


AUTO_SCALE_FACTOR = 2.0
"""The final adjustment's automatic loss scale, in units of the model's median point error: a
point's mean reprojection error over its observations is about 1.2 sigma for Gaussian keypoint
noise of sigma, so 2x its median is about 2.4 sigma, the Cauchy scale of 95 % efficiency on
inliers (`final_bundle_adjustment`)."""

FINAL_BA_LOSSES = ("none", "cauchy", "soft_l1", "huber")
"""`sfm.final_ba_loss`'s values: none = no final adjustment, else Ceres' robust loss of that name."""


PRINCIPAL_POINT_MODES = ("fixed", "refine", "auto")
"""`FinalBaConfig.principal_point`: auto (default since 2026-12-08) = freed only where the views
determine it (`PP_SIGMA_MAX`); fixed = COLMAP's image centre; refine = always freed in the final
adjustment."""

PP_SIGMA_MAX = 0.002
"""Auto principal point: it is freed only when every camera's principal point is determined by
the views to this fraction of the image's larger side (one standard deviation, from the
adjustment's covariance scaled by the model's RMS reprojection error;
`_principal_point_sigma`). Measured on finished models (docs/decisions.md, "The principal point
in the final adjustment"): 0.0036-0.055 % on castle_P30, fountain_P11, fox and sceaux_castle;
0.11-0.91 % on sacre_coeur's ten one-photo cameras (kept fixed: no ground truth to say freed
ones are right); 5.2-16 % or no covariance at all (a rank-deficient problem) on every render of
cameras in a row, among them facade-groups' 800x600 seed-2 render, where freeing the point
gives 3.0° instead of 0.014°. 0.2 % lies 3.6x above the constrained ones and 4.5x below
sacre_coeur. It replaced a two-start probe test, which that render passed (the probes measure
whether the adjustment converges to one point, not how well the views determine it)."""

PP_SIGMA_MAX_IMAGES = 1000
"""Auto principal point: above this many registered images the covariance is not estimated and
the point stays fixed. COLMAP's estimate inverts the dense Schur complement over every pose
(6 values per image): 288 MB of doubles at 1000 images, 7 GB at 5000 (orbit-100: 2.6 s)."""

OUTLIER_SCALES = 3.0
"""The final adjustment's outlier threshold, in loss scales: after its first pass, observations
more than this many Cauchy scales off (robust weight 1 / (1 + 3^2) = 10 %: the loss already all
but ignores them) are dropped and the model adjusted again (`final_bundle_adjustment`)."""


@dataclass(frozen=True)
class FinalBaConfig:
    """A last global bundle adjustment of the finished model under a robust loss
    (`final_bundle_adjustment`)."""

    loss: str = "cauchy"
    scale_px: float = 0.0  # 0 = auto: `AUTO_SCALE_FACTOR` x the median of the points' mean reprojection errors
    max_iterations: int = 100  # over both passes when `outlier_scales` > 0
    max_reproj_error_px: float = 4.0
    min_tri_angle_deg: float = 1.5
    outlier_scales: float = OUTLIER_SCALES  # 0 = one pass, the mapper's filter only
    principal_point: str = "auto"  # auto / fixed / refine (`PRINCIPAL_POINT_MODES`)


def _loss_scale(rec: pycolmap.Reconstruction, cfg: FinalBaConfig) -> float:
    """`cfg.scale_px`, or when 0 `AUTO_SCALE_FACTOR` x the median of the points' mean
    reprojection errors in `rec` as it is now (px, >= 1e-3)."""
    if cfg.scale_px > 0:
        return float(cfg.scale_px)
    return max(AUTO_SCALE_FACTOR * float(np.median([p.error for p in rec.points3D.values()])), 1e-3)


def _adjustable(rec: pycolmap.Reconstruction, cfg: FinalBaConfig) -> bool:
    """Whether the final adjustment applies: a loss, two registered images, a point."""
    return cfg.loss != "none" and rec.num_reg_images() >= 2 and rec.num_points3D() > 0


def _full_adjustment_options(refine_principal_point: bool) -> pycolmap.BundleAdjustmentOptions:
    """The final adjustment's parameters: every focal length and distortion term, principal points
    only when `refine_principal_point` (shared by `_adjust` and the covariance of
    `_principal_point_sigma`, so `auto` judges the adjustment it would run)."""
    o = pycolmap.BundleAdjustmentOptions()
    o.refine_focal_length, o.refine_principal_point, o.refine_extra_params = True, bool(refine_principal_point), True
    return o


def _adjust(rec: pycolmap.Reconstruction, loss: str, scale_px: float, iterations: int, num_threads: int,
            refine_principal_point: bool = False) -> None:
    """One global bundle adjustment of `rec` in place (every pose, point, focal length and
    distortion; principal points fixed unless `refine_principal_point`) under `loss` of scale
    `scale_px`."""
    o = _full_adjustment_options(refine_principal_point)
    o.ceres.loss_function_type = {"cauchy": pycolmap.LossFunctionType.CAUCHY,
                                  "soft_l1": pycolmap.LossFunctionType.SOFT_L1,
                                  "huber": pycolmap.LossFunctionType.HUBER}[loss]
    o.ceres.loss_function_scale = scale_px
    o.ceres.solver_options.max_num_iterations = int(iterations)
    o.ceres.solver_options.num_threads = int(num_threads)
    # COLMAP prints a 10-line solver report per adjustment through a path its log level does not
    # reach (`recon.log.quiet_colmap`): only with `recon -v`. Printing changes no result.
    o.print_summary = colmap_verbose()
    global_bundle_adjustment(rec, o)


def _every_registered_image(rec: pycolmap.Reconstruction) -> pycolmap.BundleAdjustmentConfig:
    """An adjustment of every registered image of `rec` (and, through them, its points)."""
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    return config


def global_bundle_adjustment(rec: pycolmap.Reconstruction, options: pycolmap.BundleAdjustmentOptions) -> None:
    """`pycolmap.bundle_adjustment(rec, options)` step for step (COLMAP's
    `BundleAdjustmentController::Run`: observations behind a camera dropped, every registered
    image adjusted, the gauge fixed by two cameras' poses, point errors updated), without the
    `OptionManager` that call builds: constructing one resets glog's level, so every call printed
    its heading and timer on stderr whatever `recon.log.quiet_colmap` had set, and left COLMAP
    logging everything for the rest of the stage. Same adjustment, same result to the bit
    (`tests/test_sfm.py`)."""
    pycolmap.ObservationManager(rec).filter_observations_with_negative_depth()
    config = _every_registered_image(rec)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    rec.update_point_3d_errors()


def _filter(rec: pycolmap.Reconstruction, max_reproj_error_px: float, min_tri_angle_deg: float) -> int:
    """Drop the observations over `max_reproj_error_px` and the points under `min_tri_angle_deg`
    (COLMAP's mapper filter); returns the number of observations dropped."""
    return int(pycolmap.ObservationManager(rec).filter_all_points3D(max_reproj_error_px, min_tri_angle_deg))


def final_bundle_adjustment(rec: pycolmap.Reconstruction, cfg: FinalBaConfig = FinalBaConfig(),
                            num_threads: int = MAPPING_THREADS) -> dict:
    """Adjust every pose, point, focal length and distortion of `rec` once more (in place) under
    the robust loss `cfg.loss` of scale `cfg.scale_px` (full-resolution px; 0 = automatic, see
    `AUTO_SCALE_FACTOR`), then drop the observations the mapper's own filter would drop (over
    `max_reproj_error_px`, points under `min_tri_angle_deg`). With `cfg.outlier_scales` > 0 the
    iterations are split over two passes: after the first, the observations more than
    `outlier_scales` loss scales off (the scale re-measured on the adjusted model) are dropped
    and the second pass adjusts what is left. Returns a summary for the report.

    Why: COLMAP's incremental mapper ends with a squared-loss global adjustment, so the few
    observations still 1-4 px off (inside its 4 px filter: chance matches on repeated texture,
    wide-baseline points SIFT localises differently in each view) pull every pose by their
    square. A Cauchy loss scaled to the model's own inlier noise keeps the well-localised
    majority in charge. Measured on finished models (docs/decisions.md, "Final robust bundle
    adjustment"): the difficulty curve's median relative rotation error falls 2-7x from 13° to
    52° (52°: 0.131 -> 0.045°, 0.233 -> 0.030°), castle_P30's from 0.459° to 0.436°,
    fountain_P11's from 0.2405° to 0.235°; stock COLMAP's models gain as well (castle 0.442° ->
    0.439°), and the stock comparison maps through this same stage. The scale is the model's
    own rather than a fixed 0.5 px: stock `high`'s 52° model of the difficulty curve (median
    point error 0.81 px) went from 0.146° to 0.298° under 0.5 px and to 0.098° under its own.
    The second pass (docs/decisions.md, "Outlier pass of the final adjustment"): the mapper's
    fixed 4 px filter keeps observations 5-10x the model's noise off, which the loss down-weights
    but which stay in the model and its reprojection error; COLMAP's own global refinement
    alternates adjustment and filtering the same way. Same iteration budget as one pass.
    `principal_point` "refine" frees every camera's principal point in both passes: on castle_P30
    and fountain_P11, whose true principal point lies 15-20 px off the centre COLMAP assumes, it
    cuts the rotation error 4-6x, but where the views do not constrain it (a row of cameras at one
    height) it drifts by 12-200 px and the poses follow. "auto" frees it only when the
    adjustment's covariance says the views determine it (`PP_SIGMA_MAX`,
    `_principal_point_sigma`: one covariance estimate, 0.4-3 s on the measured models;
    docs/decisions.md, "The principal point in the final adjustment")."""
    if cfg.principal_point == "auto" and _adjustable(rec, cfg):
        t0 = time.perf_counter()
        sigma = _principal_point_sigma(rec)
        refine = sigma <= PP_SIGMA_MAX
        out = _final(rec, cfg, num_threads, refine)
        out.update(principal_point="auto", principal_point_refined=refine,
                   principal_point_sigma=None if math.isinf(sigma) else round(sigma, 6),
                   seconds=round(time.perf_counter() - t0, 3))
        return out
    out = _final(rec, cfg, num_threads, cfg.principal_point == "refine")
    if out["applied"]:
        out.update(principal_point=cfg.principal_point, principal_point_refined=cfg.principal_point == "refine")
    return out


def _principal_point_sigma(rec: pycolmap.Reconstruction) -> float:
    """How well the views of `rec` determine its principal points: over every camera of a
    registered image, the larger standard deviation of its principal point's x and y, as a
    fraction of the image's larger side, from the covariance of a full adjustment with the
    principal point free (COLMAP's `estimate_ba_covariance`, unit observation noise) scaled by
    the RMS of the points' mean reprojection errors (px). inf when COLMAP cannot estimate it (a
    rank-deficient problem: the point is not determined) or the model has more than
    `PP_SIGMA_MAX_IMAGES` registered images. `rec` is not changed."""
    if rec.num_reg_images() > PP_SIGMA_MAX_IMAGES:
        return math.inf
    o = _full_adjustment_options(refine_principal_point=True)
    config = _every_registered_image(rec)
    problem = pycolmap.Reconstruction(rec)  # the adjuster holds pointers into the model's blocks
    cov_options = pycolmap.BACovarianceOptions()
    cov_options.params = pycolmap.BACovarianceOptionsParams.ALL
    # COLMAP's 1e-8 called a noise-free synthetic model rank-deficient (tests/test_sfm.py); 1e-6
    # gives the same deviations to 4 digits on every measured real and rendered model
    cov_options.damping = 1e-6
    try:
        adjuster = pycolmap.create_default_ceres_bundle_adjuster(o, config, problem)
        cov = pycolmap.estimate_ba_covariance(cov_options, problem, adjuster)
    except (RuntimeError, ValueError):  # an estimate COLMAP refuses is no estimate: keep the point
        return math.inf
    if cov is None:
        return math.inf
    rms_px = math.sqrt(float(np.mean([p.error ** 2 for p in problem.points3D.values()])))
    worst = 0.0
    for camera_id in sorted({problem.image(i).camera_id for i in problem.reg_image_ids()}):
        cam = problem.cameras[camera_id]
        block = cov.get_other_params_cov(cam.params)
        if block is None:
            return math.inf
        var = np.diag(np.asarray(block))[list(cam.principal_point_idxs())]
        worst = max(worst, math.sqrt(float(np.max(var))) * rms_px / max(cam.width, cam.height))
    return worst


def _final(rec: pycolmap.Reconstruction, cfg: FinalBaConfig, num_threads: int, refine_pp: bool) -> dict:
    """`final_bundle_adjustment` with the principal point freed or not (`refine_pp`)."""
    if not _adjustable(rec, cfg):
        return {"loss": cfg.loss, "applied": False}
    t0 = time.perf_counter()
    before = float(rec.compute_mean_reprojection_error())
    scale = _loss_scale(rec, cfg)
    two_pass = cfg.outlier_scales > 0
    first = max(1, int(cfg.max_iterations) // 2) if two_pass else int(cfg.max_iterations)
    _adjust(rec, cfg.loss, scale, first, num_threads, refine_pp)
    dropped = _filter(rec, cfg.max_reproj_error_px, cfg.min_tri_angle_deg)
    out = {"loss": cfg.loss, "applied": True, "scale_px": round(scale, 4), "auto_scale": cfg.scale_px <= 0,
           "mean_reprojection_error_before": round(before, 5)}
    if two_pass and rec.num_points3D() > 0:
        scale2 = _loss_scale(rec, cfg)  # re-measured on the adjusted model
        threshold = min(float(cfg.max_reproj_error_px), cfg.outlier_scales * scale2)
        outliers = _filter(rec, threshold, cfg.min_tri_angle_deg)
        if rec.num_points3D() > 0:
            _adjust(rec, cfg.loss, scale2, max(1, int(cfg.max_iterations) - first), num_threads,
                    refine_pp)
            outliers += _filter(rec, threshold, cfg.min_tri_angle_deg)
        out.update(outlier_threshold_px=round(threshold, 4), second_scale_px=round(scale2, 4),
                   outliers_dropped=outliers)
    out.update(mean_reprojection_error_after=round(float(rec.compute_mean_reprojection_error()), 5),
               observations_dropped=dropped, seconds=round(time.perf_counter() - t0, 3))
    return out


def write_model_atomic(rec: pycolmap.Reconstruction, model_dir: str | Path) -> None:
    """Write a binary model to `model_dir` (e.g. OUT/sparse/0) via a temporary sibling folder.

    The old model is moved aside before the new one is renamed into place and only then deleted,
    so at every moment `model_dir` is either absent or a complete model. The written model is
    read back before it replaces the old one (COLMAP's writers do not report a short write); a
    failure removes the temporary folder and raises OSError naming `model_dir` (ENOSPC for a
    full disk).
    """
    model_dir = Path(model_dir)
    tmp = model_dir.with_name(f".{model_dir.name}.tmp-{os.getpid()}")
    old = model_dir.with_name(f".{model_dir.name}.old-{os.getpid()}")
    try:
        model_dir.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        try:
            rec.write(str(tmp))
        except Exception as e:
            raise _as_os_error(e, tmp) from e
        _check_written(rec, tmp)
        if model_dir.exists():
            os.replace(model_dir, old)
        os.replace(tmp, model_dir)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, OSError) and e.filename is None:
            e.filename = str(model_dir)
        raise
    finally:
        shutil.rmtree(old, ignore_errors=True)


def _as_os_error(e: BaseException, path: Path) -> BaseException:
    """COLMAP reports write failures as RuntimeError; a full disk becomes OSError(ENOSPC, path)."""
    if isinstance(e, OSError):
        return e
    if _disk_full_near(path) or "no space" in str(e).lower():
        return OSError(errno.ENOSPC, "No space left on device", str(path))
    return OSError(errno.EIO, f"could not write the model ({type(e).__name__}: {e})", str(path))


def _disk_full_near(path: Path, margin_bytes: int = 1 << 20) -> bool:
    try:
        return shutil.disk_usage(path if path.is_dir() else path.parent).free < margin_bytes
    except OSError:
        return False


def _check_written(rec: pycolmap.Reconstruction, model_dir: Path) -> None:
    """Read the written model back: COLMAP's writers do not report a short write (a full disk)."""
    try:
        back = pycolmap.Reconstruction(str(model_dir))
        same = back.num_reg_images() == rec.num_reg_images() and back.num_points3D() == rec.num_points3D()
    except Exception:
        same = False
    if not same:
        if _disk_full_near(model_dir):
            raise OSError(errno.ENOSPC, "No space left on device", str(model_dir))
        raise OSError(errno.EIO, "the model read back differs from the one written", str(model_dir))


def model_stats(rec: pycolmap.Reconstruction | None) -> dict:
    if rec is None or rec.num_reg_images() == 0:
        return dict(registered_images=0, num_points3D=0, mean_track_length=0.0,
                    mean_reprojection_error=None, mean_observations_per_image=0.0)
    return dict(registered_images=int(rec.num_reg_images()), num_points3D=int(rec.num_points3D()),
                mean_track_length=float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0,
                mean_reprojection_error=float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else None,
                mean_observations_per_image=float(rec.compute_mean_observations_per_reg_image()))


def registered_names(rec: pycolmap.Reconstruction | None) -> list[str]:
    if rec is None:
        return []
    return sorted(rec.image(i).name for i in rec.reg_image_ids())


def write_points_ply(rec: pycolmap.Reconstruction, path: str | Path, clean: bool = False) -> int:
    """points.ply (xyz + colour) with open3d, optionally without statistical outliers; atomic.

    Points in ascending point3D id, so the file is the same bytes whether the model was just
    mapped or read back from disk (pycolmap's map iterates in another order then).
    Returns the number of points written.
    """
    import open3d as o3d

    path = Path(path)
    pts = [p for _, p in sorted(rec.points3D.items())]
    xyz = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.float64).reshape(-1, 3) / 255.0
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(xyz)
    pc.colors = o3d.utility.Vector3dVector(rgb)
    if clean and len(xyz) >= 20:
        pc, _ = pc.remove_statistical_outlier(nb_neighbors=min(20, len(xyz) - 1), std_ratio=2.0)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}.ply")  # open3d picks the format by extension
    try:
        if not o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False):  # type: ignore[arg-type]  # str works
            if _disk_full_near(path.parent):
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            raise OSError(errno.EIO, "open3d could not write the point cloud", str(path))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return int(len(pc.points))
