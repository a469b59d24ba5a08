"""The `mser` escalation level on its own, pair by pair: what its regions find and how well the
local-affine-frame (LAF) check separates right matches from wrong ones (issue 13; figures in
docs/decisions.md, "The `mser` level").

For each ground-truth pair (default: the EVD pairs) it runs `matching.mserlevel.mser_attempt`
from an empty best attempt (the level's own matches only), fits the level's RANSAC homography
and reports: regions per image, FGINN matches, RANSAC inliers and how many of them lie within
sqrt(3) / 3 / 5 px of the ground truth; and, under the ground truth, the share of the matches
within 5 px (right) and beyond (wrong) that pass the LAF check. `--grid-n 0` detects in the
originals only (the level's first version). Prints a table and writes JSON:

    python benchmarks/mser_level.py ../shared/data --only evd --json benchmarks/results/mser-level.json
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from matching.context import Attempt, MatchContext
from matching.fine import FineMatches
from matching.io import load_gray
from matching.matcher import MatcherConfig
from matching.matching_utils import ransac_homography
from matching.metrics import reprojection_errors
from matching.mser import MserConfig, laf_consistent
from matching.mserlevel import mser_attempt, pooled_mser
from matching.store import FeatureStore
from matching.twosided import fginn_match
from recon.eval.bench_pairs import discover_pairs


def one_pair(path0: Path, path1: Path, H_gt: np.ndarray, cfg: MserConfig) -> dict:
    store = FeatureStore()
    store.add_image("0", load_gray(path0))
    store.add_image("1", load_gray(path1))
    ctx = MatchContext(store, ("0", "1"), MatcherConfig(), [])
    empty = FineMatches(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros((0, 2), np.int32),
                        np.zeros(0, np.float32), {})
    t = time.perf_counter()
    att = mser_attempt(ctx, Attempt("", 0, empty, [], [], 0), cfg)
    seconds = time.perf_counter() - t
    fa, fb = pooled_mser(ctx, 0, cfg), pooled_mser(ctx, 1, cfg)  # cached by the attempt
    m = att.fine.matches
    p0, p1 = att.fine.kpts_ref[m[:, 0]], att.fine.kpts_target[m[:, 1]]
    row = {"regions": [len(fa), len(fb)], "matches": int(len(m)), "verified": att.verified,
           "laf_dropped": att.fine.per_view.get("mser_laf_dropped", 0), "seconds": round(seconds, 2)}
    H, inl = ransac_homography(p0, p1, 3.0, seed=0) if len(m) >= 4 else (None, np.zeros(len(m), bool))
    err = reprojection_errors(H_gt, p0[inl], p1[inl]) if inl.any() else np.zeros(0)
    row.update(inliers=int(inl.sum()), within_sqrt3=int((err <= np.sqrt(3)).sum()), within_3=int((err <= 3).sum()),
               within_5=int((err <= 5).sum()))
    mm, _ = fginn_match(fa, fb, cfg.ratio, cfg.fginn_px, 8, 0)  # before the check, under the ground truth
    if len(mm) and fa.frames is not None and fb.frames is not None:
        e = reprojection_errors(H_gt, fa.kpts[mm[:, 0]], fb.kpts[mm[:, 1]])
        ok = laf_consistent(H_gt, fa.kpts[mm[:, 0]], fa.frames[mm[:, 0]], fb.frames[mm[:, 1]], cfg)
        right = e <= 5
        row.update(laf_pass_right=round(float(ok[right].mean()), 3) if right.any() else None,
                   laf_pass_wrong=round(float(ok[~right].mean()), 3) if (~right).any() else None)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("--only", default="evd", help="pairs whose name contains this text (default: evd)")
    ap.add_argument("--grid-n", type=int, default=None, help="tilt steps of the level's views (0 = originals only)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a numeric MserConfig field, e.g. --set disc_px=9 (repeatable)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cfg = MserConfig()
    for kv in args.set:
        name, _, value = kv.partition("=")
        current = getattr(cfg, name, None)
        if not isinstance(current, (int, float)) or isinstance(current, bool):
            raise SystemExit(f"error: --set {kv}: not a numeric MserConfig field")
        cfg = replace(cfg, **{name: type(current)(value)})
    if args.grid_n is not None:
        cfg = replace(cfg, grid=replace(cfg.grid, n=args.grid_n))
    pairs = [p for p in discover_pairs(args.data_root) if args.only.lower() in p.name.lower()]
    if not pairs:
        raise SystemExit(f"error: no ground-truth pair under {args.data_root} matches {args.only!r}")
    rows = []
    print(f"{'pair':<14}{'regions':>13}{'matches':>9}{'verified':>9}{'inliers':>8}{'<=1.73':>8}{'<=3':>6}{'<=5':>6}"
          f"{'LAF right':>10}{'LAF wrong':>10}{'s':>7}")
    for p in pairs:
        r = {"pair": p.name, **one_pair(p.path0, p.path1, p.H_1_from_0, cfg)}
        rows.append(r)
        print(f"{p.name:<14}{r['regions'][0]:>6}/{r['regions'][1]:<6}{r['matches']:>9}{r['verified']:>9}{r['inliers']:>8}"
              f"{r['within_sqrt3']:>8}{r['within_3']:>6}{r['within_5']:>6}{str(r.get('laf_pass_right')):>10}"
              f"{str(r.get('laf_pass_wrong')):>10}{r['seconds']:>7}", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"grid_n": cfg.grid.n, "settings": args.set, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
