"""Turn per-pair matches into per-image keypoints that form multi-view tracks.

A pair matcher returns keypoints *per pair*: the extra-affine matcher finds its keypoints in
simulated views of one image, mapped back to original pixels, so the "same" corner of image B
comes out at slightly different sub-pixel positions in pair (A, B) and in pair (B, C), and with
a different index. Written to COLMAP as they are, every keypoint would be seen in exactly two
images: every track would have length 2, and incremental SfM could not register a third image
through 2D-3D correspondences (and the triangulator ignores two-view tracks by default).

`merge_tracks` therefore merges, per image, the keypoints of all its pairs that lie within
`radius` pixels of each other into one keypoint (the same idea as hloc's `match_dense.py`, which
quantises dense-matcher keypoints to a grid of `cell_size` px and keeps the most common position
per cell). We use radius ("leader") clustering instead of a fixed grid, so two observations
0.1 px apart never fall into different cells just because a cell border passes between them:

1. collect the matched keypoints of every pair the image is in (unmatched ones are useless);
2. collapse exact repeats (the SIFT baseline detects once per image, so its keypoints are
   identical across pairs) and count how often each position was seen;
3. visit positions from the most to the least often seen; each joins the nearest existing
   cluster leader within `radius`, or becomes a new leader (neighbours from scipy's KD-tree,
   decided in vectorised rounds: `_leader_cluster`); a cluster's diameter is thus at most
   2 * radius;
4. a merged keypoint is the count-weighted mean of its cluster.

Each pair's matches are then rewritten as index pairs into the merged keypoints. Merging can map
two matches onto the same (i0, i1) (duplicates: dropped) or one merged keypoint onto several
partners in the other image (many-to-one collisions): we keep a one-to-one subset greedily by
ascending descriptor distance (hloc's `get_unique_matches` does the same by score).

Merging alone does not make tracks consistent: the extra-affine matcher finds one physical point
3-8 px apart in different pairs (beyond the radius), and wrong or repeated matches chain such
clusters, so a connected component can hold several keypoints of one image (on castle_P30, 30
photos: 84 % of the observations). `consistent_tracks` then drops the matches that would do so,
most trusted first (`epipolar_inliers`: the pair's fundamental matrix), see its doc.

`radius <= 0` disables merging: every pair gets its own copies of its keypoints, which is what
the matcher alone gives (all tracks have length 2). `track_stats` measures the track lengths of a
match graph (connected components over (image, keypoint) nodes, scipy's csgraph), so the report
can give the mean track length with merging against the unmerged 2.0 without running SfM twice.

Speed (scipy against the former pure-Python loops, identical outputs): on a 30-image-like input
(435 pairs x 1500 matches, 1.3 M observations) the clustering takes 3.1-3.9 s instead of
9.4-12.0 s and `merge_tracks` 7.2-8.0 s instead of 12.9-15.6 s (2 shared cores); the components
of its 254577-node graph take 0.16 s instead of 0.25 s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass
class PairMatches:
    """One pair's matcher output in full-resolution pixels (OpenCV convention)."""

    name0: str
    name1: str
    kpts0: NDArray[np.float32]  # (N0, 2)
    kpts1: NDArray[np.float32]  # (N1, 2)
    matches: NDArray[np.int64]  # (K, 2) indices into kpts0 / kpts1
    distances: NDArray[np.float32] | None = None  # (K,) descriptor distances (lower = better)


@dataclass
class MergeStats:
    num_input_matches: int = 0
    num_output_matches: int = 0
    dropped_duplicates: int = 0  # matches that became an already present (i0, i1)
    dropped_collisions: int = 0  # many-to-one after merging (kept: the lowest distance)
    num_observations: int = 0  # matched keypoint occurrences over all pairs, before merging
    num_keypoints: int = 0  # merged keypoints over all images
    dropped_conflicts: int = 0  # matches that would put two keypoints of one image in a track

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class MergedTracks:
    """Per-image merged keypoints and, per input pair (same order), matches into them."""

    keypoints: dict[str, NDArray[np.float32]]  # (N, 2), full-res OpenCV pixels
    matches: list[NDArray[np.uint32]]  # (M, 2) per input pair
    pairs: list[tuple[str, str]]
    stats: MergeStats = field(default_factory=MergeStats)
    distances: list[NDArray[np.float32]] = field(default_factory=list)  # (M,) per pair, with `matches`


