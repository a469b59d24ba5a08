"""Markdown tables for the README from a `recon bench scenes --json` / `bench_scenes.py` file.

    python benchmarks/scene_tables.py benchmarks/results/rendered.json

One row per scene and method: registered images, median relative rotation error against the
ground truth, median camera-centre error after the similarity alignment (relative to the
scene's camera spread), and the median COLMAP-verified inliers over the pairs of neighbouring
views (adjacent in name order: the rendered arcs name their views in azimuth order) and over
the wider pairs (pairs a method did not verify count as 0, so a method that loses pairs shows
it; in brackets the same counting each distinct pair of keypoint positions once, for results
that hold it: `distinct_inliers` in docs/report-schema.md), and the share of the verified match
graph's observations in inconsistent tracks (two keypoints of one image in one track; '-' for
results written before it was measured). Rendered scenes whose results hold `correct_per_pair`
(`recon compare` since 2026-12-03: verified correspondences within sqrt(3) px of the exact
transfer through the rendered planes, `recon.eval.gt_planes`) get a column with its mean over
the verified pairs and their median distance from that transfer (`correct_median_px`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def inliers_by_neighbourhood(pairs: list[dict], key: str = "verified_inliers") -> tuple[float, float]:
    """(median over neighbouring-view pairs, median over the others) of verified inliers (`key`:
    "distinct_inliers" counts COLMAP's keypoint copies of one point once)."""
    names = sorted({p["image0"] for p in pairs} | {p["image1"] for p in pairs})
    pos = {n: i for i, n in enumerate(names)}
    near = [p.get(key, 0) for p in pairs if abs(pos[p["image0"]] - pos[p["image1"]]) == 1]
    wide = [p.get(key, 0) for p in pairs if abs(pos[p["image0"]] - pos[p["image1"]]) > 1]
    med = lambda v: float(np.median(v)) if v else float("nan")  # noqa: E731
    return med(near), med(wide)


def inconsistent_share(m: dict) -> float | None:
    """Observations in tracks with two keypoints of one image (ours: `tracks.merged`, stock:
    `tracks.graph`), or None when not measured."""
    tracks = m.get("tracks") or {}
    v = (tracks.get("merged") or tracks.get("graph") or {}).get("inconsistent_share")
    return None if v is None else float(v)


def rows(data: dict) -> list[str]:
    correct = any(m.get("correct_per_pair") is not None for res in data["scenes"] for m in res["methods"].values())
    out = ["| scene (views) | method | registered | rel. rot. err. median | centre err. (rel.) | "
           "median verified inliers, neighbours / wider pairs | " + ("correct per verified pair | " if correct else "")
           + "inconsistent tracks (obs.) | 3D points | total s |",
           "|---|---|---|---|---|---|---|---|---|" + ("---|" if correct else "")]
    for res in data["scenes"]:
        scene = Path(res["scene"]).name
        first = True
        for name, m in res["methods"].items():
            near, wide = inliers_by_neighbourhood(m.get("pairs") or [])
            inl = f"{near:.0f} / {wide:.0f}"
            if any("distinct_inliers" in p for p in m.get("pairs") or []):
                dn, dw = inliers_by_neighbourhood(m.get("pairs") or [], "distinct_inliers")
                inl += f" ({dn:.0f} / {dw:.0f} distinct)"
            reg = f"{m.get('registered_images', 0)}/{m.get('num_images', 0)}"
            rot = m.get("rel_rot_err_deg_median")
            cen = m.get("center_err_rel_median")
            label = "extra-affine" if name == "extra_affine" else name.replace("-", " ")
            secs = m.get("seconds_total")
            inc = inconsistent_share(m)
            out.append(f"| {scene + ' (' + str(m.get('num_images', 0)) + ')' if first else ''} | {label} | {reg} | "
                       f"{'-' if rot is None else f'{rot:.2f}°'} | {'-' if cen is None else f'{100 * cen:.2f} %'} | "
                       f"{inl} | {_correct(m) if correct else ''}{'-' if inc is None else f'{100 * inc:.1f} %'} | "
                       f"{m.get('num_points3D', 0)} | "
                       f"{'-' if secs is None else f'{secs:.1f}'} |")
            first = False
    return out


def _correct(m: dict) -> str:
    c, med = m.get("correct_per_pair"), m.get("correct_median_px")
    return ("-" if c is None else f"{c:.0f}") + ("" if med is None else f", {med:.2f} px") + " | "


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json", type=Path)
    args = ap.parse_args(argv)
    try:
        data = json.loads(args.json.read_text(encoding="utf-8"))
        print("\n".join(rows(data)))
    except (OSError, ValueError, KeyError) as e:
        print(f"scene_tables: {args.json}: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
