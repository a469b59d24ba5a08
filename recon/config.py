"""Every option of a run, written once: typed dataclasses, one per stage, with a docstring per field.

`RunConfig` composes the sections (`output`, `load`, `pairs`, `match`, `tracks`, `database`,
`verify`, `sfm`) plus the run-wide `seed` and `workers`; each stage reads only its own section
(see `recon.core.stages`). The attribute docstring under each field is its documentation and,
for fields with a `flag` in their metadata, the `recon run --help` text: the CLI is generated
from these fields (`recon.cli.run`), so defaults and help cannot drift apart.

Ways to build one, later ones overriding earlier ones (`build_run_config`):

1. a named preset (`PRESETS`, like hloc's `confs`): `default`, `fast`, `sift`;
2. a config file (`recon run --config FILE`, TOML or JSON) with the same nesting as `to_dict()`:
   top-level `seed` / `workers`, tables `[load]`, `[pairs]`, ... and `[matcher]` for the
   matcher's own options (`[matcher.coarse]` for a section of them);
3. the `recon run` flags (`--max-size`, `--pairs`, ...), only those given on the command line;
4. `--set KEY=VALUE` (repeatable): KEY is `seed`, `SECTION.FIELD` (e.g. `tracks.merge_px`) or
   `matcher.KEY` (e.g. `matcher.fine_top_k`, `matcher.coarse.rank_by`); the value is parsed by the
   field's type.

From Python: `RunConfig.from_options(out=..., method="sift", max_size=800)` takes the flag
names as keywords (and dotted keys). Every check is in `__post_init__` and raises
`recon.errors.UserError` (one line naming the option); nothing here imports typer.

Seeding: `seed` is the only seed. The match stage passes it to the matcher (which hands it to
every RANSAC inside), the verify stage to COLMAP's two-view RANSAC and the sfm stage to the
incremental mapper, its triangulator and their RANSACs, however the config was built.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import json
import os
import textwrap
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from recon.errors import UserError

DEFAULT_MAX_SIZE = 1600
"""Working resolution for matching (longer image side, px) of every command and both pipelines."""

MAX_SEED = 2**31 - 1  # COLMAP and OpenCV take the seed as a 32-bit signed int
MATCHER_KEY = "matcher"  # `--set matcher.KEY=...` and `[matcher]` address `match.matcher`
RESERVED_MATCHER_KEYS = {
    "seed": "set the seed with --seed (it reaches the matcher, COLMAP's RANSAC and the mapper)",
    "workers": "threads inside the matcher follow --workers (one per pair task when pairs run in parallel)",
    "variant": "the pipeline uses the matcher's multi-view variant",
}


# the sections -----------------------------------------------------------------------------------
@dataclass
class OutputConfig:
    """Where the run writes, and what it shows while it runs."""

    out: Path | None = field(default=None, metadata={"flag": "--out"})
    """Output folder (default: SCENE_DIR/recon)."""

    overwrite: bool = field(default=False, metadata={"flag": "--overwrite"})
    """Delete this tool's outputs in the output folder and start over (the content-addressed match cache is kept)."""


    clean_points: bool = field(default=False, metadata={"flag": "--clean-points"})
    """Drop statistical outliers from points.ply."""

    progress: bool = field(default=True, metadata={"flag": "--progress/--no-progress"})
    """Progress bars on stderr."""

    keep_cache: bool = field(default=True, metadata={"flag": "--keep-cache/--clean-cache"})
    """Keep OUT/cache (features, pair results, stage records: what lets a rerun resume; often many
    times the size of the outputs), or delete it after a successful run."""

    def __post_init__(self) -> None:
        if self.out is not None:
            self.out = Path(self.out).expanduser()


@dataclass
class LoadConfig:
    """The load stage: which photos, decoded at which working size."""

    max_size: int = field(default=DEFAULT_MAX_SIZE, metadata={"flag": "--max-size"})
    """Working resolution for matching (longer side, px; 0 = full)."""

    def __post_init__(self) -> None:
        if isinstance(self.max_size, bool) or not isinstance(self.max_size, int) \
                or (self.max_size != 0 and self.max_size < 64):
            raise UserError(f"--max-size {self.max_size}: use 0 (full resolution) or at least 64 px")


