"""Track-level patch refinement: every observation of a track re-localised against one anchor.

Pair refinement (`matching.refine`, inside the matcher) moves one side of each match onto the
other's detected keypoint, pair by pair. A point of image B matched in pairs (A, B) and (B, C)
is therefore aligned to A's detection in one and to C's in the other; merging (`merge_tracks`)
then averages those positions and the track's observations still disagree by the detections'
own sub-pixel noise, different in every image. Here each consistent track (after
`consistent_tracks`: at most one keypoint per image) gets one anchor, its most-matched
observation, and every other observation is moved so that its patch agrees with the anchor's,
through the match graph: a breadth-first tree from the anchor, each node aligned to its already
aligned parent over the pair that matched them (the same least-squares patch alignment as the
matcher's, `matching.refine.refine_points0`: both patches warped into a common frame by the
pair's local affine, fitted robustly to the pair's nearest matches around the point, NCC peak
refined to sub-pixel). This is the keypoint adjustment of "Pixel-Perfect Structure-from-Motion" (Lindenberger
et al. 2021) with image patches in place of learned feature maps and a tree instead of a joint
optimisation.

Coordinates: merged keypoints are full-resolution OpenCV pixels; the patches are read from the
working-resolution grays of the feature store (`to_working` / `to_full_res` convert). A node
whose alignment fails (weak NCC peak, border, shift beyond `max_shift_px`) keeps its merged
position and its children align to that. Deterministic (no randomness; the tree depends on the
node order only).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from matching.refine import RefineConfig, local_affines_at, refine_points0
from recon.core.scene import to_full_res, to_working
from recon.core.tracks import MergedTracks, match_graph

_Aligned = tuple[str, NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]


@dataclass
class TrackRefineStats:
    """What the track refinement did (`report.merge["track_refine"]`)."""

    tracks: int = 0  # tracks of two or more observations
    aligned: int = 0  # observations aligned against a parent (all but the anchors)
    moved: int = 0  # of those, moved (the others kept their merged position)
    median_shift_px: float = 0.0  # median move of the moved ones, full-resolution px
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _tree(num_nodes: int, u: NDArray[np.int64], v: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(parent, depth) of every node in breadth-first trees rooted at each component's anchor,
    its node of highest degree (ties: the lowest index); roots have parent -1 and depth 0, nodes
    without matches depth -1."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    deg = np.bincount(np.r_[u, v], minlength=num_nodes)
    graph = coo_matrix((np.ones(len(u), np.int8), (u, v)), shape=(num_nodes, num_nodes)).tocsr()
    _, label = connected_components(graph, directed=False)
    order = np.lexsort((np.arange(num_nodes), -deg, label))  # per component: highest degree first
    first = np.ones(num_nodes, bool)
    first[1:] = label[order[1:]] != label[order[:-1]]
    anchors = order[first]
    anchors = anchors[deg[anchors] > 0]
    # one breadth-first search from a virtual root joined to every anchor
    root = num_nodes
    su = np.r_[u, np.full(len(anchors), root)]
    sv = np.r_[v, anchors]
    big = coo_matrix((np.ones(len(su), np.int8), (su, sv)), shape=(num_nodes + 1, num_nodes + 1)).tocsr()
    visit, pred = breadth_first_order(big, root, directed=False, return_predecessors=True)
    parent = np.full(num_nodes, -1, np.int64)
    depth = np.full(num_nodes, -1, np.int64)
    for node in visit[1:].tolist():  # visit order: a parent is always placed before its children
        p = int(pred[node])
        if p == root:
            depth[node] = 0
        else:
            parent[node] = p
            depth[node] = depth[p] + 1
    return parent, depth


def refine_tracks(merged: MergedTracks, images: Mapping[str, NDArray[np.uint8]],
                  scales: Mapping[str, tuple[float, float]], cfg: RefineConfig | None = None,
                  workers: int = 1, progress: Callable[[int, int], None] | None = None
                  ) -> tuple[dict[str, NDArray[np.float32]], TrackRefineStats]:
    """(refined keypoints per image, full-resolution px; stats) for `merged`'s keypoints, every
    track aligned to its anchor (module doc). The matches are unchanged (same indices). `images`
    are the working-resolution grays, `scales` each image's working / full scale (`scale_xy`).
    Pairs of one tree level run on `workers` threads (OpenCV releases the GIL)."""
    import time

    t0 = time.perf_counter()
    cfg = cfg or RefineConfig()
    g = match_graph(merged)
    names, pair_of, row, u, v = g.names, g.pair_of, g.row, g.u, g.v
    out = {n: np.asarray(merged.keypoints[n], np.float32).copy() for n in names}
    stats = TrackRefineStats()
    if g.num_nodes == 0 or len(u) == 0:
        return out, stats
    parent, depth = _tree(g.num_nodes, u, v)
    stats.tracks = int((depth == 0).sum())

    # the match (pair, row) behind each tree edge, and which side of it the child is
    child_is_v = parent[v] == u
    child_is_u = ~child_is_v & (parent[u] == v)
    edge_child = np.where(child_is_v, v, u)
    tree_edge = child_is_u | child_is_v
    # a child may be joined to its parent by several matches (one per pair): keep the first
    sel = np.flatnonzero(tree_edge)
    _, first = np.unique(edge_child[sel], return_index=True)
    sel = sel[first]
    child = edge_child[sel]
    side = child_is_v[sel].astype(np.int64)  # 1: the child is the pair's image 1
    stats.aligned = len(child)

    work = {n: to_working(out[n], scales[n]) for n in names}  # current positions, working px
    moved_any = {n: np.zeros(len(out[n]), bool) for n in names}
    shifts: list[NDArray[np.float64]] = []

    def align(job: tuple[int, int, NDArray[np.int64]]) -> _Aligned:
        """One pair's children of one tree level (`s` = the children's side) aligned to their
        parents: (children's image, their keypoint indices, new working positions, moved)."""
        p, s, e = job
        a, b = merged.pairs[p]
        m = np.asarray(merged.matches[p], np.int64)
        name_c, name_p = (b, a) if s == 1 else (a, b)
        col_c, col_p = (1, 0) if s == 1 else (0, 1)
        pts_c_all = work[name_c][m[:, col_c]]
        pts_p_all = work[name_p][m[:, col_p]]
        rows = row[sel[e]]
        A = local_affines_at(pts_c_all, pts_p_all, rows, cfg.neighbours, cfg.robust_rounds)
        new, moved = refine_points0(images[name_c], images[name_p], pts_c_all[rows], pts_p_all[rows], A, cfg)
        return name_c, m[rows, col_c], np.asarray(new, np.float64), moved

    # one job per (tree level, pair, children's side): the edges sorted by that key, then split
    order = np.lexsort((side, pair_of[sel], depth[child]))
    key = np.stack([depth[child], pair_of[sel], side], axis=1)[order]
    cuts = np.flatnonzero(np.any(key[1:] != key[:-1], axis=1)) + 1
    levels: dict[int, list[tuple[int, int, NDArray[np.int64]]]] = {}
    for e in np.split(order, cuts):  # in level order
        levels.setdefault(int(depth[child[e[0]]]), []).append((int(pair_of[sel[e[0]]]), int(side[e[0]]), e))
    done_edges = 0
    for jobs in levels.values():
        if workers > 1 and len(jobs) > 1:
            with ThreadPoolExecutor(workers) as pool:
                results = list(pool.map(align, jobs))
        else:
            results = [align(j) for j in jobs]
        for name_c, kp, new, moved in results:  # children of one level are distinct nodes
            before = to_full_res(work[name_c][kp[moved]], scales[name_c]).astype(np.float64)
            work[name_c][kp[moved]] = new[moved]
            moved_any[name_c][kp[moved]] = True
            after = to_full_res(new[moved], scales[name_c]).astype(np.float64)
            shifts.append(np.linalg.norm(after - before, axis=1))
            stats.moved += int(moved.sum())
            done_edges += len(kp)
        if progress is not None:
            progress(done_edges, stats.aligned)
    for n in names:  # only moved keypoints change (no round-trip rounding on the others)
        idx = np.flatnonzero(moved_any[n])
        out[n][idx] = to_full_res(work[n][idx], scales[n])
    allshift = np.concatenate(shifts) if shifts else np.zeros(0)
    stats.median_shift_px = float(np.median(allshift)) if len(allshift) else 0.0
    stats.seconds = round(time.perf_counter() - t0, 3)
    return out, stats