_MAX_ROUNDS = 64  # vectorised rounds of `_leader_cluster` before the rest is visited one by one


def _leader_cluster(pts: NDArray[np.float64], counts: NDArray[np.int64], radius: float) -> NDArray[np.int64]:
    """Cluster id of each point: greedy leader clustering, most-seen points first (deterministic).

    Visiting points by count (desc), then first appearance, each joins the nearest leader within
    `radius` (ties: the earliest leader) or becomes a leader; ids number the leaders in visit
    order. Every leader is a point, so only neighbours within `radius` matter; scipy's KD-tree
    (`cKDTree.query_pairs`) finds them all at once. A point is a leader exactly when no earlier
    neighbour is one (the lexicographically first maximal independent set of the neighbour
    graph), which is decided in vectorised rounds: a point with an earlier leader neighbour
    follows, a point whose earlier neighbours are all decided followers leads. Squared distances
    are dx*dx + dy*dy in float64 compared with radius^2, as the former grid-hash loop computed
    them, so clusters and merged keypoints are identical to it (checked with np.array_equal on
    real runs).
    """
    from scipy.spatial import cKDTree

    n = len(pts)
    if n == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((np.arange(n), -counts))  # by count desc, then by first appearance
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    r2 = radius * radius
    # neighbour pairs (radius widened a hair so the exact test below decides the borderline),
    # each directed from the earlier-visited point u to the later one v
    pairs = cKDTree(pts).query_pairs(radius * (1.0 + 1e-6), output_type="ndarray").reshape(-1, 2)
    diff = pts[pairs[:, 0]] - pts[pairs[:, 1]]
    d2 = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]
    keep = d2 <= r2
    pairs, d2 = pairs[keep], d2[keep]
    first = rank[pairs[:, 0]] < rank[pairs[:, 1]]
    u = np.where(first, pairs[:, 0], pairs[:, 1])
    v = np.where(first, pairs[:, 1], pairs[:, 0])

    UNDECIDED, LEADER, FOLLOWER = 0, 1, 2
    state = np.zeros(n, np.int8)
    for _ in range(_MAX_ROUNDS):
        open_ = state == UNDECIDED
        if not open_.any():
            break
        su = state[u]
        has_leader = np.zeros(n, bool)
        has_leader[v[su == LEADER]] = True
        blocked = np.zeros(n, bool)
        blocked[v[su == UNDECIDED]] = True
        state[open_ & has_leader] = FOLLOWER
        state[open_ & ~has_leader & ~blocked] = LEADER
    rest = order[state[order] == UNDECIDED]
    if len(rest):  # long chains of neighbours: finish in visit order
        by_v = np.argsort(v, kind="stable")
        starts = np.searchsorted(v[by_v], np.arange(n + 1))
        for i in rest.tolist():
            earlier = u[by_v[starts[i]:starts[i + 1]]]
            state[i] = FOLLOWER if np.any(state[earlier] == LEADER) else LEADER

    # each follower joins its nearest earlier leader (ties: the earliest)
    leader = np.arange(n, dtype=np.int64)
    cand = (state[u] == LEADER) & (state[v] == FOLLOWER)
    cu, cv, cd = u[cand], v[cand], d2[cand]
    best = np.lexsort((rank[cu], cd, cv))
    cv_sorted = cv[best]
    head = np.ones(len(best), bool)
    head[1:] = cv_sorted[1:] != cv_sorted[:-1]
    leader[cv_sorted[head]] = cu[best][head]
    # leader ids in visit order
    lid = np.full(n, -1, np.int64)
    lead_in_order = order[state[order] != FOLLOWER]
    lid[lead_in_order] = np.arange(len(lead_in_order))
    return lid[leader]


