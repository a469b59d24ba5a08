"""Match-graph expansion: what `retrieval:K+expand:E` proposes, recalls and costs, against exhaustive.

    PYTHONPATH=. python benchmarks/bench_expansion.py \\
        --run castle_P30=OUT/runs/castle_P30/auto_threads-2 --run orbit-50=OUT/runs/orbit-50/exhaustive_threads-2 \\
        [--ks 5,10] [--es 0,3,5] [--out benchmarks/results/expansion.json]

Each `--run NAME=DIR` is a finished *exhaustive* `recon run` (every pair matched). Its
`report.json` holds, per pair, the matcher's match count (`raw_matches`), COLMAP's verified
inliers and the pair's matching seconds; its feature cache (`DIR/cache/features`) holds the
originals' SIFT that retrieval indexes. Because pair results are deterministic, the pairs a run
with `retrieval:K+expand:E` would match, and what each would return, are exactly these: the
benchmark replays the pipeline's own logic (`recon.core.retrieval.store_pairs`, then
`recon.core.expansion.expand` with the recorded match counts) without matching anything again.

Per scene, K and E (E = 0: retrieval alone): `proposed` pairs (retrieval + every expansion
round), `rounds`, `recall` = the share of the exhaustive run's verified pairs (>= 15 inliers)
proposed, `recall_strong` over those with >= 100, and `match_share` = the proposed pairs'
matching seconds over all pairs' (the match-stage cost relative to exhaustive, from the
recorded per-pair seconds). Prints a table, writes JSON (and a .txt copy of the table).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import recon  # noqa: F401  (cv2 before pycolmap)
from matching.store import FeatureStore
from recon.core.expansion import ExpansionConfig, expand
from recon.core.pairs import parse_pairs_spec
from recon.core.retrieval import pair_recall, store_pairs
from recon.core.scene import scan_scene

MIN_INLIERS = 15
STRONG_INLIERS = 100


def replay(name: str, run_dir: Path, ks: list[int], es: list[int], log=print) -> list[dict]:
    report = json.loads((run_dir / "report.json").read_text())
    n_img = int(report["num_images"])
    rows_by_pair = {tuple(sorted((p["image0"], p["image1"]))): p for p in report["pairs"]}
    if len(rows_by_pair) != n_img * (n_img - 1) // 2:
        raise SystemExit(f"{run_dir}: not an exhaustive run ({len(rows_by_pair)} pairs for {n_img} images)")
    truth = {p for p, r in rows_by_pair.items() if r["verified_inliers"] >= MIN_INLIERS}
    strong = {p for p, r in rows_by_pair.items() if r["verified_inliers"] >= STRONG_INLIERS}
    seconds_all = sum(float(r.get("seconds") or 0.0) for r in rows_by_pair.values())
    max_size = (report.get("config", {}).get("load", {}) or {}).get("max_size") or None
    scene, grays = scan_scene(Path(report["scene"]), max_size=max_size, workers=2)
    store = FeatureStore(cache_dir=run_dir / "cache" / "features")
    for nm in scene.names:
        store.add_image(nm, grays[nm])
    del grays
    names = scene.names
    order = {nm: i for i, nm in enumerate(names)}

    def key(p: tuple[str, str]) -> tuple[str, str]:
        return (p[0], p[1]) if order[p[0]] < order[p[1]] else (p[1], p[0])

    def counts(pairs: list[tuple[str, str]]) -> list[int]:
        return [int(rows_by_pair[tuple(sorted(p))]["raw_matches"]) for p in pairs]

    out = []
    for k in ks:
        base = store_pairs(parse_pairs_spec(f"retrieval:{k}"), store, names)
        for e in es:
            rounds = [] if e == 0 else expand(names, dict(zip(base, counts(base))), counts,
                                              ExpansionConfig(per_image=e))
            proposed = [key(p) for p in base] + [key(p) for r in rounds for p in r]
            secs = sum(float(rows_by_pair[tuple(sorted(p))].get("seconds") or 0.0) for p in proposed)
            row = {"scene": name, "N": n_img, "exhaustive_pairs": len(rows_by_pair), "verified_pairs": len(truth),
                   "strong_pairs": len(strong), "spec": f"retrieval:{k}" + (f"+expand:{e}" if e else ""),
                   "K": k, "E": e, "proposed": len(proposed), "rounds": [len(r) for r in rounds],
                   "recall": round(pair_recall(proposed, truth), 4),
                   "recall_strong": round(pair_recall(proposed, strong), 4),
                   "match_share": round(secs / seconds_all, 4) if seconds_all else None,
                   "bound": (k + e * ExpansionConfig(per_image=max(e, 1)).max_rounds) * n_img,
                   "run": str(run_dir)}
            out.append(row)
            log(line(row))
    return out


HEADER = (f"{'scene':<13} {'N':>3} {'all':>5} {'verif':>5} {'spec':<21} {'proposed':>8} {'rounds':<14} "
          f"{'recall':>7} {'>=100':>7} {'cost':>6}")


def line(r: dict) -> str:
    return (f"{r['scene']:<13} {r['N']:>3} {r['exhaustive_pairs']:>5} {r['verified_pairs']:>5} {r['spec']:<21} "
            f"{r['proposed']:>8} {'+'.join(map(str, r['rounds'])) or '-':<14} {100 * r['recall']:>6.1f}% "
            f"{100 * r['recall_strong']:>6.1f}% {100 * (r['match_share'] or 0):>5.1f}%")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", action="append", required=True, help="NAME=DIR of a finished exhaustive recon run")
    ap.add_argument("--ks", default="5,10")
    ap.add_argument("--es", default="0,3,5")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "expansion.json")
    a = ap.parse_args()
    ks = [int(v) for v in a.ks.split(",")]
    es = [int(v) for v in a.es.split(",")]
    print(HEADER, flush=True)
    rows: list[dict] = []
    for item in a.run:
        name, _, d = item.partition("=")
        rows += replay(name, Path(d), ks, es, log=lambda s: print(s, flush=True))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"command": "python benchmarks/bench_expansion.py " + " ".join(
        f"--run {r}" for r in a.run) + f" --ks {a.ks} --es {a.es}", "rows": rows}, indent=1))
    a.out.with_suffix(".txt").write_text("\n".join([HEADER, *map(line, rows)]) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
