"""Incremental-mapper option variants on databases written by `recon run` / `recon compare`.

    PYTHONPATH=. python benchmarks/bench_mapper_options.py \
        --run sacre=/tmp/b/sacre_coeur/extra_affine:../shared/data/scenes/sacre_coeur \
        --variant old=mapper.init_min_tri_angle=4 --variant now= --seeds 0,1,2 \
        --json benchmarks/results/mapper-init.json

Each `--run NAME=OUT:SCENE_DIR` names a finished run folder (its verified OUT/database.db) and the
scene folder (images for point colours, ground truth when `recon.eval.compare.load_gt` finds one).
Each `--variant LABEL=KEY=VALUE[,KEY=VALUE...]` sets attributes of `recon.core.sfm.mapping_options`
(dotted paths into `IncrementalPipelineOptions`, e.g. `mapper.init_min_tri_angle=4`); an empty
variant is the current default. Every (run, variant, seed) maps a copy of the database with one
thread and the run's pixel thresholds (`bench_mappers.px_scale_of` its report;
`recon.core.sfm.run_incremental`, bit-exact per seed), applies `recon run`'s default final
robust adjustment and evaluates the model as `recon compare` does. Prints one row each: the
models the mapper built (sizes, largest first), registered images, points, reprojection error,
median relative rotation error; writes them as JSON with `--json`. Matching is not rerun, so a
variant's effect on mapping is measured on exactly the same verified matches.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_difficulty_variants import parse_variants
from bench_mappers import find_image_dir, px_scale_of

from recon.config import RunConfig
from recon.core.sfm import final_bundle_adjustment, mapping_options, run_incremental
from recon.core.stages.sfm import final_ba_config
from recon.eval.compare import load_gt
from recon.eval.evaluate import evaluate_model
from recon.log import quiet_colmap


def apply(options: Any, items: dict[str, str]) -> Any:
    """Set each dotted attribute of `options` to its value, converted to the attribute's type."""
    for key, value in items.items():
        *path, leaf = key.split(".")
        obj = options
        for part in path:
            obj = getattr(obj, part)
        current = getattr(obj, leaf)
        setattr(obj, leaf, (value.lower() in ("1", "true")) if isinstance(current, bool) else type(current)(value))
    return options


def map_one(db: Path, images: Path, gt: Any, items: dict[str, str], seed: int, px_scale: float) -> dict[str, Any]:
    """One mapping of a copy of `db` with the variant's options, `seed` and the run's pixel-threshold
    factor `px_scale`; the evaluated row."""
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "database.db"
        shutil.copy(db, copy)
        options = apply(mapping_options(seed, 1, px_scale), items)
        t = time.perf_counter()
        res = run_incremental(copy, images, options)
        seconds = time.perf_counter() - t
    rec = res.reconstruction
    row: dict[str, Any] = {"seed": seed, "model_sizes": res.model_sizes, "map_seconds": round(seconds, 2),
                           "initial_pair": next((s["initial_pair"] for s in res.growth if s["initial_pair"]), None)}
    if rec is None:
        return {**row, "registered": 0}
    final_bundle_adjustment(rec, final_ba_config(RunConfig(), px_scale))
    metrics = evaluate_model(rec, gt, with_pairs=False) if gt is not None else {}
    return {**row, "registered": int(rec.num_reg_images()), "points": int(rec.num_points3D()),
            "reproj_px": round(float(rec.compute_mean_reprojection_error()), 4),
            "rot_err_deg": metrics.get("rel_rot_err_deg_median")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="NAME=OUT:SCENE_DIR")
    ap.add_argument("--variant", action="append", required=True, metavar="LABEL=KEY=VALUE,...")
    ap.add_argument("--seeds", default="0", help="comma-separated mapper seeds (default 0)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    variants = [(label, dict(kv.split("=", 1) for kv in settings)) for label, settings in parse_variants(args.variant)]
    seeds = [int(s) for s in args.seeds.split(",")]
    rows: list[dict[str, Any]] = []
    print(f"{'run':<28} {'variant':<8} {'seed':>4} {'models':<14} {'reg':>4} {'points':>7} {'reproj px':>9} {'rot err':>8}")
    for spec in args.run:
        name, _, rest = spec.partition("=")
        out, _, scene = rest.partition(":")
        scene_dir = Path(scene)
        images = find_image_dir(scene_dir)
        gt = load_gt(scene_dir)[0]
        px_scale = px_scale_of(json.loads((Path(out) / "report.json").read_text()))
        for label, items in variants:
            for seed in seeds:
                with quiet_colmap():
                    row = {"run": name, "variant": label, "options": items,
                           **map_one(Path(out) / "database.db", images, gt, items, seed, px_scale)}
                rows.append(row)
                rot = row.get("rot_err_deg")
                print(f"{name:<28} {label:<8} {seed:>4} {str(row['model_sizes']):<14} {row['registered']:>4} "
                      f"{row.get('points', 0):>7} {row.get('reproj_px', float('nan')):>9.4f} "
                      f"{'-' if rot is None else f'{rot:.4f}':>8}", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
