"""Pair benchmark with the extra-affine matcher before and after the coarse-stage savings of
issue 11 ("cheaper views"), side by side in one process:

    PYTHONPATH=. python benchmarks/bench_pairs_speed.py ../shared/data \
        --json benchmarks/results/pairs.json [--methods extra-affine,extra-affine-grid,asift] [--only graf]
        [--variant root=fine.root_sift=true] [--tilt OUT]

Methods (interleaved per pair, so every method of a pair runs under the same machine load):

* `extra-affine`: the default `MatcherConfig()` (coarse-to-fine (t, phi) search, the undecided
  reference's second side searched near the first side's view);
* `extra-affine-grid`: the same with `coarse.search="grid"` and `coarse.settle_targeted=False`,
  i.e. the matcher as it was before (every view of the 45-view grid on every searched side);
* `extra-affine-exact-blur`: the default matcher with `views.simulate`'s exact anti-aliasing blur
  instead of blurring by halving (`views.blur_compress_x`; the steep views before 2026-12-07);
* `extra-affine-two-warps`: the default matcher with the views at phi = 0 rotated-and-zoomed,
  blurred, then compressed (two Lanczos warps; `views.FUSED_AXIS_WARP` off, before 2026-12-08);
* `sift`, `orb`, `asift`, `aorb`: the baselines of `recon bench pairs` (stock 5 px RANSAC);
* `--variant LABEL=KEY=VALUE[,KEY=VALUE]` (repeatable): the default matcher with
  `MatcherConfig.from_overrides` settings (a top-level field or a section's field:
  `fine.root_sift=true`, `final_homography=false`), run as method LABEL.

`--tilt OUT` runs on the rendered tilt pairs of `make bench-tilt` (four textures, six viewing
angles, two azimuths, two zooms: 96 pairs with exact homographies, rendered into OUT, the two
photo textures read from DATA_ROOT) instead of DATA_ROOT's pairs.

Each method first matches the first pair once, untimed (thread pools, lazy imports and
OpenCV's first calls would otherwise be charged to whichever method runs first; `--no-warmup`).
Prints `recon bench pairs`' table and summary, then the ratio lines: each extra-affine variant's
median seconds against ASIFT's over all pairs and over graf alone, and after / before per pair.
Rows are the same as `recon bench pairs --json` writes (one per pair and method).
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path
from typing import Any

import matching.views as views
from matching.memory import return_large_buffers_to_os
from matching.registry import PairMatcher, get_matcher
from matching.store import FeatureStore
from matching.types import PairResult
from recon.config import matcher_options
from recon.errors import UserError
from recon.eval.bench_pairs import DEFAULT_TH, GtPair, discover_pairs, load_gray, print_report, run_bench, run_pair, solved

VARIANTS: dict[str, dict[str, Any]] = {
    "extra-affine": {},
    "extra-affine-grid": {"coarse__search": "grid", "coarse__settle_targeted": False},
}
TILT_ANGLES = (60.0, 70.0, 75.0, 80.0, 83.0, 85.0)  # `make bench-tilt`'s pairs
TILT_AZIMUTHS = (0.0, 45.0)
TILT_ZOOMS = (0.5, 1.0)


EXACT_BLUR = "extra-affine-exact-blur"
TWO_WARPS = "extra-affine-two-warps"
FLAG_METHODS = {EXACT_BLUR: "ANTIALIAS_HALVING", TWO_WARPS: "FUSED_AXIS_WARP"}
"""Methods that run the default matcher with one of `matching.views`' module flags off."""


