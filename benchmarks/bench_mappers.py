"""Incremental against global mapping (GLOMAP) on databases written by `recon run`.

    PYTHONPATH=. python benchmarks/bench_mappers.py --run fountain_P11=/tmp/x/fountain:/work/shared/data/scenes/fountain_P11 ...

Each `--run NAME=OUT:SCENE_DIR` names a finished `recon run SCENE_DIR --out OUT` (its
OUT/database.db, and OUT/report.json for the working-to-full-resolution factor) and the scene
folder (images and ground truth, `recon.eval.gt.find_gt`). Both mappers run on the same database
with seed 0 and one thread (`recon.core.global_sfm.run_mapper`; `global-calibrated`
first estimates focal lengths when the cameras have no prior, `run_global(calibrate=True)`;
its seconds include the calibration); the models are evaluated by
`recon.eval.evaluate.evaluate_model` as `recon compare` does (relative rotation / translation
error medians over registered GT pairs, pose AUC over all GT pairs), as the mapper left them and
after `recon run`'s final robust adjustment with its default settings
(`recon.core.stages.sfm.final_ba_config` of a default `RunConfig`, which `recon run` applies
after either mapper; `final_*` fields, `final_seconds` its own time). Prints a table and writes
benchmarks/results/mappers.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from recon.config import RunConfig
from recon.core.global_sfm import run_mapper
from recon.core.sfm import final_bundle_adjustment
from recon.core.stages.sfm import final_ba_config
from recon.eval.evaluate import evaluate_model
from recon.eval.gt import find_gt
from recon.log import quiet_colmap


def px_scale_of(report: dict) -> float:
    """The run's working-to-full-resolution factor (capped at 3), from its SfM options."""
    return float(report.get("sfm_options", {}).get("init_max_error", 4.0)) / 4.0


def bench_one(name: str, out: Path, scene_dir: Path, mappers: list[str], seed: int = 0) -> list[dict]:
    report = json.loads((out / "report.json").read_text())
    gt = find_gt(scene_dir)
    rows = []
    for mapper in mappers:
        t = time.perf_counter()
        with quiet_colmap():
            res = run_mapper(mapper.removesuffix("-calibrated"), out / "database.db", find_image_dir(scene_dir),
                             seed=seed, num_threads=1, px_scale=px_scale_of(report),
                             calibrate=mapper.endswith("-calibrated"))
        secs = time.perf_counter() - t
        rec = res.reconstruction
        ev = evaluate_model(rec, gt, with_pairs=False) if gt is not None else {}
        rows.append({
            "scene": name, "mapper": mapper, "num_images": report.get("num_images"),
            "registered": 0 if rec is None else int(rec.num_reg_images()),
            "points": 0 if rec is None else int(rec.num_points3D()),
            "num_models": res.num_models, "model_sizes": res.model_sizes, "seconds": round(secs, 2),
            "mean_reprojection_error": None if rec is None or rec.num_points3D() == 0
            else float(rec.compute_mean_reprojection_error()),
            **{k: ev.get(k) for k in ("rel_rot_err_deg_median", "rel_trans_err_deg_median", "auc_5", "auc_10",
                                      "center_err_rel_median")},
            "database": str(out / "database.db"), "max_size": report.get("config", {}).get("max_size"),
        })
        r = rows[-1]
        if rec is not None and rec.num_reg_images() >= 2:
            t = time.perf_counter()
            final_bundle_adjustment(rec, final_ba_config(RunConfig(), px_scale_of(report)))
            fin = evaluate_model(rec, gt, with_pairs=False) if gt is not None else {}
            r.update(final_seconds=round(time.perf_counter() - t, 2), final_points=int(rec.num_points3D()),
                     final_mean_reprojection_error=float(rec.compute_mean_reprojection_error())
                     if rec.num_points3D() else None,
                     **{f"final_{k}": fin.get(k) for k in ("rel_rot_err_deg_median", "auc_5")})
        print(f"{name:<16} {mapper:<12} {r['registered']:>3}/{r['num_images']:<3} {r['points']:>7} {secs:>8.1f}"
              f" {_f(r['rel_rot_err_deg_median'], '.3f'):>9} {_f(r['rel_trans_err_deg_median'], '.2f'):>9}"
              f" {_f(r['auc_5'], '.3f'):>6}   {_f(r.get('final_rel_rot_err_deg_median'), '.3f'):>9}"
              f" {_f(r.get('final_auc_5'), '.3f'):>6} {_f(r.get('final_mean_reprojection_error'), '.3f'):>6}", flush=True)
    return rows


def find_image_dir(scene_dir: Path) -> Path:
    return scene_dir / "images" if (scene_dir / "images").is_dir() else scene_dir


def _f(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", action="append", required=True, help="NAME=OUT:SCENE_DIR")
    ap.add_argument("--mappers", default="incremental,global,global-calibrated")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "mappers.json")
    a = ap.parse_args()
    print(f"{'scene':<16} {'mapper':<12} {'reg':>7} {'points':>7} {'seconds':>8} {'rot° med':>9} {'tr° med':>9} {'AUC@5':>6}"
          f"   {'final rot°':>9} {'AUC@5':>6} {'reproj':>6}")
    rows = []
    for spec in a.run:
        name, rest = spec.split("=", 1)
        out, scene_dir = rest.split(":", 1)
        rows += bench_one(name, Path(out), Path(scene_dir), a.mappers.split(","))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"meta": {"seed": 0, "num_threads": 1}, "rows": rows}, indent=1))
    print(f"JSON: {a.out}")


if __name__ == "__main__":
    main()
