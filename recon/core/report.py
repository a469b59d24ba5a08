"""The run report (`OUT/report.json`) and the console summary table.

`report.json` keys (all always present; docs/report-schema.md lists every key with its unit):

* `schema_version` (`SCHEMA_VERSION`; bumped when a key is renamed or changes meaning; reports
  without it are version 1) and `versions` (the tool, Python, pycolmap, OpenCV, numpy);
* `status`: "ok", or "no_model" when SfM registered nothing (then `message` says why), or
  "incomplete" while a new model replaces an older one (`recon.core.stages.sfm.replace_model`);
* `num_images` (usable images), `registered_images`, `num_points3D`, `mean_track_length` and
  `mean_reprojection_error` (px) of the kept (largest) model, `num_models`, `model_sizes`;
* `tracks`: track lengths of the *verified* match graph before SfM, with keypoint merging
  (`merged`: `num_tracks`, `mean_length`, `max_length`, `inconsistent` tracks holding two
  keypoints of one image, `inconsistent_share` of the observations, and
  `consistent_mean_length`, the figure the console shows; see `recon.core.tracks.track_stats`) and
  without (`unmerged`: every pair keeps its own keypoints, so every track has length exactly 2).
  `mean_track_length` above is the model's (after SfM with merging). A reconstruction without
  merging can be measured with `--merge-px 0` (see `recon.core.tracks`); the stock comparison's
  `tracks` has one entry, `graph` (its keypoints are per image already);
* `seconds_total`, `peak_mb` (peak resident memory during the run, sampled) and `peak_growth_mb`
  (its growth over the memory before the run), `stages` (seconds per stage, in order) and
  `stages_reused` (stages skipped because an earlier run built their outputs from the same key);
* `pairs`: one row per pair in pair order: `image0`, `image1`, `reference` (name of the image
  the matcher simulated, or null), `best_view` ({t, phi, s} or null), `raw_matches` (matcher
  output), `merged_matches` (after keypoint merging), `verified_inliers` (COLMAP's two-view
  geometry), `distinct_inliers` (those counted once per distinct pair of keypoint positions:
  COLMAP's SIFT keeps two orientations of one point as two keypoints, `tracks.distinct_correspondences`),
  `confirmed_inliers` (those whose two keypoints are both matched to one keypoint of a third image
  in the verified graph, `tracks.triangle_support`: a pair whose inliers no third image confirms
  in a scene where others are confirmed is one to look at),
  `two_view_config` (COLMAP's two-view model; `config` in version 1), `cached`
  (loaded from the pair cache), `reason`;
* `skipped`: [{name, reason}] for unreadable, corrupt, duplicate or un-importable images;
* `warnings`, `config` (the RunConfig, nested as `recon.config.RunConfig.to_dict`), `method` (the
  matcher, or `colmap-sift`), `preset` (stock COLMAP's preset; empty for `recon run`),
  `camera_mode_used`, `pairs_computed`, `pairs_cached`, `pairs_expanded` (`+expand:E`: the
  pairs each match-graph expansion round added; they are part of `pairs`), `pairs_simulated`
  (extra-affine pairs whose matching simulated views: paths `targeted` and `full`, not
  `originals` or `deferred`; see `match.simulate`), `simulate_used` (`match.simulate` resolved for
  the scene: `all` or `needed`, `auto` being `needed` above `match.adaptive_above` images),
  `features_computed` / `features_reused` (FeatureStore entries: each image's features are
  computed once per run and shared by all its pairs), `database_reused`, `model_reused`,
  `merge` (keypoint merging counts), `scene`, `out`;
* `verified_pairs`, `inliers_per_pair_mean` / `_median` and `distinct_inliers_per_pair_mean`
  (over verified pairs), `num_keypoints`
  (per image, as written to the database) and `num_keypoints_mean`;
* `sfm_options` (the incremental mapper's options) and `colmap_options` (`verification`, and for
  stock also `extraction` and `matching`): pycolmap's own `todict()` of the options used
  (`options_dict`), every field, not a hand-picked few;
* `sfm_growth`: one row per registration step of incremental mapping, in order: `step`,
  `model` (index of the model being built), `image` (just registered), `registered_images`
  and `num_points3D` of that model right after the step, and `initial_pair` (both images of the
  model's initial pair, by image id, on the model's first step; null on the others and in runs
  made before version 2) (kept from the run that built the model when the model is reused);
* `sfm_attempts`: one row per mapping of the incremental mapper (`sfm.retries`,
  `recon.core.sfm.map_with_retries`): `seed`, `model_sizes`, `registered` and `points` of its
  largest model, `chosen` (the model kept, whose steps `sfm_growth` lists; the live progress and
  Rerun's growth replay show the first mapping's); one row unless images were left out; empty
  for the global mapper and in reports made before the field;
* `final_ba`: the final robust bundle adjustment (`recon.core.sfm.final_bundle_adjustment`):
  `loss`, `applied`, and when applied `scale_px`, `auto_scale`, `mean_reprojection_error_before` / `_after`,
  `observations_dropped` by the mapper's filter afterwards, `seconds`.

Units: seconds (`seconds*`, `stages`), MB = 10^6 bytes (`*_mb`), pixels of the full-resolution
photo (`mean_reprojection_error`), degrees (`best_view.phi`); `scene` and `out` are absolute.
`read_report` reads any version back as the current one.

Files are written to a temporary name and `os.replace`d, so a kill never leaves half a report.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from recon.core.jsonio import write_json_atomic

SCHEMA_VERSION = 3
"""report.json's schema: 1 = before the field existed; 2 = `schema_version`, `versions`, pair rows'
`two_view_config` (was `config`), `sfm_growth[].initial_pair`; 3 = `final_ba.principal_point_sigma`
(was `principal_point_probe_gap`, with `sfm.final_ba_principal_point=auto`)."""


@dataclass
class PairRow:
    image0: str
    image1: str
    reference: str | None = None
    best_view: dict[str, float] | None = None
    raw_matches: int = 0
    merged_matches: int = 0
    verified_inliers: int = 0
    distinct_inliers: int = 0  # verified inliers counted once per distinct pair of positions (tracks.distinct_correspondences)
    confirmed_inliers: int = 0  # verified inliers that a third image confirms (tracks.triangle_support >= 1)
    two_view_config: str = ""  # COLMAP's TwoViewGeometry configuration, e.g. CALIBRATED, PLANAR
    cached: bool = False
    seconds: float = 0.0
    reason: str = ""
    path: str = ""  # the matcher's adaptive path: "originals", "targeted" or "full" (matching.adaptive)
    path_reason: str = ""  # why that path
    planned_path: str = ""  # the path the originals' evidence points to (matching.adaptive.plan_pair), adaptive or not
    finishing: str = ""  # what the matcher's finishing steps did (the epipolar round's gain or why it was skipped, refinement)


@dataclass
class RunReport:
    scene: str
    out: str
    schema_version: int = SCHEMA_VERSION
    versions: dict[str, str] = field(default_factory=dict)
    status: str = "ok"
    message: str = ""
    num_images: int = 0
    registered_images: int = 0
    num_points3D: int = 0
    mean_track_length: float = 0.0
    mean_reprojection_error: float | None = None
    num_models: int = 0
    model_sizes: list[int] = field(default_factory=list)
    registered: list[str] = field(default_factory=list)
    tracks: dict[str, Any] = field(default_factory=dict)
    merge: dict[str, Any] = field(default_factory=dict)
    seconds_total: float = 0.0
    peak_mb: float = 0.0
    stages: dict[str, float] = field(default_factory=dict)
    pairs_computed: int = 0
    pairs_cached: int = 0
    pairs_expanded: list[int] = field(default_factory=list)  # match-graph expansion: new pairs per round
    pairs_simulated: int = 0  # extra-affine pairs whose matching simulated views (path "targeted" or "full")
    simulate_used: str = ""  # extra-affine: `match.simulate` resolved for the scene ("all" / "needed"); "" other methods
    features_computed: int = 0  # FeatureStore entries computed this run (one per image and kind)
    features_reused: int = 0  # entries served from memory or the disk cache
    camera_mode_used: str = ""
    database_reused: bool = False
    model_reused: bool = False
    num_points_ply: int = 0
    method: str = ""
    preset: str = ""
    verified_pairs: int = 0
    inliers_per_pair_mean: float = 0.0
    inliers_per_pair_median: float = 0.0
    distinct_inliers_per_pair_mean: float = 0.0
    num_keypoints_mean: float = 0.0
    num_keypoints: dict[str, int] = field(default_factory=dict)
    peak_growth_mb: float | None = None
    stages_reused: list[str] = field(default_factory=list)
    sfm_options: dict[str, Any] = field(default_factory=dict)
    colmap_options: dict[str, Any] = field(default_factory=dict)
    sfm_growth: list[dict[str, Any]] = field(default_factory=list)
    sfm_attempts: list[dict[str, Any]] = field(default_factory=list)
    final_ba: dict[str, Any] = field(default_factory=dict)
    pairs: list[PairRow] = field(default_factory=list)
    skipped: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    config: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def __post_init__(self) -> None:
        if not self.versions:
            from recon.version import library_versions

            self.versions = library_versions()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def set_model(self, stats: dict[str, Any], registered: list[str]) -> None:
        """Copy a model's headline numbers (`sfm.model_stats`) and registered image names."""
        self.registered_images = stats["registered_images"]
        self.num_points3D = stats["num_points3D"]
        self.mean_track_length = stats["mean_track_length"]
        self.mean_reprojection_error = stats["mean_reprojection_error"]
        self.registered = registered


    def set_pair_summary(self) -> None:
        """`verified_pairs` and inliers per verified pair from `pairs`; keypoints per image mean."""
        for key, value in inlier_summary([(p.verified_inliers, p.distinct_inliers) for p in self.pairs]).items():
            setattr(self, key, value)
        self.num_keypoints_mean = float(np.mean(list(self.num_keypoints.values()))) if self.num_keypoints else 0.0


