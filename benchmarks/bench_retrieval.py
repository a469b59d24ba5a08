"""Retrieval pair recall: how many of the pairs an exhaustive run verifies does `retrieval:K` propose?

    PYTHONPATH=. python benchmarks/bench_retrieval.py --truth /tmp/scale/stock --truth /tmp/scale/runs \
        --scene castle_P30=/work/shared/data/scenes/castle_P30 ... [--cache /tmp/scale/feats]

Ground truth ("exhaustive verified pairs"): the pairs with >= 15 verified inliers in any of the
databases found as TRUTH_ROOT/<scene>/database.db (COLMAP stock matching with the `high` preset,
`recon.eval.stock.run_stock(scene, out, preset="high")`, exhaustive; and `recon run` exhaustive
runs where available), united. Methods, each for K in --ks:

* `vlad`: `recon.core.retrieval` over the originals' SIFT only (the default `RetrievalConfig()`);
* `vlad+views`: originals pooled with two tilted views (t = 2, phi = 0 / 90 deg);
* `vocabtree`: COLMAP's `VocabTreePairGenerator` over a temporary database holding the same
  original SIFT descriptors, with a vocabulary tree built by `pycolmap.VisualIndex` from them
  (1024 words; `num_images` = K + 1, its self-match dropped).

`recall` is over every verified pair (>= 15 inliers), `recall_strong` over those with >= 100.
Seconds: `features` is the per-image SIFT (originals; + views for vlad+views) at the working
size `--max-size` (the pipeline's, 1600 px by default), computed once per scene through a
FeatureStore (disk-cached with --cache: a rerun reports only the cache reads); `rank` is
building the index (vocabulary and VLAD vectors, once per method) plus ranking for one K.
`--append` merges the rows into an existing JSON. Prints a table, writes
benchmarks/results/retrieval.json.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from matching.store import FeatureStore
from recon.core import retrieval as R
from recon.core.scene import scan_scene

MIN_INLIERS = 15
VIEWS = ((2.0, 0.0), (2.0, 90.0))  # the simulated views of `vlad+views`
STRONG_INLIERS = 100  # recall_strong: the share of pairs with at least this many inliers
DEFAULT_SCENES = {
    "castle_P30": "/work/shared/data/scenes/castle_P30",
    "fountain_P11": "/work/shared/data/scenes/fountain_P11",
    "sacre_coeur": "/work/shared/data/scenes/sacre_coeur",
    "facade-30x80": "/tmp/scale/scenes/facade-30x80",
}


def verified_pairs(db_path: Path, min_inliers: int = MIN_INLIERS) -> dict[tuple[str, str], int]:
    """{name pair (sorted): verified inliers} for pairs with at least `min_inliers` in a COLMAP database."""
    import pycolmap

    from recon.core.database import read_verified

    db = pycolmap.Database.open(str(db_path))
    try:
        names = {int(im.image_id): im.name for im in db.read_all_images()}
    finally:
        db.close()
    out: dict[tuple[str, str], int] = {}
    for (a, b), (n, _conf, _m) in read_verified(db_path).items():
        if n >= min_inliers and a in names and b in names:
            out[tuple(sorted((names[a], names[b])))] = int(n)  # type: ignore[index]
    return out


def vocabtree_pairs(names: list[str], image_dir: Path, descs: list[np.ndarray], k: int, seed: int = 0,
                    words: int = 1024) -> list[tuple[str, str]]:
    """COLMAP's vocabulary-tree retrieval with a tree built from the scene's own descriptors."""
    import pycolmap

    from recon.core.database import import_scene_images
    from recon.log import quiet_colmap

    sift = pycolmap.FeatureExtractorType.SIFT
    with tempfile.TemporaryDirectory() as tmp, quiet_colmap():
        d = Path(tmp)
        ids, _, _ = import_scene_images(d / "db.db", image_dir, names, "per-image")
        idx = pycolmap.VisualIndex.create(128, 64)
        bo = pycolmap.VisualIndex.BuildOptions()
        bo.num_visual_words, bo.num_iterations, bo.num_threads = words, 20, 1
        idx.build(bo, pycolmap.FeatureDescriptorsFloat(sift, np.concatenate(descs).astype(np.float32)))
        idx.write(str(d / "tree.bin"))
        db = pycolmap.Database.open(str(d / "db.db"))
        try:
            for n, de in zip(names, descs):
                kp = np.zeros((len(de), 6), np.float32)  # positions unused without spatial verification
                kp[:, 2] = kp[:, 5] = 1.0
                db.write_keypoints(ids[n], kp)
                db.write_descriptors(ids[n], pycolmap.FeatureDescriptors(sift, np.clip(de, 0, 255).astype(np.uint8)))
            o = pycolmap.VocabTreePairingOptions()
            o.vocab_tree_path, o.num_images, o.num_threads = str(d / "tree.bin"), k + 1, 1
            inv = {v: n for n, v in ids.items()}
            got = {tuple(sorted((inv[a], inv[b]))) for a, b in pycolmap.VocabTreePairGenerator(o, db).all_pairs()
                   if a != b}
        finally:
            db.close()
    order = {n: i for i, n in enumerate(names)}
    return sorted(got, key=lambda p: (order[p[0]], order[p[1]]))  # type: ignore[return-value]


def run_scene(name: str, scene_dir: Path, truth_roots: list[Path], ks: list[int], cache: Path | None,
              vocabtree: bool, max_size: int = 1600, log=print) -> list[dict]:
    inliers: dict[tuple[str, str], int] = {}  # pair -> most verified inliers over the sources
    sources = []
    for root in truth_roots:
        db = root / name / "database.db"
        if db.is_file():
            v = verified_pairs(db)
            sources.append({"database": str(db), "verified_pairs": len(v)})
            for p, n_in in v.items():
                inliers[p] = max(n_in, inliers.get(p, 0))
    truth = set(inliers)
    strong = {p for p, n_in in inliers.items() if n_in >= STRONG_INLIERS}
    scene, grays = scan_scene(scene_dir, max_size=max_size, workers=2)
    names = scene.names
    n = len(names)
    store = FeatureStore(cache_dir=None if cache is None else cache / name)
    for nm in names:
        store.add_image(nm, grays[nm])
    del grays
    rows = []
    base = {"scene": name, "N": n, "exhaustive_pairs": n * (n - 1) // 2, "verified_pairs": len(truth),
            "strong_pairs": len(strong), "truth_sources": sources, "max_size": max_size}
    cfg_views = R.RetrievalConfig(views=VIEWS)
    cfg_orig = R.RetrievalConfig(views=())
    t = time.perf_counter()
    d_orig = [R.image_descriptors(store, nm, cfg_orig) for nm in names]
    t_orig = time.perf_counter() - t
    t = time.perf_counter()
    d_views = [R.image_descriptors(store, nm, cfg_views) for nm in names]
    t_views = t_orig + time.perf_counter() - t
    methods = [("vlad", d_orig, cfg_orig, t_orig), ("vlad+views", d_views, cfg_views, t_views)]
    index = {}
    for mname, descs, cfg, _t in methods:  # the index (vocabulary + VLAD vectors) does not depend on K
        t = time.perf_counter()
        g = R.global_descriptors(descs, cfg)
        index[mname] = (g @ g.T, time.perf_counter() - t)
    for k in ks:
        for mname, _descs, _cfg, t_feat in methods:
            t = time.perf_counter()
            sim, t_index = index[mname]
            pairs = R.top_k_pairs(names, sim, k)
            rows.append({**base, "method": mname, "K": k, "proposed": len(pairs), "recall": R.pair_recall(pairs, truth),
                         "recall_strong": R.pair_recall(pairs, strong),
                         **_missed(truth, pairs),
                         "seconds_features": round(t_feat, 2),
                         "seconds_rank": round(t_index + time.perf_counter() - t, 2)})
            log(_row_line(rows[-1]))
        if vocabtree:
            t = time.perf_counter()
            pairs = vocabtree_pairs(names, scene.image_dir, d_orig, k)
            rows.append({**base, "method": "vocabtree", "K": k, "proposed": len(pairs),
                         "recall": R.pair_recall(pairs, truth), "recall_strong": R.pair_recall(pairs, strong),
                         **_missed(truth, pairs),
                         "seconds_features": round(t_orig, 2), "seconds_rank": round(time.perf_counter() - t, 2)})
            log(_row_line(rows[-1]))
    return rows


def _missed(truth: set[tuple[str, str]], pairs: list[tuple[str, str]], shown: int = 20) -> dict:
    """How many verified pairs retrieval missed, and the first `shown` of them."""
    missed = sorted(truth - {tuple(sorted(p)) for p in pairs})
    return {"missed_count": len(missed), "missed": missed[:shown]}


def _row_line(r: dict) -> str:
    return (f"{r['scene']:<14} {r['N']:>3} {r['exhaustive_pairs']:>5} {r['verified_pairs']:>5}  {r['method']:<11}"
            f" {r['K']:>3} {r['proposed']:>5} {100 * r['recall']:>6.1f} %"
            f" {r['strong_pairs']:>5} {100 * r['recall_strong']:>6.1f} %"
            f" {r['seconds_features']:>7.1f} {r['seconds_rank']:>6.2f}")


HEADER = (f"{'scene':<14} {'N':>3} {'exh.':>5} {'verif':>5}  {'method':<11} {'K':>3} {'prop.':>5} {'recall':>8}"
          f" {'>=100':>5} {'recall':>8} {'feat s':>7} {'rank s':>6}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", action="append", default=[], help="NAME=DIR (default: the four scenes of issue 10)")
    ap.add_argument("--truth", action="append", type=Path, default=[], help="root of NAME/database.db truth runs")
    ap.add_argument("--ks", default="3,5,8,10,15,20")
    ap.add_argument("--cache", type=Path, default=None, help="feature cache root (reused between runs)")
    ap.add_argument("--vocabtree", action="store_true", help="also COLMAP's vocabulary tree (slow; hung once)")
    ap.add_argument("--max-size", type=int, default=1600, help="working size of the features (px)")
    ap.add_argument("--append", action="store_true", help="keep other scenes' rows already in --out")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "retrieval.json")
    a = ap.parse_args()
    scenes = dict(s.split("=", 1) for s in a.scene) if a.scene else DEFAULT_SCENES
    ks = [int(k) for k in a.ks.split(",")]
    print(HEADER, flush=True)
    rows: list[dict] = []
    for name, d in scenes.items():
        rows += run_scene(name, Path(d), a.truth, ks, a.cache, a.vocabtree, a.max_size,
                          log=lambda s: print(s, flush=True))
    if a.append and a.out.is_file():
        old = json.loads(a.out.read_text()).get("rows", [])
        rows = [r for r in old if r["scene"] not in scenes] + rows
    a.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"min_inliers": MIN_INLIERS, "strong_inliers": STRONG_INLIERS, "truth_roots": [str(t) for t in a.truth], "ks": ks,
            "retrieval_config": repr(R.RetrievalConfig()), "views": VIEWS,
            "auto": {"exhaustive_max_images": R.AUTO_EXHAUSTIVE_MAX_IMAGES, "k": R.AUTO_K}}
    a.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"JSON: {a.out}")


if __name__ == "__main__":
    main()
