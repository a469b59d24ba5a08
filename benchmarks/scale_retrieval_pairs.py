"""Retrieval pairs of rendered orbit scenes without matching: how many, and how far apart.

    PYTHONPATH=. python benchmarks/scale_retrieval_pairs.py OUT/scenes/orbit-25 OUT/scenes/orbit-200 [--k 10]

For each `orbit-N` scene folder (rendered by `recon bench scale` or `recon render-scene --preset
orbit-N`), computes `retrieval:K` pairs exactly as `recon run` does (`recon.core.retrieval.
store_pairs`, features in a temporary FeatureStore; `--cache DIR` reuses one) and prints the number
of pairs against the (K+1)*N bound, the largest gap in steps around the circle between the two
views of a proposed pair, the share within 5 steps, and the share of 1-step neighbours proposed.
The run's own count can differ by a pair or two (`recon run` decodes the photos through its loader).
Writes the rows as JSON with `--json`.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2

from matching.store import FeatureStore
from recon.core.retrieval import parse_retrieval_spec, store_pairs


def orbit_pairs(scene: Path, k: int, cache: Path) -> dict:
    t = time.perf_counter()
    names = sorted(p.name for p in (scene / "images").iterdir())
    n = len(names)
    store = FeatureStore(cache)
    for nm in names:
        store.add_image(nm, cv2.imread(str(scene / "images" / nm), cv2.IMREAD_GRAYSCALE))
    pairs = store_pairs(parse_retrieval_spec(f"retrieval:{k}"), store, names)
    idx = {nm: i for i, nm in enumerate(names)}
    gaps = [min((idx[b] - idx[a]) % n, (idx[a] - idx[b]) % n) for a, b in pairs]
    return {"scene": scene.name, "num_images": n, "k": k, "pairs": len(pairs), "bound_k_plus_1_n": (k + 1) * n,
            "max_step_gap": max(gaps), "share_within_5_steps": round(sum(g <= 5 for g in gaps) / len(gaps), 3),
            "one_step_neighbours_proposed": round(sum(g == 1 for g in gaps) / n, 3),
            "seconds": round(time.perf_counter() - t, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--cache", type=Path, default=None, help="FeatureStore cache folder (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in a.scenes:
            rows.append(orbit_pairs(scene, a.k, a.cache or Path(tmp) / scene.name))
            print(json.dumps(rows[-1]), flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