def inlier_summary(counts: list[tuple[int, int]]) -> dict[str, Any]:
    """`verified_pairs`, `inliers_per_pair_mean` / `_median` and `distinct_inliers_per_pair_mean`
    over the pairs with verified inliers, from (verified inliers, distinct inliers) per pair."""
    kept = [(v, d) for v, d in counts if v > 0]
    verified = [v for v, _ in kept]
    return {"verified_pairs": len(kept),
            "inliers_per_pair_mean": float(np.mean(verified)) if kept else 0.0,
            "inliers_per_pair_median": float(np.median(verified)) if kept else 0.0,
            "distinct_inliers_per_pair_mean": float(np.mean([d for _, d in kept])) if kept else 0.0}


def write_report(report: RunReport, path: str | Path) -> None:
    write_json_atomic(path, report.to_dict())


def upgrade_report(data: dict[str, Any]) -> dict[str, Any]:
    """A report.json of any schema version as the current one (a copy): version 1's pair `config`
    becomes `two_view_config`, growth rows get `initial_pair` null, missing keys their defaults."""
    out = dict(data)
    out.setdefault("schema_version", 1)
    out.setdefault("versions", {})
    pairs = []
    for p in out.get("pairs", []):
        p = dict(p)
        if "config" in p and "two_view_config" not in p:
            p["two_view_config"] = p.pop("config")
        pairs.append(p)
    out["pairs"] = pairs
    out["sfm_growth"] = [{"initial_pair": None, **g} for g in out.get("sfm_growth", [])]
    return out