def _one_to_one(m: NDArray[np.int64], dist: NDArray[np.float32]) -> tuple[NDArray[np.int64], int, int]:
    """Unique one-to-one subset of merged matches: (kept row indices, n_duplicates, n_collisions)."""
    if len(m) == 0:
        return np.zeros(0, np.int64), 0, 0
    order = np.lexsort((np.arange(len(m)), dist))  # best (lowest distance) first, stable
    used0: set[int] = set()
    used1: set[int] = set()
    seen: set[tuple[int, int]] = set()
    keep = []
    dup = col = 0
    for k in order.tolist():
        a, b = int(m[k, 0]), int(m[k, 1])
        if (a, b) in seen:
            dup += 1
            continue
        seen.add((a, b))
        if a in used0 or b in used1:
            col += 1
            continue
        used0.add(a)
        used1.add(b)
        keep.append(k)
    keep.sort()  # keep the matcher's order
    return np.asarray(keep, np.int64), dup, col


def merge_tracks(pairs: Sequence[PairMatches], radius: float | Mapping[str, float]) -> MergedTracks:
    """Merge the keypoints of all pairs per image (see module doc); `radius` in full-res px,
    one value or one per image name. `radius <= 0` keeps every pair's keypoints separate."""
    names: list[str] = []
    for p in pairs:
        for n in (p.name0, p.name1):
            if n not in names:
                names.append(n)

    def rad(name: str) -> float:
        return float(radius.get(name, 0.0)) if isinstance(radius, Mapping) else float(radius)

    # observations per image: (pair index, side, keypoint indices used, their coordinates)
    obs: dict[str, list[tuple[int, int, NDArray[np.int64], NDArray[np.float32]]]] = {n: [] for n in names}
    stats = MergeStats()
    for pi, p in enumerate(pairs):
        m = np.asarray(p.matches, np.int64).reshape(-1, 2)
        stats.num_input_matches += len(m)
        for side, (name, kp) in enumerate(((p.name0, p.kpts0), (p.name1, p.kpts1))):
            used = np.unique(m[:, side]) if len(m) else np.zeros(0, np.int64)
            obs[name].append((pi, side, used, np.asarray(kp, np.float32).reshape(-1, 2)[used]))
            stats.num_observations += len(used)

    # per image: merged keypoints, and a lookup (pair, side) -> (kp index -> merged id)
    keypoints: dict[str, NDArray[np.float32]] = {}
    lookup: dict[tuple[int, int], tuple[NDArray[np.int64], NDArray[np.int64]]] = {}
    for name in names:
        entries = obs[name]
        if not entries:
            keypoints[name] = np.zeros((0, 2), np.float32)
            continue
        coords = np.concatenate([e[3] for e in entries]).astype(np.float64)
        r = rad(name)
        if r <= 0 or len(coords) == 0:
            ids = np.arange(len(coords), dtype=np.int64)
            merged = coords
        else:
            q = np.round(coords * 1000.0).astype(np.int64)  # exact repeats (to 1e-3 px)
            _, first, inv, counts = np.unique(q, axis=0, return_index=True, return_inverse=True,
                                              return_counts=True)
            inv = inv.reshape(-1)
            # unique rows in order of first appearance, so ids do not depend on np.unique's sort
            by_first = np.argsort(first, kind="stable")
            rank = np.empty_like(by_first)
            rank[by_first] = np.arange(len(by_first))
            upts = coords[first[by_first]]
            ucnt = counts[by_first]
            lab = _leader_cluster(upts, ucnt, r)
            nclu = int(lab.max()) + 1 if len(lab) else 0
            w = ucnt.astype(np.float64)
            sx = np.bincount(lab, weights=w * upts[:, 0], minlength=nclu)
            sy = np.bincount(lab, weights=w * upts[:, 1], minlength=nclu)
            sw = np.bincount(lab, weights=w, minlength=nclu)
            merged = np.stack([sx / sw, sy / sw], axis=1)
            ids = lab[rank[inv]]
        keypoints[name] = merged.astype(np.float32)
        off = 0
        for pi, side, used, _ in entries:
            lookup[(pi, side)] = (used, ids[off:off + len(used)])
            off += len(used)

    out_matches: list[NDArray[np.uint32]] = []
    out_dist: list[NDArray[np.float32]] = []
    for pi, p in enumerate(pairs):
        m = np.asarray(p.matches, np.int64).reshape(-1, 2)
        if len(m) == 0:
            out_matches.append(np.zeros((0, 2), np.uint32))
            out_dist.append(np.zeros(0, np.float32))
            continue
        cols = []
        for side in (0, 1):
            used, ids = lookup[(pi, side)]
            cols.append(ids[np.searchsorted(used, m[:, side])])
        mm = np.stack(cols, axis=1)
        dist = (np.asarray(p.distances, np.float32).reshape(-1) if p.distances is not None
                and len(p.distances) == len(m) else np.zeros(len(m), np.float32))
        kept, dup, col = _one_to_one(mm, dist)
        stats.dropped_duplicates += dup
        stats.dropped_collisions += col
        stats.num_output_matches += len(kept)
        out_matches.append(np.ascontiguousarray(mm[kept].astype(np.uint32)))
        out_dist.append(np.ascontiguousarray(dist[kept]))
    stats.num_keypoints = int(sum(len(k) for k in keypoints.values()))
    return MergedTracks(keypoints, out_matches, [(p.name0, p.name1) for p in pairs], stats, out_dist)