@dataclass
class PairsConfig:
    """The pairs stage: which image pairs are matched."""

    spec: str = field(default="auto", metadata={"flag": "--pairs"})
    """auto (exhaustive up to 20 images, retrieval:10 above), exhaustive, sequential:K, retrieval:K,
    retrieval:K+sequential:S, retrieval:K+expand:E (then up to E more partners per image and
    round from the match graph), or a file of name pairs."""

    def __post_init__(self) -> None:
        from recon.core.pairs import parse_pairs_spec

        try:
            parse_pairs_spec(self.spec)
        except ValueError as e:
            raise UserError(str(e)) from None


SIMULATE = ("auto", "all", "needed")
"""`match.simulate`'s values (`MatchConfig.simulate`)."""

FIRST_PASS_DETECTORS = ("sift", "colmap-sift-plain", "colmap-sift-affine", "colmap-sift")
"""`match.first_pass_detector`'s values (`MatchConfig.first_pass_detector`)."""

SIMULATE_BRIDGES = ("cheap", "full")
"""`match.simulate_bridges`'s values (`MatchConfig.simulate_bridges`)."""


@dataclass
class MatchConfig:
    """The match stage: the pair matcher and where its pair tasks run."""

    method: str = field(default="extra-affine", metadata={"flag": "--method", "choices": "matching.registry:METHODS"})
    """Pair matcher: extra-affine, sift, orb, asift, aorb."""

    engine: str = field(default="threads", metadata={"flag": "--engine", "choices": "recon.core.engine:ENGINES"})
    """Executor of the pair tasks: threads (a thread pool of --workers threads), dask (a local Dask
    cluster of --workers processes) or dask:ADDRESS (an existing Dask scheduler)."""

    adaptive_above: int = 30
    """Scenes with more images than this are large captures: `--simulate auto` runs them as
    `needed`, and the extra-affine matcher's pairs take its adaptive per-pair paths
    (`matching.adaptive`, the `adaptive` preset: pairs whose originals already match well skip the
    simulated views) unless `matcher.adaptive` is set; 0 = never. Large captures are mostly easy
    neighbouring pairs, where the full grid costs time for nothing (README, "Scale"); small ones
    keep the full grid, which measures best on wide baselines. 30, not `--pairs auto`'s 20: the
    benchmark scenes of up to 30 images keep the full grid they were measured with."""

    simulate: str = field(default="auto", metadata={"flag": "--simulate", "choices": "recon.config:SIMULATE"})
    """Which pairs the extra-affine matcher simulates views for: all = every pair (the full
    grid, or the adaptive paths); needed = every pair's originals first (OpenCV SIFT, no view),
    then view simulation only on the pairs they leave weak and the scene needs: an image with
    few strong partners, or a bridge between parts of the strong pair graph
    (`recon.core.schedule`); auto = needed for scenes of more than `adaptive_above` images, all
    for smaller ones (`recon.core.stages.match.simulate_mode`; `report.simulate_used`). On the
    rendered 50-view walk `needed` gave the default's rotation error at 0.43x its time once the
    final robust adjustment was in; on scenes of up to 30 images `all` keeps 1.2-2.4x the
    verified inliers and the smaller errors at the wide steps (docs/decisions.md, "`--simulate
    auto`")."""

    simulate_strong_inliers: int = 100
    """`simulate = needed`: a pair whose originals verify at least this many matches is strong."""

    simulate_min_partners: int = 2
    """`simulate = needed`: a weak pair is simulated when one of its images has fewer strong partners
    (2: two strong pairs put each image in a triangle of views; 3 cost a third more time on the
    difficulty curve's narrow steps for a larger rotation error, docs/decisions.md)."""

    simulate_bridges: str = field(default="cheap", metadata={"choices": "recon.config:SIMULATE_BRIDGES"})
    """`simulate = needed`: the matcher of a weak pair simulated only as a bridge between parts of
    the strong pair graph (both images have enough strong partners). cheap = the full matcher's
    simulated views with the first pass's detector on the originals (`first_pass_detector`) and
    no epipolar round: a bridge only joins parts that their strong pairs already reconstruct;
    the covariant extraction was most of such a pair's time (sacre_coeur: 2.07x stock's total
    time with full bridges, 1.02-1.39x in four runs with cheap ones), and with the originals'
    fewer matches the epipolar round followed a wrong F (36-40 matches > 4 px off the true
    epipolar lines per bridge of the rendered facade-groups); full = the second pass's default
    matcher, as for an image short of strong partners (docs/decisions.md, "Cheap bridges")."""

    first_pass_detector: str = field(default="sift", metadata={"choices": "recon.config:FIRST_PASS_DETECTORS"})
    """`simulate = needed`: the detector of the originals in the first pass (and of cheap
    bridges): sift = OpenCV's SIFT at `first_pass_contrast`; colmap-sift-plain = COLMAP's default
    extraction (what stock COLMAP matches); colmap-sift-affine / colmap-sift = with affine shape /
    and domain-size pooling (the default matcher's originals)."""

    first_pass_contrast: float = 0.02
    """`simulate = needed`: OpenCV SIFT's contrast threshold on the originals in the first pass
    (0.02: about the keypoints of COLMAP's default extraction, 4x those of 0.04 at 1600 px)."""

    first_pass_cross_check: bool = True
    """`simulate = needed`: keep only the mutual nearest neighbours among the originals' matches in
    the first pass and in cheap bridges (`matcher.fine.original_cross_check`, as COLMAP's
    matcher does; docs/decisions.md, "Cross-check in the first pass")."""

    matcher: dict[str, Any] = field(default_factory=dict)
    """The matcher's own options by field name, e.g. {"fine_top_k": 3, "coarse.rank_by": "matches"}
    (`--set matcher.KEY=VALUE`, or a `[matcher]` table in a config file); values are checked
    against the chosen method's config dataclass."""

    def __post_init__(self) -> None:
        from matching.registry import METHODS
        from recon.core.engine import check_engine

        if self.method not in METHODS:
            raise UserError(f"--method {self.method!r}: choose one of {', '.join(METHODS)}")
        check_engine(self.engine)
        if self.simulate not in SIMULATE:
            raise UserError(f"--simulate {self.simulate!r}: choose auto, all or needed")
        if self.first_pass_detector not in FIRST_PASS_DETECTORS:
            raise UserError(f"match.first_pass_detector {self.first_pass_detector!r}: choose one of "
                            f"{', '.join(FIRST_PASS_DETECTORS)}")
        if self.simulate_bridges not in SIMULATE_BRIDGES:
            raise UserError(f"match.simulate_bridges {self.simulate_bridges!r}: choose cheap or full")
        for name in ("simulate_strong_inliers", "simulate_min_partners"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise UserError(f"match.{name} {v!r}: an integer >= 0")
        if not isinstance(self.first_pass_contrast, (int, float)) or not 0 < self.first_pass_contrast < 1:
            raise UserError(f"match.first_pass_contrast {self.first_pass_contrast!r}: a number in (0, 1)")
        if isinstance(self.adaptive_above, bool) or not isinstance(self.adaptive_above, int) or self.adaptive_above < 0:
            raise UserError(f"match.adaptive_above {self.adaptive_above!r}: a number of images >= 0 (0 = never)")
        self.matcher = matcher_options(self.method, self.matcher)


@dataclass
class TracksConfig:
    """The tracks stage: keypoint merging across pairs."""

    merge_px: float = field(default=2.0, metadata={"flag": "--merge-px"})
    """Keypoint merge radius in working px (0 = no merging)."""

    consistent: bool = True
    """Drop the matches that would put two keypoints of one image into one track (greedy, most
    trusted first: `recon.core.tracks.consistent_tracks`); false keeps every merged match."""

    conflict_order: str = field(default="support", metadata={"choices": "recon.core.tracks:CONFLICT_ORDERS"})
    """The consistency check's order of trust after the trusted-first rule: support = descending
    triangle support (keypoints of third images matched to both sides) over all pairs, then
    ascending descriptor distance; pairs = pair by pair, the pairs with more trusted matches first,
    ascending descriptor distance within a pair (the order before 2026-12-04); distance = ascending
    descriptor distance over all pairs (`recon.core.tracks.consistent_tracks`; docs/decisions.md,
    "Conflict order")."""

    trust_px: float = 1.0
    """Distance from the pair's epipolar lines (working px, scaled to full resolution as the verify
    stage scales its threshold) within which a match counts as trusted and goes first in the
    consistency check (`recon.core.tracks.epipolar_inliers`). 1 px measured a little better than the
    verify stage's 4 px (castle_P30 reprojection error 1.174 against 1.198 px, docs/decisions.md)."""

    refine: bool = True
    """Re-localise every observation of a consistent track against the track's anchor observation
    by patch alignment under the local affine of the pair joining them
    (`recon.core.track_refine`; only with `consistent`). False keeps the merged positions."""

    refine_robust_rounds: int = 2
    """Trimmed refits of the local affine under which each observation is aligned to its parent
    (`matching.refine.local_affines_at`); 0 = the plain least-squares fit used before 2026-12-03
    (sacre_coeur 0.287 -> 0.256 px with 2 on the same matches, docs/decisions.md "Robust local
    affines")."""

    def __post_init__(self) -> None:
        import math

        if isinstance(self.merge_px, bool) or not isinstance(self.merge_px, (int, float)) \
                or not (self.merge_px >= 0 and math.isfinite(self.merge_px)):
            raise UserError(f"--merge-px {self.merge_px}: must be >= 0 (0 disables merging)")
        self.merge_px = float(self.merge_px)
        if not (isinstance(self.trust_px, (int, float)) and not isinstance(self.trust_px, bool) and self.trust_px > 0):
            raise UserError(f"tracks.trust_px {self.trust_px}: must be > 0")
        self.trust_px = float(self.trust_px)
        v = self.refine_robust_rounds
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise UserError(f"tracks.refine_robust_rounds {v!r}: an integer >= 0")
        from recon.core.tracks import CONFLICT_ORDERS

        if self.conflict_order not in CONFLICT_ORDERS:
            raise UserError(f"tracks.conflict_order {self.conflict_order!r}: choose one of {', '.join(CONFLICT_ORDERS)}")


@dataclass
class DatabaseConfig:
    """The database stage: cameras, images, keypoints and raw matches in COLMAP's database."""

    camera_mode: str = field(default="auto", metadata={"flag": "--camera-mode",
                                                       "choices": "recon.core.database:CAMERA_MODES"})
    """auto (one camera when all photos share size and EXIF intrinsics), single or per-image."""

    camera_model: str = field(default="SIMPLE_RADIAL", metadata={"flag": "--camera-model",
                                                                 "choices": "recon.core.database:CAMERA_MODELS"})
    """COLMAP camera model (COLMAP's ImageReader.camera_model): SIMPLE_RADIAL (f, cx, cy, k), PINHOLE
    (fx, fy, cx, cy), SIMPLE_PINHOLE, RADIAL (k1, k2) or OPENCV (k1, k2, p1, p2)."""

    def __post_init__(self) -> None:
        from recon.core.database import CAMERA_MODELS, CAMERA_MODES

        if self.camera_mode not in CAMERA_MODES:
            raise UserError(f"--camera-mode {self.camera_mode!r}: choose one of {', '.join(CAMERA_MODES)}")
        if self.camera_model not in CAMERA_MODELS:
            raise UserError(f"--camera-model {self.camera_model!r}: choose one of {', '.join(CAMERA_MODELS)}")


@dataclass
class VerifyConfig:
    """The verify stage: COLMAP's two-view geometry (F / E / H, RANSAC) on every matched pair."""

    max_error_px: float = 4.0
    """RANSAC threshold in working-resolution px; scaled to full-resolution px by the
    working-to-full factor (capped at 3), since the matcher localises to about a working px.
    (Stock COLMAP's 4 full-resolution px instead moved fountain_P11's, sceaux_castle's and
    castle_P30's exhaustive-pair models by noise only, and helped castle_P30's retrieval pairs:
    docs/decisions.md, "Verification threshold".)"""

    min_num_inliers: int = 15
    """Pairs with fewer verified inliers keep no two-view geometry."""

    def __post_init__(self) -> None:
        if not self.max_error_px > 0:
            raise UserError(f"verify.max_error_px {self.max_error_px}: must be > 0")
        if self.min_num_inliers < 0:
            raise UserError(f"verify.min_num_inliers {self.min_num_inliers}: must be >= 0")


@dataclass
class SfmConfig:
    """The sfm stage: COLMAP's incremental mapping (see `recon.core.sfm` for its tuned options)."""

    num_threads: int = 1
    """Threads of incremental mapping (-1 = all cores). One keeps the model reproducible bit for
    bit: multi-threaded bundle adjustment sums in thread order (`recon.core.sfm.MAPPING_THREADS`)."""

    mapper: str = field(default="incremental", metadata={"flag": "--mapper"})
    """incremental (COLMAP's incremental mapper, wide-baseline options) or global (GLOMAP through
    pycolmap.global_mapping; see docs/decisions.md for the measured comparison)."""

    scale_thresholds: bool = False
    """True: multiply the mapper's pixel thresholds (reprojection filters, triangulation, initial
    pair, absolute pose) by the working-to-full-resolution factor (`recon.core.sfm.threshold_scale`,
    7.7 px instead of 4 on 3072 px photos matched at 1600 px). False (default): COLMAP's values in
    full-resolution px, as COLMAP's own pipeline applies them to its keypoints, also detected at
    the working size (the stock comparison, `recon.eval.stock`, maps with these same options): the
    scaled filter kept observations 4-7.7 px off and measured higher reprojection and rotation
    errors (docs/decisions.md, "Mapper thresholds in full-resolution px")."""

    retries: int = 2
    """When the largest model leaves out images the verified pairs connect to it, map again with
    the next seeds (`seed + 1`, ...) up to this many times and keep the model registering the most
    images (`recon.core.sfm.map_with_retries`; scenes of at most `RETRY_MAX_IMAGES` connected
    images). 0 = one mapping. Deterministic for a fixed seed."""

    structure_less_fallback: bool = False
    """COLMAP 4's structure-less registration fallback (an image seeing too few 3D points is
    registered from its 2D-2D correspondences to registered images). Off: in the benchmarks' databases it
    ran only inside a collapsing model, where one of its RANSACs took 7.7 s
    (`recon.core.sfm` module doc; docs/decisions.md, "Structure-less registration off")."""

    final_ba_loss: str = field(default="cauchy", metadata={"choices": "recon.core.sfm:FINAL_BA_LOSSES"})
    """A last global bundle adjustment of the finished model under this robust loss (cauchy,
    soft_l1, huber), then the mapper's own 4 px filter; none = the mapper's model as it ends
    (`recon.core.sfm.final_bundle_adjustment`: lower rotation errors on every benchmark scene,
    for ours and for stock COLMAP, which the comparison maps through the same stage)."""

    final_ba_scale_px: float = 0.0
    """Scale of `final_ba_loss`, full-resolution px: residuals well above it count less than
    their square. 0 = automatic: twice the model's median point error, about 2.4 sigma of its
    keypoint noise (`recon.core.sfm.AUTO_SCALE_FACTOR`; a fixed 0.5 px suited our models but
    made stock `high`'s noisier wide-baseline ones worse, docs/decisions.md)."""

    final_ba_outlier_scales: float = 3.0
    """Second pass of the final adjustment: observations more than this many loss scales off
    after the first pass (Cauchy weight under 10 %) are dropped and the model adjusted again,
    within the same 100 iterations; 0 = one pass and the mapper's 4 px filter only
    (`recon.core.sfm.OUTLIER_SCALES`; lower reprojection and equal or lower rotation errors for
    ours and for stock on the real scenes, docs/decisions.md)."""

    final_ba_principal_point: str = field(default="auto", metadata={"choices": "recon.core.sfm:PRINCIPAL_POINT_MODES"})
    """The principal point in the final adjustment. auto (default): freed only when the
    adjustment's covariance says the views determine it to 0.2 % of the image
    (`recon.core.sfm.PP_SIGMA_MAX`; one covariance estimate, about a second): where a capture
    constrains it (castle_P30, fountain_P11, whose calibrated principal point lies 15-20 px
    off-centre) the median rotation error falls from 0.43° / 0.23° to 0.07° / 0.05°, while
    cameras in a row at one height (every render here) keep it fixed. fixed: COLMAP's image
    centre, as COLMAP's own mapper does. refine: always freed; where the views do not determine
    it, it drifts by 12-200 px and the poses with it. docs/decisions.md, "The principal point in
    the final adjustment"."""

    def __post_init__(self) -> None:
        from recon.core.global_sfm import MAPPERS
        from recon.core.sfm import FINAL_BA_LOSSES, PRINCIPAL_POINT_MODES

        if self.mapper not in MAPPERS:
            raise UserError(f"--mapper {self.mapper!r}: choose one of {', '.join(MAPPERS)}")
        if self.num_threads == 0 or self.num_threads < -1:
            raise UserError(f"sfm.num_threads {self.num_threads}: use -1 (all cores) or at least 1")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or self.retries < 0:
            raise UserError(f"sfm.retries {self.retries!r}: a whole number >= 0 (0 = map once)")
        if self.final_ba_loss not in FINAL_BA_LOSSES:
            raise UserError(f"sfm.final_ba_loss {self.final_ba_loss!r}: choose one of {', '.join(FINAL_BA_LOSSES)}")
        if isinstance(self.final_ba_scale_px, bool) or not isinstance(self.final_ba_scale_px, (int, float)) \
                or not self.final_ba_scale_px >= 0:
            raise UserError(f"sfm.final_ba_scale_px {self.final_ba_scale_px!r}: a number of px >= 0 (0 = automatic)")
        if isinstance(self.final_ba_outlier_scales, bool) or not isinstance(self.final_ba_outlier_scales, (int, float)) \
                or not self.final_ba_outlier_scales >= 0:
            raise UserError(f"sfm.final_ba_outlier_scales {self.final_ba_outlier_scales!r}: a number of loss scales >= 0 "
                            "(0 = no outlier pass)")
        if self.final_ba_principal_point not in PRINCIPAL_POINT_MODES:
            raise UserError(f"sfm.final_ba_principal_point {self.final_ba_principal_point!r}: choose one of "
                            f"{', '.join(PRINCIPAL_POINT_MODES)}")


@dataclass
class RunConfig:
    """Options of one reconstruction (`recon run`, `recon.core.pipeline.run_scene`)."""

    output: OutputConfig = field(default_factory=OutputConfig)
    load: LoadConfig = field(default_factory=LoadConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    tracks: TracksConfig = field(default_factory=TracksConfig)
    database: DatabaseConfig = field(default_factory=DatabaseConfig)
    verify: VerifyConfig = field(default_factory=VerifyConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)

    seed: int = field(default=0, metadata={"flag": "--seed"})
    """Seed for the matcher and COLMAP's RANSAC."""

    workers: int = field(default=0, metadata={"flag": "--workers"})
    """Parallel pair tasks (0 = all cores)."""

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed <= MAX_SEED:
            raise UserError(f"--seed {self.seed}: must be an integer in [0, {MAX_SEED}]")
        if self.workers < 0:
            raise UserError(f"--workers {self.workers}: must be >= 0 (0 = all cores)")

    @property
    def num_workers(self) -> int:
        return self.workers or (os.cpu_count() or 1)

    def to_dict(self) -> dict[str, Any]:
        """Nested plain data (paths as strings): the report's `config`, and what `from_dict` reads."""
        return _plain(dataclasses.asdict(self))

    @staticmethod
    def from_dict(data: dict[str, Any]) -> RunConfig:
        """From nested data (`to_dict()`'s shape; a top-level `matcher` table is `match.matcher`).
        Values may be strings (parsed by the field's type); unknown keys raise UserError."""
        return _build(RunConfig, _normalise(data), "")

    @staticmethod
    def from_options(**options: Any) -> RunConfig:
        """From `recon run`'s flag names (`out`, `method`, `pairs`, `max_size`, ...) and dotted
        keys (`"tracks.merge_px"`, `"matcher.fine_top_k"` via `**{...}`), over the defaults."""
        return RunConfig.from_dict(_nest({_flag_paths().get(k, k): v for k, v in options.items()}))


# presets ----------------------------------------------------------------------------------------
PRESETS: dict[str, dict[str, Any]] = {
    # The extra-affine matcher at 1600 px, exhaustive pairs, 2 px keypoint merging: the
    # configuration every figure in the README and docs/decisions.md was measured with.
    "default": {},
    # A quarter of the default's pixels (800 px working size): quicker matching and less memory
    # on photos larger than 800 px, fewer and less precise matches; the same as `default` on
    # images already at most 800 px (the rendered scenes).
    "fast": {"load": {"max_size": 800}},
    # OpenCV's SIFT with a ratio test in place of the extra-affine matcher, same pipeline: fast
    # and deterministic (the tests use it), and the in-pipeline baseline for a matcher comparison.
    "sift": {"match": {"method": "sift"}},
    # The extra-affine matcher with adaptive per-pair paths (matching.adaptive): pairs whose
    # originals already match well skip the simulated views. About half the matching work on
    # fountain_P11 at equal accuracy, but fewer verified inliers and a larger rotation error on the
    # rendered wide-baseline facades (README, "Real multi-view scenes"): for large, ordinary captures.
    "adaptive": {"match": {"matcher": {"adaptive": True}}},
}
"""Named configurations (nested option dicts over `RunConfig()`), chosen with `recon run --preset`."""


def preset(name: str) -> RunConfig:
    """The named preset as a RunConfig; UserError naming the presets for an unknown name."""
    if name not in PRESETS:
        raise UserError(f"--preset {name!r}: choose one of {', '.join(PRESETS)}")
    return RunConfig.from_dict(PRESETS[name])


def build_run_config(preset_name: str = "default", config_file: str | Path | None = None,
                     options: dict[str, Any] | None = None, settings: list[str] | None = None) -> RunConfig:
    """preset < config file < `options` (dotted keys, e.g. flags given on the command line, or
    `recon run`'s flag names as in `RunConfig.from_options`) < `settings` (`KEY=VALUE` strings of
    `--set`); see the module doc."""
    data = preset(preset_name).to_dict()
    if config_file is not None:
        data = _merge(data, _normalise(read_config_file(config_file)))
    paths = _flag_paths()
    data = _merge(data, _normalise(_nest({paths.get(k, k): v for k, v in (options or {}).items()})))
    for text in settings or []:
        key, sep, value = text.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--set {text!r}: expected KEY=VALUE, e.g. matcher.fine_top_k=3")
        data = _merge(data, _normalise(_nest({key.strip(): value.strip()})))
    return RunConfig.from_dict(data)


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A TOML (`.toml`) or JSON file of nested options; UserError when unreadable."""
    p = Path(path).expanduser()
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise UserError(f"--config {p}: {e.strerror or e}") from None
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import tomllib

            data = tomllib.loads(text)
    except ImportError:
        raise UserError(f"--config {p}: TOML needs Python 3.11 or newer; use a .json file") from None
    except ValueError as e:  # json.JSONDecodeError and tomllib.TOMLDecodeError
        raise UserError(f"--config {p}: {' '.join(str(e).split())}") from None
    if not isinstance(data, dict):
        raise UserError(f"--config {p}: expected a table of options at the top level")
    return data


# documentation and the CLI ------------------------------------------------------------------------
@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """{field name: its attribute docstring} of a dataclass (the string right under the field)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, nxt in zip(body, body[1:], strict=False):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr) \
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str):
            docs[node.target.id] = inspect.cleandoc(nxt.value.value)
    return docs


