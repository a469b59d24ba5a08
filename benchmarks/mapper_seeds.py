"""How much a finished database's model moves with the mapper's seed: each database mapped with
seeds 0..N-1 through `recon run`'s sfm stage (its mapping options and final robust adjustment,
the default `RunConfig`), each model evaluated against the scene's ground truth.

    PYTHONPATH=. python benchmarks/mapper_seeds.py SCENE --db ours=OUT/database.db \\
        --db stock=STOCK_OUT/database.db [--seeds 5] [--json FILE]

SCENE is a scene folder with `images/` and a ground truth (`recon.eval.compare.load_gt`); the
databases are any `recon run` or stock (`recon compare`) databases of it. Seed 0 reproduces the
run's own model (the same options), so the spread says whether a gap between two methods is the
mapper's chance or the matches'. Prints one row per mapping and the median / range per database.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import recon  # noqa: F401  (cv2 before pycolmap)
from recon.config import RunConfig
from recon.core import sfm
from recon.core.stages.sfm import final_ba_config, mapping_options
from recon.eval.compare import load_gt
from recon.eval.evaluate import evaluate_model


def map_once(db: Path, scene: Path, gt: Any, seed: int, cfg: RunConfig) -> dict[str, Any]:
    """One mapping of `db` with `seed` through the sfm stage's options (full-resolution px
    thresholds, the final robust adjustment), evaluated against `gt`."""
    t = time.perf_counter()
    res = sfm.run_incremental(db, scene / "images", mapping_options(cfg, 1.0, seed))
    rec = res.reconstruction
    if rec is None:
        return {"seed": seed, "registered": 0, "points": 0, "reproj_px": None, "rot_err_deg": None,
                "auc_5": None, "seconds": round(time.perf_counter() - t, 1)}
    sfm.final_bundle_adjustment(rec, final_ba_config(cfg, 1.0), cfg.sfm.num_threads)
    ev = evaluate_model(rec, gt)
    return {"seed": seed, "registered": rec.num_reg_images(), "points": rec.num_points3D(),
            "reproj_px": rec.compute_mean_reprojection_error(), "rot_err_deg": ev.get("rel_rot_err_deg_median"),
            "auc_5": ev.get("auc_5"), "seconds": round(time.perf_counter() - t, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--db", action="append", default=[], metavar="LABEL=PATH", help="a database to map (repeatable)")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    dbs = []
    for spec in args.db:
        label, sep, path = spec.partition("=")
        if not sep or not label or not Path(path).is_file():
            ap.error(f"--db {spec!r}: expected LABEL=PATH of an existing database")
        dbs.append((label, Path(path)))
    if not dbs or args.seeds < 1:
        ap.error("give at least one --db and --seeds >= 1")
    gt, _, why = load_gt(args.scene)
    if gt is None:
        ap.error(f"{args.scene}: no ground truth ({why or 'none found'})")
    cfg = RunConfig()
    rows = []
    for seed in range(args.seeds):
        for label, db in dbs:
            row = {"db": label, **map_once(db, args.scene, gt, seed, cfg)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    for label, _ in dbs:
        errs = [r["rot_err_deg"] for r in rows if r["db"] == label and r["rot_err_deg"] is not None]
        if errs:
            print(f"{label}: rotation error median {statistics.median(errs):.4f} deg, "
                  f"range {min(errs):.4f}-{max(errs):.4f} over {len(errs)} seeds")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scene": str(args.scene), "seeds": args.seeds, "rows": rows}, indent=1) + "\n",
                             encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