def read_report(path: str | Path) -> RunReport:
    """OUT/report.json (any schema version) as a RunReport; keys this version does not know are dropped."""
    import json

    data = upgrade_report(json.loads(Path(path).read_text(encoding="utf-8")))
    known = {f.name for f in fields(RunReport)}
    pair_keys = {f.name for f in fields(PairRow)}
    data = {k: v for k, v in data.items() if k in known}
    data["pairs"] = [PairRow(**{k: v for k, v in p.items() if k in pair_keys}) for p in data.get("pairs", [])]
    report = RunReport(**data)
    report.versions = dict(data["versions"])  # as recorded (empty for version 1), not this process's
    return report


def options_dict(options: Any) -> dict[str, Any]:
    """pycolmap options (e.g. `IncrementalPipelineOptions`) as plain JSON data through their own
    `todict()`: every field, nested options as dicts, enums by name, sets as sorted lists."""

    def plain(v: Any) -> Any:
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, (set, frozenset)):
            return sorted(plain(x) for x in v)
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        return getattr(v, "name", None) or str(v)

    return plain(options.todict())


def final_ba_row(report: RunReport) -> tuple[str, str] | None:
    """(label, value) of the reprojection error before the final robust adjustment, for the
    summaries (console and Rerun); None when the step did not run."""
    fba = report.final_ba or {}
    if not fba.get("applied"):
        return None
    outliers = (f", {fba['outliers_dropped']} observations over {fba['outlier_threshold_px']:.2f} px dropped"
                if "outlier_threshold_px" in fba else "")
    return (f"before the final {fba['loss']} adjustment (scale {fba['scale_px']:.2f} px{outliers})",
            f"{fba['mean_reprojection_error_before']:.3f}")


