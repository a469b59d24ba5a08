"""`recon compare`: the extra-affine pipeline against COLMAP's stock SIFT matching, same images.

`compare_scene(scene_dir, out, presets=("default",), max_size, pairs, seed)` runs, in this one
process and on the same images and pairs:

* stock COLMAP (`recon.eval.stock.run_stock`) for each preset into `OUT/stock-<preset>/`;
* ours (`recon.core.pipeline.run_scene`, method extra-affine) into `OUT/extra_affine/`;

then evaluates both models against the scene's ground truth when it has one (`recon.eval.gt`,
`recon.eval.evaluate`, matched by image name), compares the two point clouds (`compare_clouds`) and
writes `OUT/compare.json` atomically:

    {"scene", "out", "config", "gt", "warnings",
     "stock": {...}, "extra_affine": {...},          # report.json keys + pair summary + GT keys
     "methods": {"stock-<preset>": {...}, ..., "extra_affine": {...}},
     "clouds": {...}, "clouds_by_stock": {"<preset>": {...}},
     "rotation_gap_by_stock": {"<preset>": {...} | None}}

`rotation_gap_by_stock` (with GT): ours' median relative rotation error minus each stock preset's
over the pairs both models hold, with a 95 % interval from resampling the images
(`evaluate.paired_rotation_gap`): whether a gap of hundredths of a degree is the pipelines' or the
particular images'.

`stock` is the first preset's run. Each method object holds the keys of `recon run`'s
report.json plus `verified_pairs`, `inliers_per_pair_mean/median`, `peak_mb` (the absolute RSS
peak during that run, sampled by `matching.memory.PeakRss`: `ru_maxrss` would carry an earlier
run's peak into later ones; the run's own figure is kept as `report_peak_mb`), and, with GT,
`rel_rot_err_deg_median`, `rel_trans_err_deg_median`, `auc_5/10/20`, `center_err_median`,
`center_err_rel_median` (the full evaluation without per-pair rows is under `gt_eval`; the
per-pair rotation errors under `gt_pair_rot_err`, `[image0, image1, degrees]`), and
`correct_per_pair`: on a rendered scene (`gt/scene.json` holds its planes) the mean verified
correspondences per verified pair that lie within sqrt(3) px of the exact transfer
(`recon.eval.gt_planes`) and `correct_median_px`, their median distance from it, else None.

Problems that must not end the comparison: a missing / malformed GT, or GT naming images the
scene lacks (a one-line warning naming the file, evaluation skipped); a stock run that finds no
model (its status and message are reported; the clouds are then skipped with a message).

Point clouds (`compare_clouds`): ours is aligned to stock with a similarity (`evaluate.umeyama`)
estimated from the camera centres of images registered in both models, paired by image NAME
(never by id: the two databases number images independently). Distances are open3d's
`compute_point_cloud_distance` (nearest neighbour, each direction), reported as median and 90th
percentile in the stock model's units and relative to the stock scene extent (the diagonal of
the 1st-99th percentile bounding box of its points, robust to stray points). Completeness of a
method is the fraction of its points within `threshold_rel` (default 1 %) of the extent of the
other method's cloud.

`run_scenes` does the same over every scene folder under a root (`recon bench scenes`,
`benchmarks/bench_scenes.py`) and `scenes_table` prints one summary table.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from matching.errors import InputError
from matching.memory import RUN_INTERVAL_S, PeakRss
from recon.config import DEFAULT_MAX_SIZE, SfmConfig
from recon.core.jsonio import write_json_atomic
from recon.core.scene import IMAGE_EXTS
from recon.errors import UserError
from recon.eval.evaluate import center, evaluate_model, paired_rotation_gap, umeyama
from recon.eval.gt import find_gt, gt_source
from recon.eval.gt_planes import correct_counts, correct_error_median, correct_per_pair, transfer_errors

OURS = "extra-affine"  # the matcher
OURS_KEY = "extra_affine"  # its key in compare.json and its output folder
GT_KEYS = ("rel_rot_err_deg_median", "rel_trans_err_deg_median", "auc_5", "auc_10", "auc_20",
           "center_err_median", "center_err_rel_median")
Log = Callable[[str], None]
log = logging.getLogger(__name__)


def _nolog(_: str) -> None:
    pass


# scenes and ground truth ------------------------------------------------------------------------
def discover_scenes(root: Path) -> list[str]:
    """Sub-folders of `root` holding images (in images/ or at their top level), sorted."""
    out = []
    for d in sorted(p for p in Path(root).iterdir() if p.is_dir() and not p.name.startswith(".")):
        img = d / "images" if (d / "images").is_dir() else d
        if any(f.suffix.lower() in IMAGE_EXTS for f in img.iterdir() if f.is_file()):
            out.append(d.name)
    return out


def load_gt(scene_dir: Path) -> tuple[Any, dict[str, Any] | None, str | None]:
    """(gt or None, {"format", "path", "num_images"} or None, warning or None). A missing GT is
    not a warning; a malformed one (or one naming images the scene lacks) is, naming the file."""
    try:
        gt = find_gt(scene_dir)
        src = gt_source(scene_dir)
    except InputError as e:
        return None, None, f"ground truth unusable, comparing without it: {e}"
    if gt is None or src is None:
        return None, None, None
    return gt, {"format": src[0], "path": str(src[1]), "num_images": len(gt)}, None


def load_model(model_dir: Path):
    import pycolmap

    if not Path(model_dir).is_dir():
        return None
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception:
        return None


# one method -------------------------------------------------------------------------------------
def pair_summary(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    """`num_pairs` and `report.inlier_summary` of report.json's pair rows (any schema version)."""
    from recon.core.report import inlier_summary

    counts = [(int(p.get("verified_inliers", 0)), int(p.get("distinct_inliers", 0))) for p in pairs]
    return {"num_pairs": len(pairs), **inlier_summary(counts)}


