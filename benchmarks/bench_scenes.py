"""Scene benchmark: `recon run` (extra-affine) vs COLMAP's stock SIFT pipeline, same images.

    python benchmarks/bench_scenes.py [SCENES_ROOT] [--scenes a,b] [--max-size 1600]
        [--json benchmarks/results/scenes.json] [--stock-presets default[,high]]
        [--out out/bench] [--pairs exhaustive] [--seed 0]

SCENES_ROOT (default: ../shared/data/scenes next to the repository, or $RECON_SHARED_DATA/scenes)
holds one folder per scene (photos in `images/` or at the top level, optional ground truth in
`gt/`, see `recon.gt`). For each scene, in this one process:

1. `recon.pipeline.run_scene` (method extra-affine) into `OUT/<scene>/ours`;
2. `recon.stock.run_stock` for each stock preset into `OUT/<scene>/stock-<preset>`;
3. each model is evaluated against the GT when the scene has one (`recon.evaluate`), matched by
   image name; a malformed GT is reported and the scene is still run without it.

Peak memory: every run is wrapped in `recon.bench_pairs.PeakRss` (RSS sampled from /proc; the
process-lifetime `ru_maxrss` that `recon run` reports would carry the first run's peak into the
later ones), and `peak MB` is the highest RSS seen during that run.

Prints one rich table (one row per scene and method, plus "ours / stock" ratio rows: registered
images, 3D points, mean track length, total time and peak memory ratios) and writes all rows,
evaluations and reports' headline numbers to the JSON file (atomically, after every scene).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a plain script from anywhere
    sys.path.insert(0, str(REPO))

from matching.errors import InputError  # noqa: E402
from recon.bench_pairs import PeakRss  # noqa: E402
from recon.evaluate import evaluate_model  # noqa: E402
from recon.gt import find_gt, gt_source  # noqa: E402
from recon.jsonio import write_json_atomic  # noqa: E402
from recon.pipeline import RunConfig, run_scene  # noqa: E402
from recon.scene import IMAGE_EXTS  # noqa: E402
from recon.stock import PRESETS, run_stock  # noqa: E402

OURS = "extra-affine"


def default_root() -> Path:
    data = Path(os.environ.get("RECON_SHARED_DATA") or REPO.parent / "shared" / "data")
    return data / "scenes"


def discover_scenes(root: Path) -> list[str]:
    """Sub-folders of `root` holding images (in images/ or at their top level), sorted."""
    out = []
    for d in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        img = d / "images" if (d / "images").is_dir() else d
        if any(f.suffix.lower() in IMAGE_EXTS for f in img.iterdir() if f.is_file()):
            out.append(d.name)
    return out


def _load_model(model_dir: Path):
    import pycolmap

    if not model_dir.is_dir():
        return None
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception:
        return None


def _pair_summary(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    counts = [int(p.get("verified_inliers", 0)) for p in pairs if int(p.get("verified_inliers", 0)) > 0]
    return {"num_pairs": len(pairs), "verified_pairs": len(counts),
            "inliers_per_pair_mean": float(sum(counts) / len(counts)) if counts else 0.0,
            "inliers_per_pair_median": float(sorted(counts)[len(counts) // 2]) if counts else 0.0}


HEADLINE = ("status", "message", "num_images", "registered_images", "num_points3D", "mean_track_length",
            "mean_reprojection_error", "seconds_total", "stages", "num_models", "model_sizes", "registered")


def _row(scene: str, method: str, report: dict[str, Any] | None, peak: PeakRss, gt, out: Path,
         error: str | None = None) -> dict[str, Any]:
    row: dict[str, Any] = {"scene": scene, "method": method, "out": str(out)}
    if report is None:
        row.update(status="error", message=error or "", registered_images=0, num_points3D=0, num_images=0,
                   mean_track_length=0.0, mean_reprojection_error=None, seconds_total=None)
    else:
        row.update({k: report.get(k) for k in HEADLINE})
        row.update(_pair_summary(report.get("pairs", [])))
        row["report_peak_mb"] = report.get("peak_mb")
        row["tracks"] = report.get("tracks", {})
    row["peak_mb"] = peak.total_mb
    row["peak_growth_mb"] = peak.peak_mb
    row["eval"] = None
    if gt is not None and report is not None:
        rec = _load_model(out / "sparse" / "0") if row["status"] == "ok" else None
        row["eval"] = evaluate_model(rec, gt)
    return row


def run_one_scene(root: Path, scene: str, out_root: Path, max_size: int, presets: list[str], pairs: str,
                  seed: int, progress: bool, log) -> dict[str, Any]:
    scene_dir = root / scene
    res: dict[str, Any] = {"scene": scene, "path": str(scene_dir), "gt": None, "gt_error": None, "rows": []}
    gt = None
    try:
        gt = find_gt(scene_dir)
        src = gt_source(scene_dir)
        if gt is not None and src is not None:
            res["gt"] = {"format": src[0], "path": str(src[1]), "num_images": len(gt)}
    except InputError as e:
        res["gt_error"] = str(e)
        log(f"[yellow]{scene}: ground truth unusable, evaluating without it: {e}[/yellow]")

    # ours ---------------------------------------------------------------------------------------
    out = out_root / scene / "ours"
    log(f"[bold]{scene}[/bold]: recon run ({OURS}, max size {max_size}) -> {out}")
    report, err = None, None
    with PeakRss() as mem:
        try:
            rep = run_scene(scene_dir, RunConfig(out=out, overwrite=True, max_size=max_size, method=OURS,
                                                 pairs=pairs, seed=seed, progress=progress),
                            on_warning=lambda m: None)
            report = rep.to_dict()
        except Exception as e:  # one failing run must not end the benchmark
            err = f"{type(e).__name__}: {e}"
            traceback.print_exc()
    res["rows"].append(_row(scene, OURS, report, mem, gt, out, err))

    # stock --------------------------------------------------------------------------------------
    for preset in presets:
        out = out_root / scene / f"stock-{preset}"
        log(f"[bold]{scene}[/bold]: stock COLMAP SIFT ({preset}) -> {out}")
        report, err = None, None
        with PeakRss() as mem:
            try:
                report = run_stock(scene_dir, out, preset=preset, pairs=pairs, max_size=max_size, seed=seed)  # type: ignore[arg-type]
            except Exception as e:
                err = f"{type(e).__name__}: {e}"
                traceback.print_exc()
        res["rows"].append(_row(scene, f"stock-{preset}", report, mem, gt, out, err))
    res["ratios"] = ratios(res["rows"])
    return res


def _ratio(a, b) -> float | None:
    try:
        return float(a) / float(b) if a is not None and b not in (None, 0) else None
    except (TypeError, ValueError):
        return None


def ratios(rows: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """{"ours / stock-<preset>": {registered, points, track_length, time, peak_mb}} per stock row."""
    ours = next((r for r in rows if r["method"] == OURS), None)
    out = {}
    if ours is None:
        return out
    for r in rows:
        if r["method"] == OURS:
            continue
        out[f"ours / {r['method']}"] = {
            "registered": _ratio(ours.get("registered_images"), r.get("registered_images")),
            "points": _ratio(ours.get("num_points3D"), r.get("num_points3D")),
            "track_length": _ratio(ours.get("mean_track_length"), r.get("mean_track_length")),
            "time": _ratio(ours.get("seconds_total"), r.get("seconds_total")),
            "peak_mb": _ratio(ours.get("peak_mb"), r.get("peak_mb")),
        }
    return out


# table ------------------------------------------------------------------------------------------
def _f(v, spec: str, none: str = "-") -> str:
    return none if v is None else format(v, spec)


def make_table(results: list[dict[str, Any]], max_size: int):
    from rich.table import Table

    t = Table(title=f"Scenes: recon run ({OURS}) vs stock COLMAP SIFT, max size {max_size or 'full'} px",
              header_style="bold", show_lines=False)
    for name, just in [("scene", "left"), ("method", "left"), ("registered", "right"), ("points", "right"),
                       ("track len", "right"), ("reproj px", "right"), ("total s", "right"),
                       ("peak MB", "right"), ("rot err° med", "right"), ("AUC@5", "right"), ("AUC@10", "right")]:
        t.add_column(name, justify=just)  # type: ignore[arg-type]
    for k, res in enumerate(results):
        for r in res["rows"]:
            ev = r.get("eval") or {}
            status = r.get("status")
            reg = f"{r.get('registered_images', 0)}/{r.get('num_images', 0)}"
            if status not in ("ok", None):
                reg += f" [red]{status}[/red]"
            t.add_row(res["scene"], r["method"], reg, str(r.get("num_points3D", 0)),
                      _f(r.get("mean_track_length"), ".2f"), _f(r.get("mean_reprojection_error"), ".2f"),
                      _f(r.get("seconds_total"), ".1f"), _f(r.get("peak_mb"), ".0f"),
                      _f(ev.get("rel_rot_err_deg_median"), ".2f"), _f(ev.get("auc_5"), ".3f"),
                      _f(ev.get("auc_10"), ".3f"))
        for name, q in res.get("ratios", {}).items():
            t.add_row(res["scene"], f"[italic]{name}[/italic]", _f(q["registered"], ".2f") + "x",
                      _f(q["points"], ".2f") + "x", _f(q["track_length"], ".2f") + "x", "",
                      _f(q["time"], ".2f") + "x", _f(q["peak_mb"], ".2f") + "x", "", "", "",
                      style="dim")
        if k < len(results) - 1:
            t.add_section()
    return t


# main -------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    from rich.console import Console

    from matching.memory import return_large_buffers_to_os

    return_large_buffers_to_os()  # as the recon CLI does

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", type=Path, default=None,
                    help="folder of scene folders (default: ../shared/data/scenes)")
    ap.add_argument("--scenes", default="", help="comma-separated scene names (default: all)")
    ap.add_argument("--max-size", type=int, default=1600, help="working resolution, longer side px (0 = full)")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "scenes.json")
    ap.add_argument("--stock-presets", default="default", help=f"comma-separated, of {', '.join(PRESETS)}")
    ap.add_argument("--out", type=Path, default=REPO / "out" / "bench", help="outputs: OUT/<scene>/{ours,stock-*}")
    ap.add_argument("--pairs", default="exhaustive", help="pair selection for both pipelines (as recon run --pairs)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--progress", action="store_true", help="recon run's progress bars on stderr")
    a = ap.parse_args(argv)

    console = Console(width=None if sys.stdout.isatty() else 160)  # a pipe or file: don't wrap at 80
    err = Console(stderr=True)
    root = (a.root or default_root()).expanduser()
    if not root.is_dir():
        err.print(f"[red]bench_scenes: {root}: no such folder[/red]")
        return 2
    presets = [p.strip() for p in a.stock_presets.split(",") if p.strip()]
    bad = [p for p in presets if p not in PRESETS]
    if bad:
        err.print(f"[red]bench_scenes: unknown stock preset(s) {', '.join(bad)}; choose from {', '.join(PRESETS)}[/red]")
        return 2
    available = discover_scenes(root)
    wanted = [s.strip() for s in a.scenes.split(",") if s.strip()] or available
    missing = [s for s in wanted if s not in available]
    if missing:
        err.print(f"[red]bench_scenes: no scene {', '.join(missing)} under {root} "
                  f"(found: {', '.join(available) or 'none'})[/red]")
        return 2

    meta = {"root": str(root), "max_size": a.max_size, "stock_presets": presets, "pairs": a.pairs, "seed": a.seed,
            "ours": OURS, "out": str(a.out), "cpu_count": os.cpu_count(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    results: list[dict[str, Any]] = []
    for scene in wanted:
        results.append(run_one_scene(root, scene, a.out.expanduser().resolve(), a.max_size, presets, a.pairs,
                                     a.seed, a.progress, lambda m: err.print(m)))
        rows = [r for res in results for r in res["rows"]]
        write_json_atomic(a.json, {"meta": meta, "scenes": results, "rows": rows})
    console.print(make_table(results, a.max_size))
    console.print(f"JSON: {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