def principal_point_row(report: RunReport) -> tuple[str, str] | None:
    """(label, value) of what the final adjustment did with the principal point (`auto`: freed
    or kept at the image centre, with the covariance's standard deviation against its limit),
    for the summaries (console and Rerun); None when the step did not run."""
    fba = report.final_ba or {}
    if not fba.get("applied") or "principal_point" not in fba:
        return None
    where = "refined" if fba.get("principal_point_refined") else "fixed at the image centre"
    if fba["principal_point"] != "auto":
        return (f"principal point ({fba['principal_point']})", where)
    from recon.core.sfm import PP_SIGMA_MAX

    sigma = fba.get("principal_point_sigma")
    how = ("the views do not determine it" if sigma is None else
           f"sd {100 * sigma:.2g} % of the image, limit {100 * PP_SIGMA_MAX:.2g} %")
    return ("principal point (auto)", f"{where} ({how})")


def summary_table(report: RunReport):
    """A rich Table with the headline numbers and seconds per stage."""
    from rich.table import Table

    t = Table(title=f"recon run: {Path(report.scene).name}", show_header=True, header_style="bold")
    t.add_column("metric")
    t.add_column("value", justify="right")
    t.add_row("status", report.status if report.ok else f"[red]{report.status}[/red]")
    t.add_row("images (usable / skipped)", f"{report.num_images} / {len(report.skipped)}")
    t.add_row("registered images", f"{report.registered_images} / {report.num_images}")
    if len(report.sfm_attempts) > 1:  # the mapper was retried (`sfm.retries`): images per seed
        t.add_row("  mapping attempts (seed: images)", ", ".join(
            f"{a['seed']}: {a['registered']}" + (" (kept)" if a.get("chosen") else "") for a in report.sfm_attempts))
    t.add_row("3D points", str(report.num_points3D))
    t.add_row("mean track length (model)", f"{report.mean_track_length:.2f}")
    merged = report.tracks.get("merged", {})
    if merged:
        t.add_row("mean track length (graph, consistent tracks, merged / unmerged)",
                  f"{merged.get('consistent_mean_length', merged.get('mean_length', 0.0)):.2f} / "
                  f"{report.tracks.get('unmerged', {}).get('mean_length', 0.0):.2f}")
        if merged.get("inconsistent_share", 0.0) > 0:
            t.add_row("  observations in inconsistent graph tracks", f"{100 * merged['inconsistent_share']:.0f} %")
    refined = (report.merge or {}).get("track_refine")
    if refined and refined.get("aligned"):
        t.add_row("observations re-localised by track refinement",
                  f"{refined['moved']} / {refined['aligned']} (median {refined['median_shift_px']:.2f} px)")
    err = report.mean_reprojection_error
    t.add_row("mean reprojection error (px)", "-" if err is None else f"{err:.3f}")
    before_final_ba = final_ba_row(report)
    if before_final_ba:
        t.add_row(f"  {before_final_ba[0]}", before_final_ba[1])
    principal_point = principal_point_row(report)
    if principal_point:
        t.add_row(f"  {principal_point[0]}", principal_point[1])
    t.add_row("pairs (computed / cached)", f"{report.pairs_computed} / {report.pairs_cached}")
    if report.method == "extra-affine":
        mode = f" (--simulate {report.simulate_used})" if report.simulate_used else ""
        t.add_row("pairs with simulated views", f"{report.pairs_simulated} / {len(report.pairs)}{mode}")
    if report.pairs_expanded:
        t.add_row("  of which from match-graph expansion (per round)", " + ".join(map(str, report.pairs_expanded)))
    verified = sum(1 for p in report.pairs if p.verified_inliers > 0)
    t.add_row("pairs verified", f"{verified} / {len(report.pairs)}")
    inliers = sum(p.verified_inliers for p in report.pairs)
    if inliers and report.num_images > 2:
        confirmed = sum(p.confirmed_inliers for p in report.pairs)
        unconfirmed = sum(1 for p in report.pairs if p.verified_inliers > 0 and p.confirmed_inliers == 0)
        note = f" (none in {unconfirmed} pair{'s' if unconfirmed > 1 else ''})" if unconfirmed else ""
        t.add_row("  verified inliers a third image confirms", f"{100 * confirmed / inliers:.0f} %{note}")
    for k, v in report.stages.items():
        t.add_row(f"  {k} (s)", f"{v:.1f}" + (" (reused)" if k in report.stages_reused else ""))
    t.add_row("total (s)", f"{report.seconds_total:.1f}")
    t.add_row("peak memory (MB)", f"{report.peak_mb:.0f}")
    t.add_row("output", report.out)
    return t