def method_result(method: str, report: dict[str, Any] | None, peak: PeakRss, gt, out: Path,
                  error: str | None = None) -> dict[str, Any]:
    """The report's keys + pair summary + measured peak + GT metrics (flat) for one run."""
    row: dict[str, Any] = {}
    if report is None:
        row.update(status="error", message=error or "", registered_images=0, num_points3D=0, num_images=0,
                   mean_track_length=0.0, mean_reprojection_error=None, seconds_total=None, stages={},
                   registered=[])
    else:
        row.update(report)
        row.update(pair_summary(report.get("pairs", [])))
        row["report_peak_mb"] = report.get("peak_mb")
    row["method"] = method
    row["out"] = str(out)
    row["peak_mb"] = None if peak.total_mb is None else round(peak.total_mb, 1)
    row["peak_growth_mb"] = None if peak.peak_mb is None else round(peak.peak_mb, 1)
    row["gt_eval"] = None
    if gt is not None and report is not None:
        rec = load_model(out / "sparse" / "0") if row.get("status") == "ok" else None
        ev = evaluate_model(rec, gt, with_pairs=True)
        row["gt_pair_rot_err"] = [[p["image0"], p["image1"], p["rot_err_deg"]] for p in ev.pop("pairs")
                                  if math.isfinite(p["rot_err_deg"])]
        ev.pop("center_err", None)
        row["gt_eval"] = ev
        row.update({k: ev.get(k) for k in GT_KEYS})
    return row