@dataclass(frozen=True)
class OptionSpec:
    """One option of `RunConfig` as the CLI shows it."""

    path: str  # dotted path in RunConfig, e.g. "load.max_size"
    name: str  # the keyword name (flag without dashes), e.g. "max_size"
    flag: str  # click's declaration, e.g. "--max-size" or "--progress/--no-progress"
    type: Any  # the field's type (Literal types stay Literal)
    default: Any
    help: str
    choices: tuple[str, ...] = ()  # the valid values of a str option (its metadata's "choices")


def run_options() -> list[OptionSpec]:
    """Every RunConfig field with a `flag`, in declaration order: what `recon run` offers."""
    out = []
    for path, f, owner in _leaves(RunConfig):
        flag = f.metadata.get("flag")
        if flag:
            default = f.default_factory() if f.default is dataclasses.MISSING else f.default  # type: ignore[misc,operator]
            out.append(OptionSpec(path, flag.split("/")[0].lstrip("-").replace("-", "_"), flag,
                                  typing.get_type_hints(owner)[f.name], default,
                                  " ".join(field_docs(owner).get(f.name, "").split()),
                                  _choices(f.metadata.get("choices"))))
    return out


def _choices(ref: str | None) -> tuple[str, ...]:
    """The values named by a field's "choices" metadata, "module:NAME" (imported lazily: this
    module imports neither matching nor pycolmap at load time)."""
    if not ref:
        return ()
    import importlib

    module, _, name = ref.partition(":")
    return tuple(str(c) for c in getattr(importlib.import_module(module), name))