def epipolar_inliers(merged: MergedTracks, max_error_px: float, seed: int = 0) -> list[NDArray[np.bool_]]:
    """Per pair, which merged matches fit a fundamental matrix fitted to the pair's matches
    (OpenCV RANSAC, `max_error_px` full-resolution px from the epipolar lines, seeded): the
    order of trust `consistent_tracks` follows. A pair with fewer than 8 matches or no F fitted
    gets none. This is a cheap stand-in for COLMAP's own verification, which runs later."""
    import cv2

    out: list[NDArray[np.bool_]] = []
    for (a, b), m in zip(merged.pairs, merged.matches, strict=True):
        mask = np.zeros(len(m), bool)
        if len(m) >= 8:
            cv2.setRNGSeed(int(seed))
            F, inl = cv2.findFundamentalMat(merged.keypoints[a][m[:, 0]], merged.keypoints[b][m[:, 1]],
                                            cv2.FM_RANSAC, float(max_error_px), 0.999, 2000)
            if F is not None and inl is not None and len(inl) == len(m):
                mask = inl.ravel().astype(bool)
        out.append(mask)
    return out


@dataclass
class MatchGraph:
    """`MergedTracks` as one graph: node = (image, merged keypoint), numbered image by image in
    `keypoints` order (image i's keypoint k is node `offset[i] + k`); edge = one match, pair by
    pair in order (`pair_of`, `row`: its pair and its row in that pair's matches)."""

    names: list[str]
    offset: NDArray[np.int64]  # (num_images + 1,)
    u: NDArray[np.int64]  # (E,) node of each match's image-0 side
    v: NDArray[np.int64]  # (E,) node of its image-1 side
    pair_of: NDArray[np.int64]  # (E,)
    row: NDArray[np.int64]  # (E,)

    @property
    def num_nodes(self) -> int:
        return int(self.offset[-1])


