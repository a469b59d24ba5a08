"""Track consistency and accuracy of finished runs: one row per `recon run` (or stock) output folder.

    python benchmarks/bench_tracks.py --scene ../shared/data/scenes/castle_P30 \\
        before=out/castle-before after=out/castle stock=out/castle-stock --json benchmarks/results/tracks.json

For each LABEL=FOLDER (a `recon run` output, or a `recon.eval.stock.run_stock` one) it reads
`report.json` and the first model under `sparse/`, and prints: registered images, 3D points,
mean track length, mean reprojection error (full-resolution px, COLMAP's), the share of the
verified match graph's observations in inconsistent tracks (two keypoints of one image in one
track; for ours also the merged graph's share before the consistency check and the matches it
dropped), the verified inliers over all pairs, and with ground truth (`recon.eval.gt.find_gt`)
the median relative rotation error and AUC@5 (`recon.eval.evaluate`). Nothing is rerun, so the
runs being compared must come from the same pairs and pair cache to be comparable.

`--sfm-seeds 0,1,2` also reruns COLMAP's incremental mapper alone on each run's `database.db`
with each seed (`recon.core.global_sfm.run_mapper`, one thread, as `bench_mappers.py` does) and
prints one row per run and seed: how much of a difference between two runs is the mapper's own
spread. (These figures differ from the run's own model, whose SfM stage adds its retries and
hooks, so compare them only with each other.)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import recon  # noqa: F401  (OpenCV before pycolmap)


def row(label: str, folder: Path, gt: dict | None) -> dict:
    """The figures of one run folder (see module doc)."""
    import pycolmap

    from recon.eval.compare import inconsistent_share
    from recon.eval.evaluate import evaluate_model

    rep = json.loads((folder / "report.json").read_text(encoding="utf-8"))
    merge = rep.get("merge") or {}
    out = {"label": label, "folder": str(folder), "registered": rep.get("registered_images", 0),
           "num_images": rep.get("num_images", 0), "points": rep.get("num_points3D", 0),
           "track_length": rep.get("mean_track_length"), "reproj_px": rep.get("mean_reprojection_error"),
           "inconsistent_share": inconsistent_share(rep),
           "inconsistent_share_merged_before": merge.get("inconsistent_share_merged"),
           "dropped_conflicts": merge.get("dropped_conflicts"),
           "verified_inliers": int(sum(p.get("verified_inliers", 0) for p in rep.get("pairs", []))),
           "rel_rot_err_deg_median": None, "auc_5": None}
    models = sorted((folder / "sparse").glob("*")) if (folder / "sparse").is_dir() else []
    if gt and models:
        ev = evaluate_model(pycolmap.Reconstruction(str(models[0])), gt)
        out["rel_rot_err_deg_median"], out["auc_5"] = ev["rel_rot_err_deg_median"], ev["auc_5"]
    return out


def seed_rows(label: str, folder: Path, scene: Path, seeds: list[int], gt: dict | None) -> list[dict]:
    """The incremental mapper alone on `folder`'s database, once per seed (see module doc)."""
    from recon.core.global_sfm import run_mapper
    from recon.core.scene import find_image_dir
    from recon.eval.evaluate import evaluate_model
    from recon.log import quiet_colmap

    rep = json.loads((folder / "report.json").read_text(encoding="utf-8"))
    px_scale = float(rep.get("sfm_options", {}).get("init_max_error", 4.0)) / 4.0  # as bench_mappers.py
    out = []
    for seed in seeds:
        with quiet_colmap():
            rec = run_mapper("incremental", folder / "database.db", find_image_dir(scene), seed=seed, num_threads=1,
                             px_scale=px_scale).reconstruction
        ev = evaluate_model(rec, gt, with_pairs=False) if gt and rec is not None else {}
        out.append({"label": label, "seed": seed, "registered": 0 if rec is None else int(rec.num_reg_images()),
                    "points": 0 if rec is None else int(rec.num_points3D()),
                    "reproj_px": None if rec is None else float(rec.compute_mean_reprojection_error()),
                    "rel_rot_err_deg_median": ev.get("rel_rot_err_deg_median"), "auc_5": ev.get("auc_5")})
        r = out[-1]
        rot = r["rel_rot_err_deg_median"]
        print(f"| {label} | {seed} | {r['registered']} | {r['points']} | "
              f"{'-' if r['reproj_px'] is None else format(r['reproj_px'], '.3f')} | "
              f"{'-' if rot is None else f'{rot:.3f}°'} | {'-' if r['auc_5'] is None else format(r['auc_5'], '.3f')} |",
              flush=True)
    return out


def table(rows: list[dict]) -> list[str]:
    def f(v, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    lines = ["| run | registered | points | track length | reproj. px | inconsistent obs. (merged, before check) | "
             "dropped conflicts | verified inliers | rel. rot. err. median | AUC@5 |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        inc = "-" if r["inconsistent_share"] is None else f"{100 * r['inconsistent_share']:.1f} %"
        if r["inconsistent_share_merged_before"] is not None:
            inc += f" ({100 * r['inconsistent_share_merged_before']:.1f} %)"
        rot = r["rel_rot_err_deg_median"]
        lines.append(f"| {r['label']} | {r['registered']}/{r['num_images']} | {r['points']} | "
                     f"{f(r['track_length'], '.2f')} | {f(r['reproj_px'], '.3f')} | {inc} | "
                     f"{f(r['dropped_conflicts'], 'd')} | {r['verified_inliers']} | "
                     f"{'-' if rot is None else f'{rot:.3f}°'} | {f(r['auc_5'], '.3f')} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=FOLDER, a finished run's output folder")
    ap.add_argument("--scene", type=Path, help="scene folder, for its ground-truth cameras")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--sfm-seeds", default="", help="comma-separated seeds: rerun the mapper alone per run (slow)")
    args = ap.parse_args(argv)
    from recon.eval.gt import find_gt

    try:
        gt = find_gt(args.scene) if args.scene else None
        rows = []
        for spec in args.runs:
            label, sep, folder = spec.partition("=")
            if not sep:
                raise ValueError(f"{spec}: expected LABEL=FOLDER")
            rows.append(row(label, Path(folder), gt))
    except (OSError, ValueError, KeyError) as e:
        print(f"bench_tracks: {e}", file=sys.stderr)
        return 2
    print("\n".join(table(rows)))
    seeded: list[dict] = []
    if args.sfm_seeds:
        if not args.scene:
            print("bench_tracks: --sfm-seeds needs --scene", file=sys.stderr)
            return 2
        seeds = [int(x) for x in args.sfm_seeds.split(",")]
        print("\n| run | mapper seed | registered | points | reproj. px | rel. rot. err. median | AUC@5 |\n"
              "|---|---|---|---|---|---|---|")
        for r in rows:
            seeded += seed_rows(r["label"], Path(r["folder"]), args.scene, seeds, gt)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scene": str(args.scene or ""), "rows": rows, "mapper_seeds": seeded},
                                        indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