class FlagOff:
    """A matcher run with a `matching.views` module flag off for the call (`ANTIALIAS_HALVING`:
    the exact anti-aliasing blur; `FUSED_AXIS_WARP`: two warps for the views with phi = 0, as
    before 2026-12-08); the benchmark matches one pair at a time, so nothing else sees it."""

    def __init__(self, name: str, inner: PairMatcher):
        self.name, self.inner, self.flag = name, inner, FLAG_METHODS[name]

    def match(self, store: FeatureStore, name0: str, name1: str) -> PairResult:
        setattr(views, self.flag, False)
        try:
            return self.inner.match(store, name0, name1)
        finally:
            setattr(views, self.flag, True)


def median_seconds(rows: list[dict], method: str, dataset: str | None = None) -> float | None:
    """Median seconds of `method` over its rows (of `dataset` only, when given)."""
    s = [r["seconds"] for r in rows if r["method"] == method and (dataset is None or r["dataset"] == dataset)]
    return statistics.median(s) if s else None


def parse_variant(spec: str) -> tuple[str, dict[str, Any]]:
    """`LABEL=KEY=VALUE[,KEY=VALUE]` as (label, `MatcherConfig.from_overrides` keywords): the keys
    are `recon run --set matcher.KEY=VALUE`'s, checked and typed as it does
    (`recon.config.matcher_options`; the seed comes from `--seed`)."""
    label, _, rest = spec.partition("=")
    if not label:
        raise SystemExit(f"--variant {spec!r}: expected LABEL=KEY=VALUE[,KEY=VALUE]")
    options: dict[str, str] = {}
    for item in filter(None, (x.strip() for x in rest.split(","))):
        key, sep, text = item.partition("=")
        if not sep:
            raise SystemExit(f"--variant {spec!r}: {item!r} is not KEY=VALUE")
        options[key] = text
    try:
        typed = matcher_options("extra-affine", options)
    except UserError as e:
        raise SystemExit(f"--variant {label}: {e}") from None
    return label, {key.replace(".", "__", 1): value for key, value in typed.items()}


def tilt_pairs(data_root: Path, out: Path) -> list[GtPair]:
    """The rendered tilt pairs of `make bench-tilt`, written under `out`."""
    from recon.eval.bench_tilt import parse_textures, tilt_views, write_pairs

    textures = parse_textures(f"procedural:0,procedural:1,{data_root / 'oxford/graf/img1.png'},"
                              f"{data_root / 'hpatches/v_dogman/1.png'}")
    return write_pairs(out, textures, tilt_views(TILT_ANGLES, TILT_AZIMUTHS, zooms=TILT_ZOOMS))[0]


def variant_lines(rows: list[dict], variants: dict[str, dict[str, Any]]) -> list[str]:
    """Per extra-affine variant: pairs solved (`bench_pairs.solved`: precision >= 50 % with >= 20
    correct, as `recon bench pairs` counts them), correct
    matches in all, and against the default (`extra-affine`) pairs with more / fewer correct."""
    base = {r["pair"]: r for r in rows if r["method"] == "extra-affine"}
    lines = []
    for m in variants:
        mine = [r for r in rows if r["method"] == m]
        if not mine:
            continue
        line = (f"{m}: solved {sum(map(solved, mine))}/{len(mine)}, "
                f"correct {sum(r['correct'] for r in mine)}")
        if base and m != "extra-affine":
            more = sum(r["correct"] > base[r["pair"]]["correct"] for r in mine if r["pair"] in base)
            fewer = sum(r["correct"] < base[r["pair"]]["correct"] for r in mine if r["pair"] in base)
            line += f"; against extra-affine: {more} pairs with more correct, {fewer} with fewer"
        lines.append(line)
    return lines