def option_paths() -> list[str]:
    """Every dotted key `--set` accepts besides `matcher.KEY`."""
    return [p for p, _, _ in _leaves(RunConfig) if p != "match.matcher"]


# matcher options ------------------------------------------------------------------------------------
def matcher_fields(method: str) -> dict[str, Any]:
    """{dotted option name: type} of the matcher `method`'s config dataclass (nested sections
    as `section.field`), read from `matching.registry.get_matcher(method).cfg`."""
    from matching.registry import get_matcher

    cfg = getattr(get_matcher(method), "cfg", None)
    if not dataclasses.is_dataclass(cfg):
        return {}
    out: dict[str, Any] = {}

    def walk(cls: type, prefix: str) -> None:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            t = hints[f.name]
            if dataclasses.is_dataclass(t):
                walk(t, f"{prefix}{f.name}.")  # type: ignore[arg-type]
            else:
                out[f"{prefix}{f.name}"] = t

    walk(type(cfg), "")
    return out


def matcher_options(method: str, options: dict[str, Any]) -> dict[str, Any]:
    """`options` checked against the matcher's config and parsed by each field's type;
    UserError naming the valid options for an unknown one."""
    if not options:
        return {}
    known = matcher_fields(method)
    out = {}
    for key, value in _flatten(options).items():
        leaf = key.rsplit(".", 1)[-1]
        if leaf in RESERVED_MATCHER_KEYS:
            raise UserError(f"matcher.{key}: {RESERVED_MATCHER_KEYS[leaf]}")
        if key not in known:
            valid = ", ".join(k for k in known if k.rsplit(".", 1)[-1] not in RESERVED_MATCHER_KEYS)
            raise UserError(f"matcher.{key}: not an option of the {method} matcher; valid: {valid}")
        out[key] = parse_value(value, known[key], f"matcher.{key}")
    return out


