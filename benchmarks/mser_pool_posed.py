"""`recon bench posed`'s wide pairs with the default matcher and matcher variants, side by side:

    PYTHONPATH=. python benchmarks/mser_pool_posed.py ../shared/data/scenes --min-angle 80 \
        --variant pooled=escalation.mser.pool=verified --json benchmarks/results/mser-pool-posed.json

The pairs are `recon bench posed`'s (3 per 15° bin and scene, up to 120°), here only those of at
least `--min-angle` degrees between the cameras (where the escalation runs); each variant is the
pair matcher with `final_homography=False`, as the posed benchmark builds it, plus the variant's
settings (`bench_pairs_speed.parse_variant`'s `LABEL=KEY=VALUE[,KEY=VALUE]`, checked and typed as
`recon run --set matcher.KEY=VALUE`). Prints every pair where a variant differs from the default or the
default escalates (level, correct matches, pose error in degrees, seconds), then each method's
summary (solved, AUC@5 / 10 / 20°). docs/decisions.md, "Pooling the escalation's verified
matches for `mser`", is its first use.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from bench_pairs_speed import parse_variant  # the sibling script (this folder is on sys.path when run)

from matching.registry import PairMatcher, get_matcher
from recon.eval.bench_posed import discover_posed_pairs, run_posed_bench, summarize_posed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", type=Path, help="a folder of scenes with GT cameras (../shared/data/scenes)")
    ap.add_argument("--min-angle", type=float, default=80.0, help="widest pairs only: at least this angle, degrees")
    ap.add_argument("--variant", action="append", default=[], help="LABEL=KEY=VALUE[,KEY=VALUE]")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    variants = dict(parse_variant(v) for v in args.variant)
    matchers: dict[str, PairMatcher] = {"extra-affine": get_matcher("extra-affine", seed=args.seed, final_homography=False)}
    for label, kw in variants.items():
        matchers[label] = get_matcher("extra-affine", seed=args.seed, final_homography=False, **kw)
    pairs = [p for p in discover_posed_pairs(args.root, per_bin=3, max_angle=120.0) if p.angle_deg >= args.min_angle]
    if not pairs:
        raise SystemExit(f"{args.root}: no posed pairs of at least {args.min_angle:g} degrees")
    print(f"{len(pairs)} pairs of at least {args.min_angle:g} degrees")
    rows = run_posed_bench(pairs, list(matchers), matchers, seed=args.seed, json_path=args.json, progress=False)
    by: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        by.setdefault(r["pair"], {})[r["method"]] = r
    for pair, d in by.items():
        base = d["extra-affine"]
        others = [d[m] for m in variants]
        if base["escalation"] or any((o["correct"], o["escalation"]) != (base["correct"], base["escalation"]) for o in others):
            parts = [f"{r['method']} {r['escalation'] or 'fast'} {r['correct']} {r['pose_err_deg']:.2f}° {r['seconds']:.1f} s"
                     for r in (base, *others)]
            print(f"{pair} ({base['angle_deg']:.0f}°): " + " | ".join(parts))
    for m, s in summarize_posed(rows).items():
        auc = " / ".join(f"{a:.3f}" for a in s["auc"])
        print(f"{m}: solved {s['solved']}/{s['pairs']}, AUC@5 / 10 / 20 {auc}, median correct {s['median_correct']:g}, "
              f"total {s['total_seconds']:.1f} s")


if __name__ == "__main__":
    main()
