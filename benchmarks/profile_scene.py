"""Where a finished `recon run` spent its time: the stages, and inside the match stage the
matcher's own per-pair stages summed over the run's pairs.

    PYTHONPATH=. python benchmarks/profile_scene.py OUT [--json FILE]

OUT is a `recon run` output folder (its `report.json` and its pair cache, `OUT/cache/pairs`,
kept by default). Stage seconds are the report's wall-clock seconds; the pair stages are the
matcher's own timings (`PairResult.timings`, wall seconds measured inside each pair task), summed
over the pairs computed in that run. With several pair threads they overlap, so their sum
exceeds the match stage's wall time; the shares say where the pair threads spent theirs. Nested
stages are listed under their parent and not counted twice: the matcher's `refine` runs inside
its `ransac` (the finishing steps), whose own share is given without it. The first pair of each
image also pays that image's feature extraction (COLMAP's covariant SIFT of the original under
the default matcher), inside `fine` (or `originals`).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path
from typing import Any

from recon.core.paircache import load_pair_result
from recon.core.report import read_report

NESTED = {"refine": "ransac"}
"""Matcher stages timed inside another one (child: parent)."""
LEVEL_PREFIX = "level:"
"""The escalation levels' own timings (`matching.strategies.escalate`), inside "escalation"."""


def pair_stage_seconds(pair_dir: Path) -> tuple[dict[str, float], int]:
    """({stage: seconds summed over the cached pair results}, number of pairs read); each parent
    stage of `NESTED` without its nested children."""
    total: collections.Counter[str] = collections.Counter()
    n = 0
    for path in sorted(pair_dir.glob("*.npz")):
        r = load_pair_result(path)
        if r is None:
            continue
        n += 1
        for k, v in r.timings.items():
            total[k] += float(v)
    for child, parent in NESTED.items():
        if child in total and parent in total:
            total[parent] -= total[child]
    for child in [k for k in total if k.startswith(LEVEL_PREFIX)]:  # each escalation level, inside "escalation"
        if "escalation" in total:
            total["escalation"] -= total[child]
    return dict(total), n


def profile(out: Path) -> dict[str, Any]:
    """The run's stage seconds and its pairs' summed matcher stages (module doc)."""
    rep = read_report(out / "report.json")
    pairs, n = pair_stage_seconds(out / "cache" / "pairs")
    return {"out": str(out), "seconds_total": rep.seconds_total, "stages": dict(rep.stages),
            "pairs_read": n, "pairs_computed": rep.pairs_computed, "pair_stages": pairs}


def table(p: dict[str, Any]) -> str:
    lines = [f"{p['out']}: {p['seconds_total']:.1f} s in total"]
    for k, v in p["stages"].items():
        lines.append(f"  stage {k:<10} {v:8.1f} s  {100 * v / max(p['seconds_total'], 1e-9):5.1f} %")
    pt = p["pair_stages"]
    summed = pt.get("total", sum(v for k, v in pt.items() if k != "total"))
    lines.append(f"  matcher stages over {p['pairs_read']} pairs ({p['pairs_computed']} computed in the run), "
                 f"{summed:.1f} pair-thread s:")
    for k, v in sorted(((k, v) for k, v in pt.items() if k != "total"), key=lambda kv: -kv[1]):
        inner = f" (without {', '.join(c for c, par in NESTED.items() if par == k)})" if k in NESTED.values() else ""
        lines.append(f"    {k:<12} {v:8.1f} s  {100 * v / max(summed, 1e-9):5.1f} %{inner}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="a recon run output folder")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if not (args.out / "report.json").is_file():
        print(f"profile_scene: {args.out}: no report.json (not a finished recon run output)", file=sys.stderr)
        return 2
    p = profile(args.out)
    print(table(p))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(p, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