def match_graph(merged: MergedTracks) -> MatchGraph:
    """The match graph of `merged` (`MatchGraph`)."""
    names = list(merged.keypoints)
    index = {n: i for i, n in enumerate(names)}
    sizes = [len(merged.keypoints[n]) for n in names]
    offset = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    counts = [len(m) for m in merged.matches]
    empty = np.zeros(0, np.int64)
    pair_of = np.repeat(np.arange(len(counts), dtype=np.int64), counts)
    row = np.concatenate([np.arange(c, dtype=np.int64) for c in counts]) if counts else empty
    u = np.concatenate([np.asarray(m[:, 0], np.int64) + offset[index[a]]
                        for (a, _), m in zip(merged.pairs, merged.matches)]) if counts else empty
    v = np.concatenate([np.asarray(m[:, 1], np.int64) + offset[index[b]]
                        for (_, b), m in zip(merged.pairs, merged.matches)]) if counts else empty
    return MatchGraph(names, offset, u, v, pair_of, row)


CONFLICT_ORDERS = ("pairs", "distance", "support")
"""`consistent_tracks`' orders of trust among the trusted (and then the other) matches."""


def triangle_support(graph: MatchGraph) -> NDArray[np.int64]:
    """Per match of `graph`, the number of keypoints (of third images) matched to both of its
    keypoints: the triangles the match closes in the match graph, (A A)[u, v] for the symmetric
    adjacency A (scipy sparse product; degrees are at most the number of images, so it is cheap).

    Why: a right match is usually seen again through a third image (u-w and v-w both matched),
    a wrong one that merely fits one pair's epipolar band rarely is. On the difficulty curve's
    13-view facade (79059 merged matches, checked against the rendered truth) 70 % of the matches
    closing no triangle are right, 93 % of those closing one, 98 % of those closing three and
    99.6-100 % of those closing five or more."""
    from scipy.sparse import coo_matrix

    n, e = graph.num_nodes, len(graph.u)
    if e == 0:
        return np.zeros(0, np.int64)
    adj = coo_matrix((np.ones(2 * e, np.int32), (np.r_[graph.u, graph.v], np.r_[graph.v, graph.u])),
                     shape=(n, n)).tocsr()
    adj.data[:] = 1  # a repeated match counts once
    two_step = (adj @ adj).tocsr()
    return np.asarray(two_step[graph.u, graph.v], np.int64).reshape(-1)


