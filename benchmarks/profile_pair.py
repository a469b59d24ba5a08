"""Where one pair's matching time goes: CPU seconds per primitive of the extra-affine matcher.

    PYTHONPATH=. python benchmarks/profile_pair.py ../shared/data "graf 1-3,graf 1-5" \
        [--set coarse__search=grid --set coarse__settle_targeted=false]

Runs the matcher single-threaded (`workers=1`, so the per-stage figures add up) on each named
pair of `recon.eval.bench_pairs.discover_pairs` twice (the first run warms up, the second is
reported) and prints the matcher's own stage timings (wall seconds) and the process CPU seconds
spent in each primitive, wrapped where the stages call it: SIFT / ORB detection, view warping
(`views.simulate`), the canvas-edge filter, L2 / Hamming ratio matching, RANSAC homographies and
the guided round, with the number of calls (e.g. ORB calls = coarse views scored + the target).
CPU seconds are steadier than wall seconds on a loaded machine; OpenCV's own threads count.

`--timeline` runs the matcher as `recon bench pairs` does (its view pool on every core) and prints
instead, per call of those primitives and of the patch refinement's blocks, the wall-clock
interval (seconds from the pair's start) and the thread it ran on: which detections overlap the
coarse search or each other, and what the critical path is (docs/decisions.md, "SIFT detections
side by side within a pixel budget").
"""

from __future__ import annotations

import argparse
import collections
import functools
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

import matching.coarse as coarse
import matching.features as features
import matching.fine as fine
import matching.guided as guided
import matching.matching_utils as mu
import matching.reference as reference
import matching.refine as refine
import matching.strategies as strategies
import matching.viewfeatures as viewfeatures
import matching.views as views
from matching.matcher import ExtraAffineMatcher, MatcherConfig
from recon.eval.bench_pairs import discover_pairs, load_gray, run_pair

CPU: dict[str, float] = collections.defaultdict(float)
CALLS: collections.Counter[str] = collections.Counter()
TIMELINE: list[tuple[float, float, str, str]] = []
"""(start, end, thread, primitive) of every wrapped call, wall seconds of `time.perf_counter`."""


def _wrap(fn, label, detail=None):
    @functools.wraps(fn)
    def timed(*a, **k):
        name = label if detail is None else f"{label}:{detail(*a, **k)}"
        t = time.process_time()
        w = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            CPU[name] += time.process_time() - t
            CALLS[name] += 1
            TIMELINE.append((w, time.perf_counter(), threading.current_thread().name, name))
    return timed


def instrument() -> Callable[[], None]:
    """Wrap the primitives in every module that calls them (they are imported by name); returns
    the function that puts the originals back (so a caller in the same process, such as a test,
    leaves nothing wrapped)."""
    undo: list[tuple[Any, str, Any]] = []

    def patch(module: Any, name: str, new: Any) -> None:
        undo.append((module, name, getattr(module, name)))
        setattr(module, name, new)

    patch(viewfeatures, "detect", _wrap(features.detect, "detect", lambda img, cfg, mask=None: cfg.name))
    patch(viewfeatures, "simulate", _wrap(views.simulate, "warp views"))
    patch(viewfeatures, "away_from_canvas_edge", _wrap(viewfeatures.away_from_canvas_edge, "canvas-edge filter"))
    rm = _wrap(mu.ratio_match, "ratio match",
               lambda a, b, norm, *x, **k: "hamming" if norm == cv2.NORM_HAMMING else "L2")
    for module in (coarse, fine, reference):
        patch(module, "ratio_match", rm)
    rh = _wrap(mu.ransac_homography, "RANSAC homography")
    for module in (coarse, strategies, reference, guided):
        patch(module, "ransac_homography", rh)
    patch(guided, "guided_match", _wrap(fine.guided_match, "guided match"))
    patch(refine, "refine_points0", _wrap(refine.refine_points0, "patch refinement block"))

    def restore() -> None:
        for module, name, old in reversed(undo):
            setattr(module, name, old)

    return restore


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_root", type=Path)
    ap.add_argument("pairs", help='comma-separated pair names, e.g. "graf 1-3,graf 1-5"')
    ap.add_argument("--set", action="append", default=[], metavar="SECTION__FIELD=VALUE",
                    help="a MatcherConfig override (MatcherConfig.from_overrides), repeatable")
    ap.add_argument("--timeline", action="store_true",
                    help="wall-clock intervals per thread with the view pool on every core, instead of CPU seconds")
    args = ap.parse_args(argv)
    overrides: dict[str, Any] = {}
    for kv in args.set:
        key, _, raw = kv.partition("=")
        overrides[key] = {"true": True, "false": False}.get(raw.lower(), raw)
    restore = instrument()
    try:
        profile(args, overrides)
    finally:
        restore()


def profile(args: argparse.Namespace, overrides: dict[str, Any]) -> None:
    """Run and print each pair of `args.pairs` (`main`'s loop, with the primitives wrapped)."""
    by_name = {p.name: p for p in discover_pairs(args.data_root)}
    matcher = ExtraAffineMatcher(MatcherConfig.from_overrides(workers=0 if args.timeline else 1, **overrides))
    try:
        for name in [n.strip() for n in args.pairs.split(",")]:
            profile_one(by_name, name, matcher, args.timeline)
    finally:
        matcher.close()


def profile_one(by_name: dict[str, Any], name: str, matcher: ExtraAffineMatcher, timeline: bool) -> None:
    """Run pair `name` twice (the first warms up) and print the second run's profile."""
    if name not in by_name:
        raise SystemExit(f"no pair {name!r}; pairs: {', '.join(by_name)}")
    pair = by_name[name]
    img0, img1 = load_gray(pair.path0), load_gray(pair.path1)
    run_pair(pair, img0, img1, "extra-affine", matcher)
    CPU.clear()
    CALLS.clear()
    TIMELINE.clear()
    c0 = time.process_time()
    w0 = time.perf_counter()
    row = run_pair(pair, img0, img1, "extra-affine", matcher)
    cpu = time.process_time() - c0
    stages = ", ".join(f"{k} {v:.2f}" for k, v in row["timings"].items())
    print(f"{name}: path {row['path']}, {row['points']} points at {100 * row['precision']:.2f} %, "
          f"{cpu:.2f} CPU s; stages (wall s): {stages}")
    if timeline:
        for start, end, thread, what in sorted(TIMELINE):
            print(f"    {start - w0:.3f}-{end - w0:.3f} s ({end - start:.3f})  {thread:12s} {what}")
        return
    for k, v in sorted(CPU.items(), key=lambda kv: -kv[1]):
        print(f"    {k:28s} {v:6.3f} CPU s  {100 * v / cpu:5.1f} %  ({CALLS[k]} calls)")


if __name__ == "__main__":
    main()