def ratio_lines(rows: list[dict], variants: dict[str, dict[str, Any]] = VARIANTS,
                before_method: str = "extra-affine-grid") -> list[str]:
    """"X: median s over all pairs / graf, N x faster than asift" per extra-affine variant, and
    the per-pair after (`extra-affine`) / before (`before_method`) seconds."""
    lines = []
    for m in variants:
        for dataset, label in ((None, "all pairs"), ("oxford", "graf")):
            ours, base = median_seconds(rows, m, dataset), median_seconds(rows, "asift", dataset)
            if ours is None:
                continue
            line = f"{m} on {label}: median {ours:.2f} s"
            if base:
                line += f", asift {base:.2f} s: {base / ours:.2f} x faster than asift"
            lines.append(line)
    after = {r["pair"]: r for r in rows if r["method"] == "extra-affine"}
    before = {r["pair"]: r for r in rows if r["method"] == before_method}
    for pair in after:
        if pair in before and after[pair]["seconds"] > 0:
            a, b = after[pair], before[pair]
            counts = ("identical" if (a["points"], a["correct"]) == (b["points"], b["correct"])
                      else f"{b['points']}/{b['correct']} -> {a['points']}/{a['correct']}")
            lines.append(f"{pair}: {b['seconds']:.2f} s -> {a['seconds']:.2f} s "
                         f"({b['seconds'] / a['seconds']:.2f} x), points / correct {counts}"
                         + (f", escalation {a['escalation']}" if a.get("escalation") else ""))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("--methods", default="extra-affine,extra-affine-grid,asift",
                    help=f"comma-separated: extra-affine, extra-affine-grid, {EXACT_BLUR}, {TWO_WARPS}, sift, orb, asift, aorb")
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    ap.add_argument("--only", default=None, help="only pairs whose name contains this text")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-warmup", action="store_true",
                    help="do not match the first pair once per method (untimed) before the run")
    ap.add_argument("--variant", action="append", default=[],
                    help="LABEL=KEY=VALUE[,KEY=VALUE]: the default matcher with these settings, as method LABEL")
    ap.add_argument("--tilt", type=Path, default=None,
                    help="render `make bench-tilt`'s 96 pairs into this folder and run on them")
    args = ap.parse_args()
    return_large_buffers_to_os()  # as the recon CLI does: the peak MB column is comparable with `recon bench pairs`
    variants = {**VARIANTS, **dict(parse_variant(v) for v in args.variant)}
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    methods += [label for label in variants if label not in VARIANTS and label not in methods]
    matchers: dict[str, PairMatcher] = {}
    for m in methods:
        if m in FLAG_METHODS:
            matchers[m] = FlagOff(m, get_matcher("extra-affine", seed=args.seed))
        elif m in variants:
            try:
                matchers[m] = get_matcher("extra-affine", seed=args.seed, **variants[m])
            except (TypeError, ValueError) as e:
                raise SystemExit(f"--variant {m}: {e}") from None
        else:
            matchers[m] = get_matcher(m, seed=args.seed)
    try:
        pairs = tilt_pairs(args.data_root, args.tilt) if args.tilt else discover_pairs(args.data_root)
    except UserError as e:  # a texture photo missing under DATA_ROOT, an unreadable homography
        raise SystemExit(f"error: {e}") from None
    if args.only:
        pairs = [p for p in pairs if args.only.lower() in p.name.lower()]
    if not pairs:
        raise SystemExit(f"{args.data_root}: no ground-truth pairs")
    if not args.no_warmup:  # thread pools, lazy imports and OpenCV's first calls: not the first pair's cost
        img0, img1 = load_gray(pairs[0].path0), load_gray(pairs[0].path1)
        for m in methods:
            run_pair(pairs[0], img0, img1, m, matchers[m])
    rows = run_bench(pairs, methods, th=DEFAULT_TH, json_path=args.json, matchers=matchers)
    print_report(rows, th=DEFAULT_TH)
    flagged = [m for m in methods if m in FLAG_METHODS]
    shown = {**variants, **{m: {} for m in flagged}}
    before = flagged[0] if flagged else "extra-affine-grid"
    for line in ratio_lines(rows, shown, before) + variant_lines(rows, shown):
        print(line)
    if args.json is not None:
        print(f"wrote {len(rows)} rows to {args.json}")


if __name__ == "__main__":
    main()