def run_ours(scene_dir: Path, out: Path, gt, max_size: int, pairs: str, seed: int, progress: bool = False,
             strict: bool = True, workers: int = 0, settings: Sequence[str] = ()) -> dict[str, Any]:
    """`recon run` (extra-affine) on the scene with `settings` (`recon run --set KEY=VALUE`
    strings, e.g. "matcher.adaptive=true") on top of the options, evaluated (`method_result`)."""
    from recon.config import build_run_config
    from recon.core.pipeline import run_scene

    report, err = None, None
    with PeakRss(RUN_INTERVAL_S) as mem:
        try:
            cfg = build_run_config(options={"out": str(out), "overwrite": True, "max_size": max_size, "method": OURS,
                                            "pairs": pairs, "seed": seed, "progress": progress, "workers": workers},
                                   settings=list(settings))
            rep = run_scene(scene_dir, cfg)
            report = rep.to_dict()
        except (InputError, UserError) as e:
            if strict:
                raise
            err = f"{type(e).__name__}: {e}"
        except Exception as e:  # one failing run must not end the comparison
            err = f"{type(e).__name__}: {e}"
            log.debug("recon run on %s failed", scene_dir, exc_info=True)
    return method_result(OURS_KEY, report, mem, gt, out, err)


def run_stock_preset(scene_dir: Path, out: Path, gt, preset: str, max_size: int, pairs: str, seed: int,
                     strict: bool = True, workers: int = 0, sfm: SfmConfig | None = None) -> dict[str, Any]:
    """Stock COLMAP (`preset`) on the scene, evaluated; `sfm`: the mapping options of ours
    (`sfm.*` settings), so both map the same way."""
    from recon.eval.stock import run_stock

    report, err = None, None
    with PeakRss(RUN_INTERVAL_S) as mem:
        try:
            report = run_stock(scene_dir, out, preset=preset, pairs=pairs, max_size=max_size,  # type: ignore[arg-type]
                               seed=seed, workers=workers, sfm=sfm).to_dict()
        except (InputError, UserError) as e:
            if strict:
                raise
            err = f"{type(e).__name__}: {e}"
        except Exception as e:
            err = f"{type(e).__name__}: {e}"
            log.debug("stock COLMAP (%s) on %s failed", preset, scene_dir, exc_info=True)
    return method_result(f"stock-{preset}", report, mem, gt, out, err)


# point clouds -----------------------------------------------------------------------------------
def camera_centers(rec) -> dict[str, np.ndarray]:
    """{image name: camera centre} of a pycolmap.Reconstruction's registered images."""
    from recon.eval.evaluate import poses_from_estimate

    return {n: center(P) for n, P in poses_from_estimate(rec).items()}


def points_xyz(rec) -> np.ndarray:
    pts = [p.xyz for p in rec.points3D.values()]
    return np.asarray(pts, np.float64).reshape(-1, 3)


def robust_extent(pts: np.ndarray) -> float:
    """Diagonal of the 1st-99th percentile bounding box (stray points do not inflate it)."""
    if len(pts) < 2:
        return 0.0
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    return float(np.linalg.norm(hi - lo))


def _nn_dist(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    import open3d as o3d

    a = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(src, np.float64)))
    b = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(dst, np.float64)))
    return np.asarray(a.compute_point_cloud_distance(b), np.float64)


