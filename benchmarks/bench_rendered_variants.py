"""Our pipeline with matcher variants side by side on rendered presets over several image sizes
and seeds, stock COLMAP alongside: a measured choice between options whose effect on one scene
swings with a single relative rotation (issues 11 and 13).

Each (preset, size, seed) scene is rendered under OUT/scenes (`scenes.render.render_scene`; a
finished render is reused), stock COLMAP runs once per scene (`--stock-presets`, deterministic per
seed) and `recon run` once per `--variant LABEL=KEY=VALUE[,KEY=VALUE]` (the `--set` syntax;
`LABEL=` = no override), one after the other and each from an empty output folder, so their
times are side by side. `--textures PHOTO[,PHOTO]` pastes photos on the planes instead of the
procedural textures (scenes the project did not tune on).

    python benchmarks/bench_rendered_variants.py --out /tmp/rv --presets facade-groups \\
        --sizes 640x480,800x600,1024x768 --seeds 0,1,2 \\
        --variant sift=match.simulate=needed \\
        --variant plain=match.simulate=needed,match.first_pass_detector=colmap-sift-plain \\
        --json benchmarks/results/first-pass-rendered.json

Writes OUT/variants.json (rewritten after every run) and prints one row per run (registered
images, median relative rotation error against the rendered cameras, mean verified inliers per
verified pair, mean reprojection error, seconds) and, per method, the median over the scenes of
its rotation error and of its time as a multiple of the first stock preset's.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from bench_difficulty_variants import parse_variants, run_variant

import recon  # noqa: F401  (cv2 before pycolmap)
from recon.core.jsonio import write_json_atomic
from recon.eval.compare import load_gt, run_stock_preset
from recon.eval.difficulty import _scene
from scenes.render import textures_label


def parse_size(text: str) -> tuple[int, int]:
    """"640x480" -> (640, 480)."""
    w, _, h = text.lower().partition("x")
    return int(w), int(h)


def row_of(scene: str, size: str, seed: int, method: str, m: dict[str, Any]) -> dict[str, Any]:
    """One run's figures (a `recon.eval.compare.method_result`)."""
    return {"scene": scene, "size": size, "seed": seed, "method": method, "status": m.get("status"),
            "registered": m.get("registered_images", 0), "images": m.get("num_images", 0),
            "rot_err_deg": m.get("rel_rot_err_deg_median"), "auc_5": m.get("auc_5"),
            "inliers_per_pair": m.get("inliers_per_pair_mean", 0.0), "points": m.get("num_points3D", 0),
            "reproj_px": m.get("mean_reprojection_error"), "seconds": m.get("seconds_total")}


def _fmt(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table(rows: list[dict[str, Any]]) -> str:
    lines = [f"{'scene':<16} {'size':>9} {'seed':>4} {'method':<18} {'reg':>6} {'rot.err':>8} {'inl/pair':>9} "
             f"{'reproj':>7} {'s':>7}"]
    for r in rows:
        lines.append(f"{r['scene']:<16} {r['size']:>9} {r['seed']:>4} {r['method']:<18} "
                     f"{r['registered']:>2}/{r['images']:<3} {_fmt(r['rot_err_deg'], '.3f'):>8} "
                     f"{r['inliers_per_pair']:>9.1f} {_fmt(r['reproj_px'], '.3f'):>7} {_fmt(r['seconds'], '.1f'):>7}")
    return "\n".join(lines)


def summary(rows: list[dict[str, Any]], reference: str) -> str:
    """Per method over all scenes: every image registered in how many, the median rotation error
    and the median of its time over `reference`'s on the same scene."""
    ref_s = {(r["scene"], r["size"], r["seed"]): r["seconds"] for r in rows if r["method"] == reference}
    lines = [f"{'method':<18} {'all registered':>14} {'rot.err median':>14} {'rot.err max':>11} "
             f"{'x ' + reference:>18}"]
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method]
        full = sum(r["registered"] == r["images"] and r["images"] > 0 for r in mine)
        errs = [r["rot_err_deg"] for r in mine if r["rot_err_deg"] is not None]
        ratios = [r["seconds"] / ref_s[k] for r in mine
                  if r["seconds"] and ref_s.get(k := (r["scene"], r["size"], r["seed"]))]
        lines.append(f"{method:<18} {f'{full}/{len(mine)}':>14} "
                     f"{_fmt(statistics.median(errs) if errs else None, '.3f'):>14} "
                     f"{_fmt(max(errs) if errs else None, '.3f'):>11} "
                     f"{_fmt(statistics.median(ratios) if ratios else None, '.2f'):>17}x")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--presets", default="facade-groups", help="comma-separated `recon render-scene` presets")
    ap.add_argument("--sizes", default="640x480,800x600", help="comma-separated WxH")
    ap.add_argument("--seeds", default="0", help="comma-separated render seeds (the runs use seed 0)")
    ap.add_argument("--variant", action="append", default=[], help="LABEL=KEY=VALUE[,KEY=VALUE] or LABEL=")
    ap.add_argument("--stock-presets", default="default")
    ap.add_argument("--textures", default="",
                    help="comma-separated photos pasted on the planes instead of the procedural textures")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    textures = [Path(t).expanduser().resolve() for t in args.textures.split(",") if t]
    for t in textures:
        if not t.is_file():
            ap.error(f"--textures: no such file {t}")

    variants = parse_variants(args.variant)
    stock_presets = [p for p in args.stock_presets.split(",") if p]
    out = args.out.expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    config = {"presets": args.presets, "sizes": args.sizes, "seeds": args.seeds, "variants": dict(variants),
              "stock_presets": stock_presets,
              "textures": textures_label(textures), "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    rows: list[dict[str, Any]] = []
    for preset in args.presets.split(","):
        for size in args.sizes.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                name = f"{preset}-{size}-s{seed}"
                scene, _ = _scene(out, preset, seed, parse_size(size), lambda m: print(m, file=sys.stderr),
                                  name=name, textures=textures or None)
                gt, _, _ = load_gt(scene)
                for p in stock_presets:
                    m = run_stock_preset(scene, out / "runs" / name / f"stock-{p}", gt, p, 1600, "exhaustive", 0,
                                         strict=False)
                    rows.append(row_of(preset, size, seed, f"stock-{p}", m))
                for label, settings in variants:
                    print(f"{name}: ours {label} {settings}", file=sys.stderr)
                    run_dir = out / "runs" / name / f"ours-{label}"
                    shutil.rmtree(run_dir, ignore_errors=True)  # cold: no pair or feature cache of an earlier call
                    m = run_variant(scene, run_dir, gt, settings, 0)
                    rows.append(row_of(preset, size, seed, f"ours-{label}", m))
                    write_json_atomic(out / "variants.json", {"config": config, "rows": rows})
                print(table([r for r in rows if (r["scene"], r["size"], r["seed"]) == (preset, size, seed)]),
                      flush=True)
    write_json_atomic(out / "variants.json", {"config": config, "rows": rows})
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "variants.json", args.json)
    print(table(rows))
    if stock_presets:
        print(summary(rows, f"stock-{stock_presets[0]}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
