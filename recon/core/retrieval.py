"""Retrieval pairs: for every image, its K most similar images by appearance (`--pairs retrieval:K`).

Matching every pair costs N(N-1)/2 matcher calls; real captures have hundreds of photos, of
which each overlaps only a few. Retrieval proposes at most K*N pairs (each image with its K
nearest neighbours in a global image descriptor, unordered pairs deduplicated), optionally united
with the K' next images in name order for video-like captures (`retrieval:K+sequential:K'`).
`auto` is exhaustive up to `AUTO_EXHAUSTIVE_MAX_IMAGES` images and `retrieval:AUTO_K` above.

The index is built offline from the scene's own features (no vocabulary download):

1. per image, SIFT descriptors of the original (the matcher's own `sift0@orig` FeatureStore
   entry, so the matching stage reuses them and retrieval costs no extra detection),
   optionally pooled with the SIFT of a few simulated tilted views (`RetrievalConfig.views`,
   the matcher's affine views, `matching.views`): appearance retrieval is weakest on exactly
   the extreme-viewpoint pairs this project exists for, and an image's tilted views look like
   the oblique photos of the same surface. Measured on the four scenes of issue 10, two t = 2
   views bought at most 2.4 points of recall for 2-4x the feature time: off by default;
2. RootSIFT (L1 normalise, square root), a seeded k-means vocabulary of `num_words` centres
   (plain numpy Lloyd iterations with k-means++ seeding, on at most `train_descriptors`
   descriptors sampled evenly from all images);
3. one VLAD vector per image (Jegou et al. 2010: residuals to the nearest centre, summed per
   centre, intra-normalised per centre, signed square root, L2-normalised: Arandjelovic and
   Zisserman 2013, "All about VLAD");
4. cosine similarity between all images (an N x N matrix: fine to many thousands of images),
   each image's K best other images, ties broken by name order.

Why not pycolmap's `VisualIndex` (4.2.1): `VisualIndex.query(options, descriptors, out_list)`
returns its scores through a C++ output vector that the binding does not copy back (the Python
list stays empty), so ranking needs `VocabTreePairGenerator` over a COLMAP database holding
every image's keypoints and descriptors; it is kept as a measured alternative in
`benchmarks/bench_retrieval.py`, not as the default.

Everything is deterministic for a fixed seed: sampling and k-means use a seeded generator,
distances are computed in float64, and ranking ties are broken by image order.
Output pairs are (name_i, name_j) with name_i before name_j in the scene's name order,
sorted by (i, j).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from matching.features import DetectorConfig
from matching.store import FeatureStore
from matching.types import ViewParams
from matching.viewfeatures import original_features, view_features
from matching.views import capped_view

Pair = tuple[str, str]

# `auto`: exhaustive for at most this many images, retrieval:AUTO_K above. Up to 20 images
# exhaustive matching is at most 190 pairs, no more than retrieval:10 proposes (up to 10·N), so
# retrieval would save nothing. Above, retrieval keeps only part of the pairs that verify (in the
# scenes measured here 80-100 % of all pairs overlap: castle_P30 47 % recall at K = 10, orbit-50
# 26 %; benchmarks/results/retrieval.json, expansion.json), yet the model is as good: the same
# registered images and rotation errors as exhaustive on castle_P30 (30/30, 0.446 deg against
# 0.454 deg), the rendered orbit-25 (25/25, 0.0326 / 0.0332 deg) and orbit-50 (50/50, 0.019 /
# 0.025 deg), and the rendered facade-30x80 30/30 at 0.0225 deg (stock `high`, exhaustive: 0.0292)
# for 38 % of castle's pairs (README, "Scale"). The weak pairs exhaustive adds do not improve the
# model; users who want them add match-graph expansion (`+expand:E`, recon.core.expansion).
AUTO_EXHAUSTIVE_MAX_IMAGES = 20
AUTO_K = 10


# specs ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RetrievalSpec:
    """A parsed `retrieval:K[+sequential:S]` or `auto` pair spec.

    `k`: nearest neighbours per image (>= 1); `sequential`: also pair each image with the next
    `sequential` images in name order (0 = none); `expand`: after matching, each image proposes
    up to `expand` more partners per round from the match graph (`recon.core.expansion`; 0 =
    none); `auto`: exhaustive for small scenes (see `AUTO_EXHAUSTIVE_MAX_IMAGES`), else
    retrieval with `k`.
    """

    k: int
    sequential: int = 0
    auto: bool = False
    expand: int = 0

    def __str__(self) -> str:
        if self.auto:
            return "auto"
        return (f"retrieval:{self.k}" + (f"+sequential:{self.sequential}" if self.sequential else "")
                + (f"+expand:{self.expand}" if self.expand else ""))


_TERM = re.compile(r"^(retrieval|sequential|expand):(\d+)$")


def as_retrieval_spec(spec: object) -> RetrievalSpec:
    """A RetrievalSpec from itself or from a `recon.core.pairs.PairsSpec` of kind retrieval / auto."""
    if isinstance(spec, RetrievalSpec):
        return spec
    kind = getattr(spec, "kind", None)
    if kind not in ("retrieval", "auto"):
        raise ValueError(f"--pairs {spec}: not a retrieval spec")
    return RetrievalSpec(k=int(getattr(spec, "k", 0)), sequential=int(getattr(spec, "sequential", 0)),
                         auto=kind == "auto", expand=int(getattr(spec, "expand", 0)))


def parse_retrieval_spec(spec: str) -> RetrievalSpec:
    """Parse `auto`, `retrieval:K`, `retrieval:K+sequential:S`, `retrieval:K+expand:E` or all
    three (in any order).

    Raises ValueError with a one-line message naming the accepted forms.
    """
    s = (spec or "").strip()
    if s == "auto":
        return RetrievalSpec(k=AUTO_K, auto=True)
    usage = ("expected retrieval:K, optionally +sequential:S and +expand:E, with integers K, S, E >= 1")
    terms: dict[str, int] = {}
    for term in s.split("+"):
        m = _TERM.match(term.strip())
        if m is None or m.group(1) in terms:
            raise ValueError(f"--pairs {spec!r}: {usage}")
        terms[m.group(1)] = int(m.group(2))
    if "retrieval" not in terms or any(v < 1 for v in terms.values()):
        raise ValueError(f"--pairs {spec!r}: {usage}")
    return RetrievalSpec(k=terms["retrieval"], sequential=terms.get("sequential", 0), expand=terms.get("expand", 0))


def is_retrieval_spec(spec: str) -> bool:
    """True for what `parse_retrieval_spec` handles: `auto`, `retrieval`, `retrieval:...`, or a
    `+`-joined list with a retrieval term (a pairs file such as `retrieval_pairs.txt` is not)."""
    s = (spec or "").strip()
    terms = [t.strip() for t in s.split("+")]
    return s == "auto" or any(t == "retrieval" or t.startswith("retrieval:") for t in terms)


# configuration ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RetrievalConfig:
    """How global image descriptors are built (see module doc)."""

    num_words: int = 64
    """VLAD centres (k-means clusters); the vector has num_words * 128 dimensions."""
    train_descriptors: int = 20000
    """At most this many descriptors (sampled evenly over images) train the k-means."""
    kmeans_iters: int = 15
    """Lloyd iterations after k-means++ seeding."""
    views: tuple[tuple[float, float], ...] = ()
    """Simulated views (tilt t, longitude phi in degrees) whose SIFT is pooled with the
    original's, e.g. ((2, 0), (2, 90)); () (default) indexes the originals only. Rendered like
    the matcher's fine views (Lanczos, anti-aliased, zoom capped to the original's area) so
    they share its cache. Measured (benchmarks/results/retrieval.json): two t = 2 views add
    0-2.4 points of recall for 2-4x the feature time, so they are off by default."""
    max_descriptors_per_image: int = 4000
    """Strongest descriptors kept per image and view (by detector response), bounding time."""
    seed: int = 0
    """Seeds descriptor sampling and k-means."""

    def __post_init__(self) -> None:
        if self.num_words < 2:
            raise ValueError("RetrievalConfig.num_words must be >= 2")
        if any(t < 1.0 for t, _ in self.views):
            raise ValueError("RetrievalConfig.views: tilts must be >= 1")


SIFT = DetectorConfig("sift", 0, False)  # the matcher's fine-stage detector: its cache entries are shared


def _strongest(desc: NDArray, resp: NDArray | None, n: int) -> NDArray:
    if n <= 0 or len(desc) <= n or resp is None:
        return desc
    keep = np.argsort(-resp, kind="stable")[:n]
    return desc[np.sort(keep)]


def image_descriptors(store: FeatureStore, name: str, cfg: RetrievalConfig = RetrievalConfig()
                      ) -> NDArray[np.float32]:
    """(M, 128) SIFT descriptors of image `name` and its simulated views, pooled (not normalised).

    Uses (and fills) the store's entries: the original's `sift0@orig` is the matcher's own.
    """
    f = original_features(store, name, SIFT)
    parts = [_strongest(f.descriptors, f.responses, cfg.max_descriptors_per_image)]
    h, w = store.image(name).shape[:2]
    for t, phi in cfg.views:
        v = capped_view(ViewParams(t=float(t), phi=float(phi), s=1.0 + 0.5 * round(math.log(t, math.sqrt(2)))),
                        (w, h), max_area_ratio=1.0)
        fv = view_features(store, name, v, SIFT, "lanczos", True)
        parts.append(_strongest(fv.descriptors, fv.responses, cfg.max_descriptors_per_image))
    return np.ascontiguousarray(np.concatenate(parts, axis=0).astype(np.float32, copy=False))


# global descriptors -----------------------------------------------------------------------------
def root_sift(desc: NDArray) -> NDArray[np.float64]:
    """RootSIFT: L1-normalise, element-wise square root (unit L2 norm), float64."""
    d = np.asarray(desc, np.float64)
    d = d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(np.maximum(d, 0.0))


def _sq_dists(x: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.maximum((x * x).sum(1)[:, None] - 2.0 * x @ c.T + (c * c).sum(1)[None, :], 0.0)


def _assign(x: NDArray[np.float64], c: NDArray[np.float64], chunk: int = 20000) -> NDArray[np.intp]:
    out = np.empty(len(x), np.intp)
    for i in range(0, len(x), chunk):
        out[i:i + chunk] = np.argmin(_sq_dists(x[i:i + chunk], c), axis=1)
    return out


def kmeans(x: NDArray[np.float64], k: int, iters: int, seed: int) -> NDArray[np.float64]:
    """(k, D) centres of `x` by k-means++ seeding and `iters` Lloyd steps (seeded, deterministic).

    An empty cluster is re-seeded with the point farthest from its centre.
    """
    rng = np.random.default_rng(seed)
    k = min(k, len(x))
    centres = np.empty((k, x.shape[1]), np.float64)
    centres[0] = x[rng.integers(len(x))]
    d2 = _sq_dists(x, centres[:1])[:, 0]
    for j in range(1, k):
        p = d2 / d2.sum() if d2.sum() > 0 else None
        centres[j] = x[rng.choice(len(x), p=p)]
        d2 = np.minimum(d2, _sq_dists(x, centres[j:j + 1])[:, 0])
    for _ in range(iters):
        lab = _assign(x, centres)
        counts = np.bincount(lab, minlength=k)
        sums = np.zeros_like(centres)
        np.add.at(sums, lab, x)
        new = sums / np.maximum(counts, 1)[:, None]
        empty = np.flatnonzero(counts == 0)
        if len(empty):
            far = np.argsort(-((x - new[lab]) ** 2).sum(1), kind="stable")[:len(empty)]
            new[empty] = x[far]
        if np.allclose(new, centres, atol=1e-10):
            centres = new
            break
        centres = new
    return centres


def vocabulary(descs: Sequence[NDArray], cfg: RetrievalConfig = RetrievalConfig()) -> NDArray[np.float64]:
    """k-means centres over RootSIFT descriptors sampled evenly from every image (seeded)."""
    rng = np.random.default_rng(cfg.seed)
    per = max(1, cfg.train_descriptors // max(1, len(descs)))
    sample = []
    for d in descs:
        if len(d) > per:
            d = d[np.sort(rng.choice(len(d), per, replace=False))]
        sample.append(root_sift(d))
    x = np.concatenate(sample, axis=0) if sample else np.zeros((0, 128))
    if len(x) < 2:
        raise ValueError("retrieval: too few descriptors to build a vocabulary")
    return kmeans(x, cfg.num_words, cfg.kmeans_iters, cfg.seed)


def vlad(desc: NDArray, centres: NDArray[np.float64]) -> NDArray[np.float64]:
    """The VLAD vector (K*D,) of one image: intra-normalised, signed-sqrt, L2-normalised."""
    k, dim = centres.shape
    v = np.zeros((k, dim), np.float64)
    if len(desc):
        x = root_sift(desc)
        lab = _assign(x, centres)
        np.add.at(v, lab, x - centres[lab])
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    flat = v.ravel()
    flat = np.sign(flat) * np.sqrt(np.abs(flat))
    return flat / max(float(np.linalg.norm(flat)), 1e-12)


def global_descriptors(descs: Sequence[NDArray], cfg: RetrievalConfig = RetrievalConfig()) -> NDArray[np.float64]:
    """(N, num_words*128) unit VLAD vectors of the images, from a vocabulary of their own descriptors."""
    centres = vocabulary(descs, cfg)
    return np.stack([vlad(d, centres) for d in descs]) if len(descs) else np.zeros((0, centres.size))


# pairs ------------------------------------------------------------------------------------------
def top_k_pairs(names: Sequence[str], similarity: NDArray[np.float64], k: int) -> list[Pair]:
    """Each image with its `k` most similar other images; unordered pairs, i < j, sorted.

    `similarity[i, j]` is any score where larger means more alike (need not be symmetric:
    row i ranks the candidates of image i). Ties are broken by image order (stable sort).
    """
    n = len(names)
    if similarity.shape != (n, n):
        raise ValueError(f"similarity is {similarity.shape}, expected ({n}, {n})")
    keys: set[tuple[int, int]] = set()
    for i in range(n):
        row = -np.asarray(similarity[i], np.float64).copy()
        row[i] = np.inf  # never the image itself
        for j in np.argsort(row, kind="stable")[:min(k, n - 1)]:
            keys.add((min(i, int(j)), max(i, int(j))))
    return [(names[i], names[j]) for i, j in sorted(keys)]


def sequential_keys(n: int, s: int) -> set[tuple[int, int]]:
    return {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + s))}


def retrieval_pairs(names: Sequence[str], descs: Sequence[NDArray], k: int, sequential: int = 0,
                    cfg: RetrievalConfig = RetrievalConfig()) -> list[Pair]:
    """The retrieval pairs of images `names` (scene name order) with SIFT descriptors `descs`.

    `descs[i]`: (M_i, 128) float SIFT descriptors of image i (e.g. `image_descriptors`).
    Returns at most k*N + sequential*N pairs (name_i, name_j), i < j in `names` order, sorted.
    """
    if len(names) != len(descs):
        raise ValueError(f"retrieval: {len(names)} names but {len(descs)} descriptor arrays")
    if k < 1:
        raise ValueError(f"retrieval: k must be >= 1, got {k}")
    names = list(names)
    g = global_descriptors(descs, cfg)
    pairs = top_k_pairs(names, g @ g.T, k)
    if sequential > 0:
        index = {n: i for i, n in enumerate(names)}
        keys = {(index[a], index[b]) for a, b in pairs} | sequential_keys(len(names), sequential)
        pairs = [(names[i], names[j]) for i, j in sorted(keys)]
    return pairs


def pairs_for_spec(spec: object, names: Sequence[str], descriptors_of: Callable[[str], NDArray],
                   cfg: RetrievalConfig = RetrievalConfig()) -> list[Pair]:
    """Pairs for a parsed retrieval / auto spec; `descriptors_of(name)` is only called when needed.

    `spec`: a RetrievalSpec or a `pairs.PairsSpec` of kind retrieval / auto. `auto` gives every
    pair for at most `AUTO_EXHAUSTIVE_MAX_IMAGES` images.
    """
    spec = as_retrieval_spec(spec)
    names = list(names)
    if spec.auto and len(names) <= AUTO_EXHAUSTIVE_MAX_IMAGES:
        return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names))]
    return retrieval_pairs(names, [descriptors_of(n) for n in names], spec.k, spec.sequential, cfg)


def store_pairs(spec: object, store: FeatureStore, names: Sequence[str],
                cfg: RetrievalConfig = RetrievalConfig()) -> list[Pair]:
    """`pairs_for_spec` with descriptors from a FeatureStore holding every image (working resolution)."""
    return pairs_for_spec(spec, names, lambda n: image_descriptors(store, n, cfg), cfg)


def pair_recall(proposed: Sequence[Pair], truth: Sequence[Pair] | Mapping[Pair, object]) -> float:
    """Share of `truth` pairs (unordered) that `proposed` contains; 1.0 for an empty truth."""
    got = {frozenset(p) for p in proposed}
    want = {frozenset(p) for p in truth}
    return 1.0 if not want else len(want & got) / len(want)