def consistent_tracks(merged: MergedTracks, trusted: Sequence[NDArray[np.bool_]] | None = None,
                      order_by: str = "support") -> MergedTracks:
    """The same merged keypoints with the matches that would put two keypoints of one image into
    one track dropped, so every track (connected component) holds at most one keypoint per image.

    Why: a track is one 3D point, seen once per image. Keypoints of one physical point found 3-8
    working px apart in different pairs (beyond the merge radius), a wrong match or a repeated
    pattern chain distinct keypoints of an image into one component; on castle_P30 (30 photos,
    exhaustive) 84 % of the match graph's observations sat in such tracks, one of them 57864
    nodes long (COLMAP then splits or trims them while triangulating). Matches are added to
    tracks greedily in the order of trust, a union-find whose components remember their images
    (Kruskal-like, as OpenMVG's and Theia's track builders check each union): `trusted` matches
    (e.g. `epipolar_inliers`) first, then, with `order_by` "support", descending
    `triangle_support` over all pairs and ascending descriptor distance among equals; with
    "pairs", pairs with more trusted matches before pairs with fewer and ascending descriptor
    distance within a pair; with "distance", ascending descriptor distance over all pairs. A
    match joining two components that share an image is dropped (counted in
    `stats.dropped_conflicts`). A match inside one component is kept (it adds no keypoint).
    Deterministic; COLMAP's verification afterwards can only remove matches, so the verified
    graph stays consistent too.

    Why "support": pair by pair, the narrow pairs (more matches) settle every track first, with
    their few wrong matches that happen to fit the epipolar geometry, and a wide pair's right
    matches that meet those tracks are dropped (on the difficulty curve's 13-view facade 87 % of
    what the check dropped from the widest pair was right against the rendered ground truth). A
    match that third images confirm is almost always right (`triangle_support`), so admitting the
    confirmed ones first settles the tracks on them: on that facade 66234 right and 5410 wrong
    matches kept against 64691 and 5430 pair by pair (by distance: 65666 and 5166, but higher
    rotation errors), and castle_P30's rotation error 0.4406 -> 0.4361° (docs/decisions.md,
    "Conflict order").
    """
    if order_by not in CONFLICT_ORDERS:
        raise ValueError(f"order_by {order_by!r}: one of {', '.join(CONFLICT_ORDERS)}")
    names = list(merged.keypoints)
    sizes = [len(merged.keypoints[n]) for n in names]
    image_of = np.repeat(np.arange(len(names), dtype=np.int64), sizes)
    n_pairs = len(merged.matches)
    counts = np.array([len(m) for m in merged.matches], np.int64)
    if counts.sum() == 0:
        return merged
    g = match_graph(merged)
    offset, pair_of, row, u, v = g.offset, g.pair_of, g.row, g.u, g.v
    trust = [np.zeros(c, bool) if trusted is None else np.asarray(t, bool).reshape(-1)
             for c, t in zip(counts, trusted if trusted is not None else [None] * n_pairs)]
    dist = [d if len(d) == c else np.zeros(c, np.float32)
            for c, d in zip(counts, merged.distances or [np.zeros(0, np.float32)] * n_pairs)]
    t_all = np.concatenate(trust)
    n_trusted = np.array([t.sum() for t in trust], np.int64)
    if order_by == "pairs":
        order = np.lexsort((row, pair_of, np.concatenate(dist), -n_trusted[pair_of], ~t_all))
    elif order_by == "support":
        order = np.lexsort((row, pair_of, np.concatenate(dist), -triangle_support(g), ~t_all))
    else:
        order = np.lexsort((row, pair_of, np.concatenate(dist), ~t_all))

    parent = list(range(int(offset[-1])))
    images: dict[int, set[int]] = {}  # component root -> its images (roots of single nodes: absent)
    img = image_of.tolist()

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    keep = np.zeros(len(u), bool)
    ul, vl = u.tolist(), v.tolist()
    for e in order.tolist():
        ra, rb = find(ul[e]), find(vl[e])
        if ra != rb:
            sa, sb = images.get(ra) or {img[ra]}, images.get(rb) or {img[rb]}
            if not sa.isdisjoint(sb):
                continue
            if len(sa) < len(sb):
                ra, rb, sa, sb = rb, ra, sb, sa
            parent[rb] = ra
            sa |= sb
            images[ra] = sa
            images.pop(rb, None)
        keep[e] = True
    starts = np.concatenate([[0], np.cumsum(counts)])
    matches, distances = [], []
    for p in range(n_pairs):
        k = keep[starts[p]:starts[p + 1]]
        matches.append(np.ascontiguousarray(merged.matches[p][k]))
        distances.append(dist[p][k])
    stats = MergeStats(**merged.stats.to_dict())
    dropped = int(len(keep) - keep.sum())
    stats.dropped_conflicts += dropped
    stats.num_output_matches -= dropped
    return MergedTracks(merged.keypoints, matches, list(merged.pairs), stats, distances)


def confirmed_counts(keypoints: Mapping[str, NDArray], pairs: Sequence[tuple[str, str]],
                     matches: Sequence[NDArray]) -> list[int]:
    """Per pair, how many of its `matches` (K, 2) into `keypoints` a third image confirms
    (`triangle_support` >= 1 in the graph of all `pairs`): the report's `confirmed_inliers`."""
    merged = MergedTracks({n: np.asarray(k) for n, k in keypoints.items()},
                          [np.asarray(m, np.uint32).reshape(-1, 2) for m in matches], list(pairs))
    confirmed = triangle_support(match_graph(merged)) > 0  # pair by pair, in `match_graph`'s edge order
    per_pair = np.split(confirmed, np.cumsum([len(m) for m in merged.matches])[:-1])
    return [int(np.count_nonzero(c)) for c in per_pair]