def compare_clouds(stock_centers: dict[str, np.ndarray], stock_pts: np.ndarray,
                   ours_centers: dict[str, np.ndarray], ours_pts: np.ndarray,
                   threshold_rel: float = 0.01) -> dict[str, Any]:
    """Align ours to stock by the camera centres of images registered in both (by name), then
    nearest-neighbour distances both ways and completeness (see module doc). Never raises for
    too little data: returns {"status": "skipped", "message": ...}."""
    common = sorted(set(stock_centers) & set(ours_centers))
    out: dict[str, Any] = {"status": "skipped", "message": "", "common_images": common,
                           "num_points_stock": int(len(stock_pts)), "num_points_ours": int(len(ours_pts)),
                           "threshold_rel": threshold_rel}
    if len(common) < 3:
        out["message"] = f"need at least 3 images registered in both models to align them, have {len(common)}"
        return out
    if len(stock_pts) == 0 or len(ours_pts) == 0:
        out["message"] = "a model has no 3D points"
        return out
    src = np.array([ours_centers[n] for n in common])
    dst = np.array([stock_centers[n] for n in common])
    try:
        s, R, t = umeyama(src, dst)
    except ValueError as e:
        out["message"] = f"cannot align the models: {e}"
        return out
    aligned = (s * (R @ np.asarray(ours_pts, np.float64).T)).T + t
    cam_err = np.linalg.norm((s * (R @ src.T)).T + t - dst, axis=1)
    extent = robust_extent(np.asarray(stock_pts, np.float64))
    if extent <= 0:
        out["message"] = "the stock point cloud has no extent"
        return out
    th = threshold_rel * extent
    d_os = _nn_dist(aligned, stock_pts)  # each of our points -> nearest stock point
    d_so = _nn_dist(stock_pts, aligned)
    out.update(
        status="ok", message="",
        alignment={"scale": s, "R": R.tolist(), "t": t.tolist(),
                   "camera_center_err_median": float(np.median(cam_err)),
                   "camera_center_err_rel_median": float(np.median(cam_err) / extent)},
        extent=extent, threshold=th,
        dist_ours_to_stock_median=float(np.median(d_os)),
        dist_ours_to_stock_p90=float(np.percentile(d_os, 90)),
        dist_stock_to_ours_median=float(np.median(d_so)),
        dist_stock_to_ours_p90=float(np.percentile(d_so, 90)),
        completeness_ours=float(np.mean(d_os <= th)),  # our points near stock's cloud
        completeness_stock=float(np.mean(d_so <= th)),  # stock's points near ours
    )
    for k in ("dist_ours_to_stock_median", "dist_ours_to_stock_p90", "dist_stock_to_ours_median",
              "dist_stock_to_ours_p90"):
        out[k.replace("dist_", "rel_dist_")] = out[k] / extent
    return out


def clouds_between(stock_row: dict[str, Any], ours_row: dict[str, Any], threshold_rel: float = 0.01
                   ) -> dict[str, Any]:
    for name, row in (("stock", stock_row), ("extra_affine", ours_row)):
        if row.get("status") != "ok":
            return {"status": "skipped", "message": f"{name} has no model ({row.get('status')}: "
                                                    f"{row.get('message') or 'no message'})"}
    rs, ro = load_model(Path(stock_row["out"]) / "sparse" / "0"), load_model(Path(ours_row["out"]) / "sparse" / "0")
    if rs is None or ro is None:
        return {"status": "skipped", "message": "a model could not be read from sparse/0"}
    return compare_clouds(camera_centers(rs), points_xyz(rs), camera_centers(ro), points_xyz(ro), threshold_rel)