# parsing values by type -----------------------------------------------------------------------------
_TRUE, _FALSE = {"1", "true", "yes", "on"}, {"0", "false", "no", "off"}


def parse_value(value: Any, typ: Any, name: str) -> Any:
    """`value` (a string from --set, or a TOML/JSON value) as type `typ`; UserError otherwise."""
    origin, args = typing.get_origin(typ), typing.get_args(typ)
    if origin is Literal:
        choices = list(args)
        v = value if not isinstance(value, str) else next((c for c in choices if str(c) == value), value)
        if v not in choices:
            raise UserError(f"{name} {value!r}: choose one of {', '.join(map(str, choices))}")
        return v
    if origin in (typing.Union, types.UnionType):
        if value is None or (isinstance(value, str) and value.lower() in ("", "none", "null")):
            if type(None) in args:
                return None
        return parse_value(value, next(a for a in args if a is not type(None)), name)
    try:
        if typ is bool:
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in _TRUE | _FALSE:
                return value.lower() in _TRUE
            raise ValueError
        if typ is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if typ is float:
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if typ is str:
            if not isinstance(value, str):
                raise ValueError
            return value
        if typ is Path:
            return Path(str(value)).expanduser()
    except (TypeError, ValueError):
        raise UserError(f"{name} {value!r}: expected {getattr(typ, '__name__', typ)}") from None
    return value


