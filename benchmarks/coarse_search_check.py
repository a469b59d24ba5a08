"""Does the coarse-to-fine (t, phi) search find the full grid's best views? Every side of every
ground-truth pair:

    PYTHONPATH=. python benchmarks/coarse_search_check.py ../shared/data [--set search_stride=2]

For each pair of `recon.eval.bench_pairs.discover_pairs` and each side (image 0 simulated
against image 1, then the reverse), the coarse search runs once with `CoarseConfig(search="grid")`
(all 45 views) and once with the default coarse-to-fine search (`--set` overrides fields of
`CoarseConfig`); prints the best view's ORB inliers, how many distinct ORB views each scored,
and whether the fine stage's views (`fine.select_fine_views` of the ranking: the top 2, the
default `fine_top_k`, and the top 4, the `topk` escalation level's) are the same.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from matching.coarse import CoarseConfig, coarse_search, rank_views
from matching.fine import select_fine_views
from matching.store import FeatureStore
from matching.types import CoarseScore
from matching.views import view_grid
from recon.eval.bench_pairs import discover_pairs, load_gray


def distinct_views(scores: list[CoarseScore]) -> int:
    """ORB views actually scored: the t = 1 views share one score."""
    return len([c for c in scores if c.view.t > 1.0]) + (1 if any(c.view.t == 1.0 for c in scores) else 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a CoarseConfig field of the coarse-to-fine run (int values), repeatable")
    args = ap.parse_args()
    kw: dict[str, Any] = {}
    for kv in args.set:
        key, _, raw = kv.partition("=")
        kw[key] = int(raw) if raw.lstrip("-").isdigit() else raw
    grid_cfg, c2f_cfg = CoarseConfig(search="grid"), CoarseConfig(**kw)
    grid = view_grid()
    n = same2 = same4 = 0
    counts: list[int] = []
    print(f"{'pair':14s} side  best inliers  views scored  same top 2  same top 4")
    for pair in discover_pairs(args.data_root):
        store = FeatureStore()
        store.add_image("0", load_gray(pair.path0))
        store.add_image("1", load_gray(pair.path1))
        for side in (0, 1):
            ref, target = str(side), str(1 - side)
            full = rank_views(coarse_search(store, ref, target, grid, grid_cfg))
            c2f = coarse_search(store, ref, target, grid, c2f_cfg)
            ok2 = select_fine_views(full, 2) == select_fine_views(rank_views(c2f), 2)
            ok4 = select_fine_views(full, 4) == select_fine_views(rank_views(c2f), 4)
            n, same2, same4 = n + 1, same2 + ok2, same4 + ok4
            counts.append(distinct_views(c2f))
            print(f"{pair.name:14s} {side:4d}  {full[0].inliers:12d}  {counts[-1]:6d} / {distinct_views(full)}"
                  f"  {'yes' if ok2 else 'NO':>10s}  {'yes' if ok4 else 'no':>10s}")
    print(f"same top 2 on {same2} of {n} sides, same top 4 on {same4}; views scored: mean {sum(counts) / n:.1f}, "
          f"min {min(counts)}, max {max(counts)} (the grid: {len([v for v in grid if v.t > 1.0]) + 1})")


if __name__ == "__main__":
    main()