# one scene --------------------------------------------------------------------------------------
def compare_scene(scene_dir: str | Path, out: str | Path | None = None, presets: Sequence[str] = ("default",),
                  max_size: int = DEFAULT_MAX_SIZE, pairs: str = "exhaustive", seed: int = 0, progress: bool = False,
                  threshold_rel: float = 0.01, strict: bool = True, log: Log = _nolog,
                  on_warning: Log = _nolog, workers: int = 0, settings: Sequence[str] = ()) -> dict[str, Any]:
    """Run stock (each preset) and ours (with `settings`, `recon run --set` strings), evaluate,
    compare clouds, write OUT/compare.json.

    `strict`: InputError / UserError (unusable scene, bad options) propagate; otherwise they are
    recorded as that run's error (the scene benchmark keeps going)."""
    from recon.core.pipeline import RunConfig
    from recon.eval.stock import PRESETS

    scene_dir = Path(scene_dir).expanduser()
    if not scene_dir.is_dir():
        raise InputError(f"{scene_dir}: no such scene folder")
    scene_dir = scene_dir.resolve()
    bad = [p for p in presets if p not in PRESETS]
    if bad or not presets:
        raise UserError(f"stock preset {', '.join(bad) or '(none)'}: choose from {', '.join(PRESETS)}")
    RunConfig.from_options(max_size=max_size, pairs=pairs, seed=seed)  # validates the options (UserError)
    from recon.config import build_run_config

    sfm_cfg = build_run_config(settings=list(settings)).sfm  # validates the settings (UserError)
    out_dir = Path(out).expanduser().resolve() if out is not None else scene_dir / "compare"
    out_dir.mkdir(parents=True, exist_ok=True)

    res: dict[str, Any] = {"scene": str(scene_dir), "out": str(out_dir),
                           "config": {"stock_presets": list(presets), "max_size": max_size, "pairs": pairs,
                                      "seed": seed, "method": OURS, "settings": list(settings),
                                      "threshold_rel": threshold_rel, "cpu_count": os.cpu_count(),
                                      "started": time.strftime("%Y-%m-%dT%H:%M:%S")},
                           "gt": None, "warnings": []}

    def warn(msg: str) -> None:
        res["warnings"].append(msg)
        on_warning(msg)

    gt, info, w = load_gt(scene_dir)
    res["gt"] = info
    if w:
        warn(w)

    methods: dict[str, dict[str, Any]] = {}
    for preset in presets:
        d = out_dir / f"stock-{preset}"
        log(f"{scene_dir.name}: stock COLMAP SIFT ({preset}) -> {d}")
        methods[f"stock-{preset}"] = run_stock_preset(scene_dir, d, gt, preset, max_size, pairs, seed, strict, workers,
                                                      sfm_cfg)
    d = out_dir / OURS_KEY
    log(f"{scene_dir.name}: recon run ({OURS}) -> {d}")
    methods[OURS_KEY] = run_ours(scene_dir, d, gt, max_size, pairs, seed, progress, strict, workers, settings)
    for name, row in methods.items():
        if row.get("status") != "ok":
            warn(f"{name}: {row.get('status')}: {row.get('message') or 'no message'}")
        # a rendered scene (gt/scene.json holds its planes): verified correspondences that are right
        errors = transfer_errors(row.get("out"), scene_dir)
        row["correct_per_pair"] = correct_per_pair(row.get("pairs") or [], correct_counts(errors))
        row["correct_median_px"] = correct_error_median(errors)

    res["methods"] = methods
    res["stock"] = methods[f"stock-{presets[0]}"]
    res[OURS_KEY] = methods[OURS_KEY]
    res["clouds_by_stock"] = {p: clouds_between(methods[f"stock-{p}"], methods[OURS_KEY], threshold_rel)
                              for p in presets}
    res["clouds"] = res["clouds_by_stock"][presets[0]]
    res["ratios"] = ratios(methods)
    res["rotation_gap_by_stock"] = {p: rotation_gap(methods[OURS_KEY], methods[f"stock-{p}"]) for p in presets}
    write_json_atomic(out_dir / "compare.json", res)
    return res


def rotation_gap(ours: dict[str, Any], stock: dict[str, Any]) -> dict[str, Any] | None:
    """`evaluate.paired_rotation_gap` of two method rows' `gt_pair_rot_err` (ours minus stock), or
    None without ground truth or shared pairs."""
    rows = [[{"image0": a, "image1": b, "rot_err_deg": e} for a, b, e in m.get("gt_pair_rot_err") or []]
            for m in (ours, stock)]
    return paired_rotation_gap(rows[0], rows[1])


def _ratio(a, b) -> float | None:
    try:
        return float(a) / float(b) if a is not None and b not in (None, 0) else None
    except (TypeError, ValueError):
        return None