def connected_components(n: int, edges: NDArray[np.int64]) -> NDArray[np.int64]:
    """Component label of each of n nodes joined by undirected `edges` (E, 2): scipy's
    `csgraph.connected_components` (labels 0..k-1, numbered by their smallest node)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    if n == 0:
        return np.zeros(0, np.int64)
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    return scipy_components(graph, directed=False)[1].astype(np.int64)


def track_stats(num_keypoints: Mapping[str, int], pairs: Sequence[tuple[str, str]],
                matches: Sequence[NDArray]) -> dict:
    """Tracks of a match graph: {num_tracks, mean_length, max_length, inconsistent,
    consistent_mean_length, inconsistent_share}.

    A track is a connected component of (image, keypoint) nodes joined by matches; its length is
    its number of nodes. `inconsistent` counts tracks holding two keypoints of one image (COLMAP
    splits or trims those while triangulating), `inconsistent_share` is the fraction of nodes
    in them, and `consistent_mean_length` the mean length of the other tracks. With dense
    matches on repeated texture a few wrong matches can chain most nodes into one giant
    inconsistent component (the rendered 30-image facade: one of 271510 nodes), which makes
    `mean_length` meaningless; `consistent_mean_length` stays the number to read.
    """
    names = list(num_keypoints)
    offset, image_of = {}, []
    total = 0
    for i, n in enumerate(names):
        offset[n] = total
        total += int(num_keypoints[n])
        image_of.append(np.full(int(num_keypoints[n]), i, np.int64))
    edges = [np.stack([np.asarray(m[:, 0], np.int64) + offset[a], np.asarray(m[:, 1], np.int64) + offset[b]], 1)
             for (a, b), m in zip(pairs, matches) if len(m)]
    if not edges:
        return dict(num_tracks=0, mean_length=0.0, max_length=0, inconsistent=0, consistent_mean_length=0.0,
                    inconsistent_share=0.0)
    e = np.concatenate(edges)
    lab = connected_components(total, e)
    in_graph = np.zeros(total, bool)
    in_graph[e.ravel()] = True
    comp = lab[in_graph]
    _, sizes = np.unique(comp, return_counts=True)
    img = np.concatenate(image_of)[in_graph]
    # tracks with two nodes of one image: distinct (component, image) < component size
    ci = np.unique(np.stack([comp, img], 1), axis=0)
    _, per_comp_images = np.unique(ci[:, 0], return_counts=True)
    bad = per_comp_images < sizes
    good_sizes = sizes[~bad]
    return dict(num_tracks=int(len(sizes)), mean_length=float(sizes.mean()), max_length=int(sizes.max()),
                inconsistent=int(np.count_nonzero(bad)),
                consistent_mean_length=float(good_sizes.mean()) if len(good_sizes) else 0.0,
                inconsistent_share=float(sizes[bad].sum() / sizes.sum()))


def distinct_correspondences(kpts0: NDArray, kpts1: NDArray, matches: NDArray, decimals: int = 2) -> int:
    """Number of distinct (position in image 0, position in image 1) among `matches` (K, 2)
    indices into `kpts0` / `kpts1` (px, positions rounded to 10^-decimals).

    Why: COLMAP's SIFT keeps up to two orientations (`max_num_orientations`), and with affine
    shape estimation two shapes, of one detected point as separate keypoints at the same
    position, and matching pairs them copy for copy, so one correspondence counts as two verified
    inliers. Our merged keypoints hold one position each, so "verified inliers per pair"
    compared the two on different footings; this count compares them on the same one (figures:
    docs/decisions.md, "Distinct verified inliers")."""
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    if len(m) == 0:
        return 0
    k0 = np.asarray(kpts0, np.float64).reshape(-1, 2)[m[:, 0]]
    k1 = np.asarray(kpts1, np.float64).reshape(-1, 2)[m[:, 1]]
    key = np.round(np.c_[k0, k1] * 10.0 ** decimals).astype(np.int64)
    return int(len(np.unique(key, axis=0)))