# helpers --------------------------------------------------------------------------------------------
def _plain(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return str(v) if isinstance(v, Path) else v


def _leaves(cls: type, prefix: str = "") -> list[tuple[str, dataclasses.Field, type]]:
    """(dotted path, field, owning class) of every non-section field, declaration order."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if dataclasses.is_dataclass(hints[f.name]):
            out += _leaves(hints[f.name], f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", f, cls))
    return out


@functools.cache
def _flag_paths() -> dict[str, str]:
    return {o.name: o.path for o in run_options()}


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    """{"load.max_size": 800, "matcher.coarse.rank_by": "x"} -> nested dicts (matcher keys stay
    dotted under "matcher")."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        head, _, rest = key.partition(".")
        if head == MATCHER_KEY and rest:
            out.setdefault(MATCHER_KEY, {})[rest] = value
        elif rest:
            out.setdefault(head, {})
            if not isinstance(out[head], dict):
                raise UserError(f"{head} is an option, not a section; {key!r} is not valid")
            out[head] = _merge(out[head], _nest({rest: value}))
        else:
            out[key] = value
    return out


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """Nested option tables -> {"a.b": value}."""
    if not isinstance(d, dict):
        raise UserError(f"{prefix.rstrip('.') or MATCHER_KEY}: expected a table of options")
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _normalise(d: dict[str, Any]) -> dict[str, Any]:
    """A top-level `matcher` table moved to match.matcher (flat dotted keys)."""
    d = dict(d)
    if MATCHER_KEY in d:
        m = _flatten(d.pop(MATCHER_KEY))
        d["match"] = {**(d.get("match") or {}), "matcher": {**((d.get("match") or {}).get("matcher") or {}), **m}}
    return d


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _build(cls: type, data: Any, prefix: str) -> Any:
    """cls(**data) with nested sections, values parsed by field type, unknown keys refused."""
    where = prefix.rstrip(".") or "the run config"
    if not isinstance(data, dict):
        raise UserError(f"{where}: expected a table of options, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = [k for k in data if k not in fields]
    if unknown:
        valid = [p for p in option_paths() if p.startswith(prefix)] if prefix else option_paths() + ["matcher.KEY"]
        raise UserError(f"unknown option {prefix}{unknown[0]!s}; valid: {', '.join(valid)}")
    kw = {}
    for name, value in data.items():
        t = hints[name]
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            kw[name] = _build(t, value, f"{prefix}{name}.")
        elif name == "matcher" and cls is MatchConfig:
            kw[name] = _flatten(value or {})
        else:
            kw[name] = parse_value(value, t, f"{prefix}{name}")
    return cls(**kw)