def ratios(methods: dict[str, dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """{"ours / stock-<preset>": {registered, points, track_length, time, peak_mb}} per stock run."""
    ours = methods.get(OURS_KEY)
    out: dict[str, dict[str, float | None]] = {}
    if ours is None:
        return out
    for name, r in methods.items():
        if name == OURS_KEY:
            continue
        out[f"ours / {name}"] = {
            "registered": _ratio(ours.get("registered_images"), r.get("registered_images")),
            "points": _ratio(ours.get("num_points3D"), r.get("num_points3D")),
            "track_length": _ratio(ours.get("mean_track_length"), r.get("mean_track_length")),
            "time": _ratio(ours.get("seconds_total"), r.get("seconds_total")),
            "peak_mb": _ratio(ours.get("peak_mb"), r.get("peak_mb")),
        }
    return out


# tables -----------------------------------------------------------------------------------------
def _f(v, spec: str, none: str = "-") -> str:
    return none if v is None else format(v, spec)


def inconsistent_share(m: dict[str, Any]) -> float | None:
    """Share of the verified match graph's observations in tracks holding two keypoints of one
    image (`recon.core.tracks.track_stats`): ours under `tracks.merged`, stock under
    `tracks.graph`; None when the run did not measure it."""
    tracks = m.get("tracks") or {}
    graph = tracks.get("merged") or tracks.get("graph") or {}
    v = graph.get("inconsistent_share")
    return None if v is None else float(v)


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def compare_table(res: dict[str, Any]):
    """One column per method, one row per metric, then the cloud comparison."""
    from rich.table import Table

    methods = res["methods"]
    cfg = res["config"]
    t = Table(title=f"recon compare: {Path(res['scene']).name} (max size {cfg['max_size'] or 'full'} px, "
                    f"pairs {cfg['pairs']})", header_style="bold")
    t.add_column("metric", max_width=60)
    for name in methods:
        t.add_column(name, justify="right")

    def row(label: str, fn) -> None:
        t.add_row(label, *[fn(m) for m in methods.values()])

    def status(m):
        s = m.get("status")
        return "ok" if s == "ok" else f"[red]{s}[/red]"

    row("status", status)
    row("registered images", lambda m: f"{m.get('registered_images', 0)}/{m.get('num_images', 0)}")
    row("3D points", lambda m: str(m.get("num_points3D", 0)))
    row("mean track length", lambda m: _f(m.get("mean_track_length"), ".2f"))
    row("mean reproj. error px", lambda m: _f(m.get("mean_reprojection_error"), ".3f"))
    row("obs. in inconsistent tracks %", lambda m: _pct(inconsistent_share(m)))
    row("verified pairs", lambda m: f"{m.get('verified_pairs', 0)}/{m.get('num_pairs', 0)}")
    row("inliers / verified pair", lambda m: _f(m.get("inliers_per_pair_mean"), ".0f"))
    row("  distinct correspondences", lambda m: _f(m.get("distinct_inliers_per_pair_mean"), ".0f"))
    if any(m.get("correct_per_pair") is not None for m in methods.values()):
        row("  correct (rendered truth)", lambda m: _f(m.get("correct_per_pair"), ".0f"))
        row("  their median error px", lambda m: _f(m.get("correct_median_px"), ".3f"))
    stages: list[str] = []
    for m in methods.values():
        stages += [s for s in (m.get("stages") or {}) if s not in stages]
    for s in stages:
        row(f"  {s} s", lambda m, s=s: _f((m.get("stages") or {}).get(s), ".2f"))
    row("total s", lambda m: _f(m.get("seconds_total"), ".1f"))
    row("peak MB (RSS)", lambda m: _f(m.get("peak_mb"), ".0f"))
    if res.get("gt"):
        t.add_section()
        row("GT rel. rot. err ° (median)", lambda m: _f(m.get("rel_rot_err_deg_median"), ".4f"))
        for preset, g in (res.get("rotation_gap_by_stock") or {}).items():
            if g is not None:
                cells = [""] * len(methods)
                cells[list(methods).index(OURS_KEY)] = (f"{g['gap']:+.4f} [{g['ci_low']:+.4f}, {g['ci_high']:+.4f}]"
                                                        f", lower on {g['a_below_b']}/{g['num_pairs']}")
                t.add_row(f"  minus stock-{preset}'s (95 % CI, images resampled)", *cells)
        row("GT rel. trans. err ° (median)", lambda m: _f(m.get("rel_trans_err_deg_median"), ".4f"))
        for k in ("auc_5", "auc_10", "auc_20"):
            row(f"GT AUC@{k[4:]}°", lambda m, k=k: _f(m.get(k), ".3f"))
        row("GT centre err (median)", lambda m: _f(m.get("center_err_median"), ".4f"))
    for preset, c in res.get("clouds_by_stock", {}).items():
        t.add_section()
        label = f"clouds vs stock-{preset}"
        cells = [""] * len(methods)
        if c.get("status") != "ok":
            t.add_row(label, *(["[yellow]skipped[/yellow]"] + [""] * (len(methods) - 1)))
            t.add_row(f"  {c.get('message', '')}", *cells)
            continue
        names = list(methods)
        si, oi = names.index(f"stock-{preset}"), names.index(OURS_KEY)

        def pair_row(lbl: str, stock_v: str, ours_v: str, names: list[str] = names, si: int = si, oi: int = oi) -> None:
            cs = [""] * len(names)
            cs[si], cs[oi] = stock_v, ours_v
            t.add_row(lbl, *cs)

        t.add_row(label, *cells)
        t.add_row(f"  aligned on {len(c['common_images'])} common images", *cells)
        t.add_row(f"  stock extent {c['extent']:.3g}, threshold {c['threshold']:.3g}", *cells)
        pair_row("  dist. to other cloud, median", f"{c['dist_stock_to_ours_median']:.3g} "
                 f"({100 * c['rel_dist_stock_to_ours_median']:.2f} %)",
                 f"{c['dist_ours_to_stock_median']:.3g} ({100 * c['rel_dist_ours_to_stock_median']:.2f} %)")
        pair_row("  dist. to other cloud, p90", f"{c['dist_stock_to_ours_p90']:.3g} "
                 f"({100 * c['rel_dist_stock_to_ours_p90']:.2f} %)",
                 f"{c['dist_ours_to_stock_p90']:.3g} ({100 * c['rel_dist_ours_to_stock_p90']:.2f} %)")
        pair_row(f"  within {100 * c['threshold_rel']:.0f} % of other", f"{100 * c['completeness_stock']:.1f} %",
                 f"{100 * c['completeness_ours']:.1f} %")
    return t


def scenes_table(results: list[dict[str, Any]], max_size: int):
    """One summary table for several scenes: a row per scene and method, plus ratio rows."""
    from rich.table import Table

    t = Table(title=f"Scenes: recon run ({OURS}) vs stock COLMAP SIFT, max size {max_size or 'full'} px",
              header_style="bold", show_lines=False)
    for name, just in [("scene", "left"), ("method", "left"), ("registered", "right"), ("points", "right"),
                       ("track len", "right"), ("reproj px", "right"), ("incons. %", "right"), ("total s", "right"),
                       ("peak MB", "right"), ("rot err° med", "right"), ("AUC@5", "right"), ("AUC@10", "right"),
                       ("cloud med %", "right"), ("complete %", "right")]:
        t.add_column(name, justify=just, no_wrap=name in ("scene", "method"))  # type: ignore[arg-type]
    for k, res in enumerate(results):
        scene = Path(res["scene"]).name
        clouds = res.get("clouds_by_stock", {})
        for name, r in res.get("methods", {}).items():
            status = r.get("status")
            reg = f"{r.get('registered_images', 0)}/{r.get('num_images', 0)}"
            if status not in ("ok", None):
                reg += f" [red]{status}[/red]"
            c = clouds.get(name[len("stock-"):]) if name.startswith("stock-") else None
            cmed = ccomp = ""
            if c is not None and c.get("status") == "ok":
                cmed = f"{100 * c['rel_dist_ours_to_stock_median']:.2f}"
                ccomp = f"{100 * c['completeness_ours']:.0f} / {100 * c['completeness_stock']:.0f}"
            t.add_row(scene, name, reg, str(r.get("num_points3D", 0)),
                      _f(r.get("mean_track_length"), ".2f"), _f(r.get("mean_reprojection_error"), ".2f"),
                      _pct(inconsistent_share(r)), _f(r.get("seconds_total"), ".1f"), _f(r.get("peak_mb"), ".0f"),
                      _f(r.get("rel_rot_err_deg_median"), ".4f"), _f(r.get("auc_5"), ".3f"),
                      _f(r.get("auc_10"), ".3f"), cmed, ccomp)
        for name, q in res.get("ratios", {}).items():
            t.add_row(scene, f"[italic]{name}[/italic]", _f(q["registered"], ".2f") + "x",
                      _f(q["points"], ".2f") + "x", _f(q["track_length"], ".2f") + "x", "", "",
                      _f(q["time"], ".2f") + "x", _f(q["peak_mb"], ".2f") + "x", "", "", "", "", "",
                      style="dim")
        if k < len(results) - 1:
            t.add_section()
    t.caption = ("incons. %: observations of the verified match graph in tracks with two keypoints of one image; "
                 "cloud med %: median distance of ours (aligned) to the stock cloud, % of the stock extent; "
                 "complete %: ours within 1 % of stock / stock within 1 % of ours")
    return t


# several scenes ---------------------------------------------------------------------------------
def run_scenes(root: str | Path, out_root: str | Path, scenes: Sequence[str] | None = None,
               presets: Sequence[str] = ("default",), max_size: int = DEFAULT_MAX_SIZE, pairs: str = "exhaustive",
               seed: int = 0, progress: bool = False, json_path: str | Path | None = None,
               log: Log = _nolog, workers: int = 0, settings: Sequence[str] = ()) -> list[dict[str, Any]]:
    """`compare_scene` for each scene folder under `root` into OUT_ROOT/<scene>; the JSON file
    (when given) is rewritten atomically after every scene. UserError for an unknown scene."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise UserError(f"{root}: no such folder")
    available = discover_scenes(root)
    wanted = list(scenes) if scenes else available
    missing = [s for s in wanted if s not in available]
    if missing:
        raise UserError(f"no scene {', '.join(missing)} under {root} (found: {', '.join(available) or 'none'})")
    if not wanted:
        raise UserError(f"{root}: no scene folders with images")
    out_root = Path(out_root).expanduser().resolve()
    meta = {"root": str(root), "max_size": max_size, "stock_presets": list(presets), "pairs": pairs, "seed": seed,
            "ours": OURS, "settings": list(settings), "out": str(out_root), "cpu_count": os.cpu_count(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    results: list[dict[str, Any]] = []
    for scene in wanted:
        res = compare_scene(root / scene, out_root / scene, presets=presets, max_size=max_size, pairs=pairs,
                            seed=seed, progress=progress, strict=False, log=log, workers=workers,
                            on_warning=functools.partial(_scene_warning, log, scene), settings=settings)
        results.append(res)
        if json_path is not None:
            write_json_atomic(json_path, {"meta": meta, "scenes": results, "rows": scene_rows(results)})
    return results


def scene_rows(results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One flat row per (scene, method) of `compare_scene` results, each named by its own scene
    (the folder name of the result's "scene" path)."""
    return [dict(r, scene=Path(x["scene"]).name) for x in results for r in x["methods"].values()]


def _scene_warning(log: Callable[[str], None], label: str, message: str) -> None:
    """A run's warning in the log, prefixed with what it belongs to (scene)."""
    log(f"{label}: warning: {message}")
