"""Our pipeline on the difficulty curve's scenes with matcher variants side by side, against stock
COLMAP's `high` (issue 13 item 4: verified inliers per pair where views are close).

`recon bench difficulty` runs one configuration of ours; this runs `recon run` on the same
rendered facades (`recon.eval.difficulty`, seed 0, 800x600) once per variant (`--variant
LABEL=KEY=VALUE[,KEY=VALUE]`, the `--set` syntax of `recon run`; `base` = no override), in turn
on each scene, so their times are side by side, and takes stock `high` (and `default`) from a
finished `recon bench difficulty` output (`--stock-from DIR/runs/<scene>/compare.json`,
COLMAP's runs are deterministic for a seed) or runs them when absent.

    python benchmarks/bench_difficulty_variants.py --out /tmp/dv --views 13,9,7,4,3 \\
        --stock-from out/bench-difficulty --variant base= \\
        --variant colmap=matcher.fine.original_detector=colmap-sift \\
        --json benchmarks/results/difficulty-colmap-sift.json

Writes OUT/variants.json (rows rewritten after every run) and prints a table: per scene and
method, registered images, median relative rotation error, mean verified inliers per verified
pair, seconds. `--texture PHOTO` (repeatable) pastes photos on the planes, as `recon bench
difficulty --texture` does (a scene nothing was tuned on).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import recon  # noqa: F401  (cv2 before pycolmap)
from matching.memory import RUN_INTERVAL_S, PeakRss
from recon.config import build_run_config
from recon.core.jsonio import write_json_atomic
from recon.eval.compare import load_gt, method_result, run_stock_preset
from recon.eval.difficulty import DEFAULT_MAX_AZIMUTH, _scene, step_deg
from recon.eval.gt_planes import correct_counts, correct_error_median, correct_per_pair, transfer_errors
from scenes.render import textures_label


def run_variant(scene: Path, out: Path, gt, settings: list[str], seed: int) -> dict[str, Any]:
    """`recon run` on `scene` with `--set` `settings`, evaluated as `recon compare` does."""
    from recon.core.pipeline import run_scene

    cfg = build_run_config(options={"output.out": str(out), "output.overwrite": True, "output.progress": False,
                                    "seed": seed},
                           settings=settings)
    report, err = None, None
    with PeakRss(RUN_INTERVAL_S) as mem:
        try:
            report = run_scene(scene, cfg).to_dict()
        except Exception as e:  # noqa: BLE001  (one failing run must not end the sweep)
            err = f"{type(e).__name__}: {e}"
    return method_result("ours", report, mem, gt, out, err)


def parse_variants(specs: list[str]) -> list[tuple[str, list[str]]]:
    """`--variant LABEL=KEY=VALUE[,KEY=VALUE]` specs as (label, `--set` settings); none = one
    variant "base" without overrides."""
    variants = []
    for v in specs or ["base="]:
        label, _, rest = v.partition("=")
        variants.append((label, [s for s in rest.split(",") if s.strip()]))
    return variants


def row_of(name: str, m: dict[str, Any], n: int, step: float, source: str, scene: Path) -> dict[str, Any]:
    """One table row; `correct_per_pair` from the run's database and the scene's ground truth."""
    errors = transfer_errors(m.get("out"), scene)
    correct = correct_counts(errors)
    return {"views": n, "step_deg": round(step, 2), "method": name, "status": m.get("status"),
            "registered": m.get("registered_images", 0), "images": m.get("num_images", 0),
            "rot_err_deg": m.get("rel_rot_err_deg_median"), "auc_5": m.get("auc_5"),
            "verified_pairs": m.get("verified_pairs", 0), "pairs": m.get("num_pairs", 0),
            "inliers_per_pair": m.get("inliers_per_pair_mean", 0.0),
            "distinct_per_pair": m.get("distinct_inliers_per_pair_mean", 0.0),
            "correct_per_pair": correct_per_pair(m.get("pairs") or [], correct),
            "correct_median_px": correct_error_median(errors), "points": m.get("num_points3D", 0),
            "reproj_px": m.get("mean_reprojection_error"), "seconds": m.get("seconds_total"),
            "match_seconds": (m.get("stages") or {}).get("match"),
            "source": source}


def table(rows: list[dict[str, Any]]) -> str:
    lines = [f"{'views':>5} {'step':>6} {'method':<16} {'reg':>6} {'rot.err':>8} {'inl/pair':>9} {'distinct':>9} "
             f"{'correct':>8} {'s':>7} {'match s':>7}"]
    for r in rows:
        rot = "-" if r["rot_err_deg"] is None else f"{r['rot_err_deg']:.3f}"
        sec = "-" if r["seconds"] is None else f"{r['seconds']:.1f}"
        msec = "-" if r["match_seconds"] is None else f"{r['match_seconds']:.1f}"
        corr = "-" if r.get("correct_per_pair") is None else f"{r['correct_per_pair']:.1f}"
        lines.append(f"{r['views']:>5} {r['step_deg']:>6} {r['method']:<16} {r['registered']:>2}/{r['images']:<3} "
                     f"{rot:>8} {r['inliers_per_pair']:>9.1f} {r.get('distinct_per_pair', 0.0):>9.1f} {corr:>8} "
                     f"{sec:>7} {msec:>7}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--views", default="13,9,7,5,4,3")
    ap.add_argument("--variant", action="append", default=[], help="LABEL=KEY=VALUE[,KEY=VALUE] or LABEL=")
    ap.add_argument("--stock-from", type=Path, default=None, help="a `recon bench difficulty` output folder")
    ap.add_argument("--stock-presets", default="high,default", help="comma-separated; \"\" = none")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--texture", action="append", type=Path, default=None, metavar="PHOTO",
                    help="a photo pasted on the facade's planes (repeatable, as `recon bench difficulty "
                         "--texture`; default: the procedural textures)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    for photo in args.texture or []:
        if not photo.expanduser().is_file():
            print(f"bench_difficulty_variants: --texture {photo}: no such file", file=sys.stderr)
            return 2
    variants = parse_variants(args.variant)
    out = args.out.expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    config = {"views": args.views, "variants": dict(variants), "seed": args.seed,
              "textures": textures_label(args.texture),
              "stock_from": str(args.stock_from) if args.stock_from else None,
              "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    rows: list[dict[str, Any]] = []
    for n in (int(x) for x in args.views.split(",")):
        preset = f"facade-{n}x{DEFAULT_MAX_AZIMUTH:g}"
        scene, _ = _scene(out, preset, args.seed, None, lambda m: print(m, file=sys.stderr), textures=args.texture)
        gt, _, _ = load_gt(scene)
        step = step_deg(n, DEFAULT_MAX_AZIMUTH)
        stock = None
        if args.stock_from is not None:
            cj = args.stock_from / "runs" / preset / "compare.json"
            if cj.is_file():
                stock = json.loads(cj.read_text(encoding="utf-8"))["methods"]
        for p in [p for p in args.stock_presets.split(",") if p]:  # "" = none
            key = f"stock-{p}"
            if stock is not None and key in stock:
                rows.append(row_of(key, stock[key], n, step, str(args.stock_from), scene))
            else:
                m = run_stock_preset(scene, out / "runs" / preset / key, gt, p, 1600, "exhaustive", args.seed,
                                     strict=False)
                rows.append(row_of(key, m, n, step, "this run", scene))
        for label, settings in variants:
            d = out / "runs" / preset / f"ours-{label}"
            print(f"{preset}: ours {label} {settings}", file=sys.stderr)
            rows.append(row_of(f"ours-{label}", run_variant(scene, d, gt, settings, args.seed), n, step, "this run", scene))
            write_json_atomic(out / "variants.json", {"config": config, "rows": rows})
        print(table([r for r in rows if r["views"] == n]), flush=True)
    write_json_atomic(out / "variants.json", {"config": config, "rows": rows})
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "variants.json", args.json)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
