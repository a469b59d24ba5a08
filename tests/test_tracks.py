"""Keypoint merging into multi-view tracks and the consistency check (recon.core.tracks), on synthetic
keypoints and on real castle_P30 matches."""

from __future__ import annotations

import numpy as np
import pytest

from recon.core.tracks import (
    MergedTracks,
    PairMatches,
    _leader_cluster,
    connected_components,
    consistent_tracks,
    epipolar_inliers,
    merge_tracks,
    track_stats,
)
from shared_paths import SHARED_DATA


def _three_view_pairs(n=60, noise=0.3, seed=0):
    """n 3D points seen in images A, B, C; each pair reports its own noisy, shuffled keypoints."""
    rng = np.random.default_rng(seed)
    # well separated true positions (>= 10 px apart) so clusters cannot touch
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(10)), -1).reshape(-1, 2)[:n] * 20.0 + 30.0
    true = {k: grid + rng.uniform(-3, 3, grid.shape) for k in "ABC"}
    pairs = []
    for a, b in (("A", "B"), ("B", "C"), ("A", "C")):
        pa, pb = rng.permutation(n), rng.permutation(n)  # per-pair keypoint order differs
        k0 = (true[a][pa] + rng.normal(0, noise, (n, 2))).astype(np.float32)
        k1 = (true[b][pb] + rng.normal(0, noise, (n, 2))).astype(np.float32)
        inv_a, inv_b = np.argsort(pa), np.argsort(pb)  # true point j is k0[inv_a[j]], k1[inv_b[j]]
        m = np.stack([inv_a, inv_b], 1)
        pairs.append(PairMatches(a, b, k0, k1, m, rng.uniform(50, 200, n).astype(np.float32)))
    return pairs, true


def _nk(mt):
    return {k: len(v) for k, v in mt.keypoints.items()}


def test_merging_gives_one_keypoint_per_point_and_tracks_of_three():
    pairs, true = _three_view_pairs()
    mt = merge_tracks(pairs, 2.0)
    assert _nk(mt) == {"A": 60, "B": 60, "C": 60}  # 120 observations per image -> 60 keypoints
    assert mt.stats.num_observations == 360 and mt.stats.num_keypoints == 180
    assert mt.stats.dropped_duplicates == 0 and mt.stats.dropped_collisions == 0
    for name, k in mt.keypoints.items():  # merged positions are the averages: close to the truth
        d = np.linalg.norm(k[:, None] - true[name][None], axis=2).min(1)
        assert d.max() < 1.0
    st = track_stats(_nk(mt), mt.pairs, mt.matches)
    assert st == {"num_tracks": 60, "mean_length": 3.0, "max_length": 3, "inconsistent": 0,
                  "consistent_mean_length": 3.0, "inconsistent_share": 0.0}


def test_no_merging_keeps_pairs_apart_and_tracks_of_two():
    pairs, _ = _three_view_pairs()
    mt = merge_tracks(pairs, 0.0)
    assert _nk(mt) == {"A": 120, "B": 120, "C": 120}
    st = track_stats(_nk(mt), mt.pairs, mt.matches)
    assert st["num_tracks"] == 180 and st["mean_length"] == 2.0 and st["max_length"] == 2


def test_per_image_radius_and_matches_index_merged_keypoints():
    pairs, _ = _three_view_pairs()
    mt = merge_tracks(pairs, {"A": 2.0, "B": 2.0, "C": 0.0})  # C not merged
    assert _nk(mt) == {"A": 60, "B": 60, "C": 120}
    for (a, b), m, p in zip(mt.pairs, mt.matches, pairs):
        assert m.dtype == np.uint32 and m.shape == (60, 2)
        # every merged match joins points near the matcher's original pair of points
        ka, kb = mt.keypoints[a][m[:, 0]], mt.keypoints[b][m[:, 1]]
        pa, pb = p.kpts0[p.matches[:, 0]], p.kpts1[p.matches[:, 1]]
        assert np.abs(np.sort(ka[:, 0]) - np.sort(pa[:, 0])).max() < 2.0
        assert np.abs(np.sort(kb[:, 0]) - np.sort(pb[:, 0])).max() < 2.0


def test_duplicates_and_many_to_one_collisions_are_dropped():
    k0 = np.array([[10, 10], [10.5, 10.2], [100, 100]], np.float32)  # first two merge
    k1 = np.array([[50, 50], [80, 80], [50.4, 50.1], [200, 200]], np.float32)  # 0 and 2 merge
    m = np.array([[0, 0],   # -> (a, x)
                  [1, 2],   # -> (a, x) again: duplicate
                  [1, 1],   # -> (a, y): collision with (a, x) in image 0
                  [2, 3]])  # -> (b, z)
    dist = np.array([5, 1, 2, 3], np.float32)  # the duplicate is the best (lowest) one
    mt = merge_tracks([PairMatches("A", "B", k0, k1, m, dist)], 2.0)
    assert _nk(mt) == {"A": 2, "B": 3}
    assert mt.stats.dropped_duplicates == 1 and mt.stats.dropped_collisions == 1
    out = mt.matches[0]
    assert len(out) == 2
    assert len(set(out[:, 0].tolist())) == 2 and len(set(out[:, 1].tolist())) == 2  # one-to-one
    # the kept (a, .) match is (a, x), not the worse (a, y)
    a = int(np.argmin(np.linalg.norm(mt.keypoints["A"] - [10.25, 10.1], axis=1)))
    x = int(np.argmin(np.linalg.norm(mt.keypoints["B"] - [50.2, 50.05], axis=1)))
    assert [a, x] in out.tolist()


def test_radius_not_grid_cells_decides():
    # 0.2 px apart across a 2 px grid border (x = 1.5): a fixed grid would split them
    k = np.array([[1.4, 5.0], [1.6, 5.0]], np.float32)
    other = np.array([[20, 20], [40, 40]], np.float32)
    pairs = [PairMatches("A", "B", k[:1], other[:1], np.array([[0, 0]])),
             PairMatches("A", "C", k[1:], other[1:], np.array([[0, 0]]))]
    mt = merge_tracks(pairs, 2.0)
    assert len(mt.keypoints["A"]) == 1
    assert np.allclose(mt.keypoints["A"][0], [1.5, 5.0])
    assert track_stats(_nk(mt), mt.pairs, mt.matches)["mean_length"] == 3.0


def test_merging_is_deterministic_and_exact_repeats_collapse():
    pairs, _ = _three_view_pairs(seed=3)
    a = merge_tracks(pairs, 2.0)
    b = merge_tracks(pairs, 2.0)
    for n in a.keypoints:
        assert np.array_equal(a.keypoints[n], b.keypoints[n])
    for x, y in zip(a.matches, b.matches):
        assert np.array_equal(x, y)
    # identical keypoints in every pair (a detector run once per image) merge exactly
    k = np.random.default_rng(1).uniform(0, 500, (40, 2)).astype(np.float32)
    m = np.stack([np.arange(40), np.arange(40)], 1)
    mt = merge_tracks([PairMatches("A", "B", k, k, m), PairMatches("A", "C", k, k, m)], 0.01)
    assert len(mt.keypoints["A"]) == 40 and np.allclose(np.sort(mt.keypoints["A"], 0), np.sort(k, 0))


def _leader_cluster_reference(pts, counts, radius):
    """The rule in its plainest form: visit by (count desc, first appearance); join the nearest
    leader with dx*dx + dy*dy <= radius^2 (ties: the earliest leader) or lead."""
    order = sorted(range(len(pts)), key=lambda i: (-counts[i], i))
    leaders, labels = [], [0] * len(pts)
    for i in order:
        x, y = pts[i]
        best, best_d = -1, radius * radius
        for lid, (lx, ly) in enumerate(leaders):
            d = (lx - x) * (lx - x) + (ly - y) * (ly - y)
            if d < best_d or (d == best_d and best < 0):
                best, best_d = lid, d
        if best < 0:
            best = len(leaders)
            leaders.append((float(x), float(y)))
        labels[i] = best
    return labels


def test_kdtree_leader_clustering_equals_the_sequential_rule():
    """Random clumps, points exactly `radius` apart, equidistant leaders, and a long chain of
    neighbours (more dependent steps than the vectorised rounds: the sequential finish)."""
    rng = np.random.default_rng(0)
    centres = rng.uniform(0, 200, (40, 2))
    clumps = (centres[rng.integers(0, 40, 600)] + rng.normal(0, 1.2, (600, 2)))
    # a point exactly `radius` from a leader joins it; a point 1.5 px from two leaders joins the earlier
    exact = np.array([[300.0, 0.0], [302.0, 0.0], [310.0, 0.0], [313.0, 0.0], [311.5, 0.0]])
    chain = np.stack([400.0 + 1.9 * np.arange(150), np.zeros(150)], 1)  # 150 links of 1.9 px
    pts = np.concatenate([clumps, exact, chain])
    counts = np.concatenate([rng.integers(1, 4, 600), [9, 1, 9, 9, 1], 200 - np.arange(150)])
    got = _leader_cluster(pts, counts.astype(np.int64), 2.0)
    assert got.tolist() == _leader_cluster_reference(pts, counts.tolist(), 2.0)
    e = got[600:605]
    assert e[1] == e[0] and e[4] == e[2] != e[3]
    assert len(set(got[-150:].tolist())) == 75  # the chain: every other link leads


def test_connected_components_matches_union_find():
    rng = np.random.default_rng(0)
    n = 500
    edges = rng.integers(0, n, (300, 2))
    lab = connected_components(n, edges)
    parent = list(range(n))

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in edges.tolist():
        parent[find(a)] = find(b)
    roots = [find(i) for i in range(n)]
    for i in range(n):
        for j in (0, i // 2, n - 1):
            assert (lab[i] == lab[j]) == (roots[i] == roots[j])


def test_track_stats_counts_inconsistent_tracks():
    # A0-B0, B0-C0, C0-A1: one track holding two keypoints of A
    m_ab = np.array([[0, 0]], np.uint32)
    m_bc = np.array([[0, 0]], np.uint32)
    m_ca = np.array([[0, 1]], np.uint32)
    st = track_stats({"A": 2, "B": 1, "C": 1}, [("A", "B"), ("B", "C"), ("C", "A")], [m_ab, m_bc, m_ca])
    assert st == {"num_tracks": 1, "mean_length": 4.0, "max_length": 4, "inconsistent": 1,
                  "consistent_mean_length": 0.0, "inconsistent_share": 1.0}


def test_track_stats_separate_a_giant_inconsistent_component():
    """Ten clean 3-view tracks plus one chain that links two keypoints of A: the mean over all
    tracks is pulled up, the consistent mean is not."""
    n = 10
    clean = np.stack([np.arange(n), np.arange(n)], 1).astype(np.uint32)
    chain_ab = np.array([[n, n]], np.uint32)  # A10-B10
    chain_bc = np.array([[n, n]], np.uint32)  # B10-C10
    chain_ca = np.array([[n, n + 1]], np.uint32)  # C10-A11: A twice
    st = track_stats({"A": n + 2, "B": n + 1, "C": n + 1}, [("A", "B"), ("B", "C"), ("C", "A")],
                     [np.vstack([clean, chain_ab]), np.vstack([clean, chain_bc]), np.vstack([clean, chain_ca])])
    assert st["num_tracks"] == n + 1 and st["inconsistent"] == 1
    assert st["consistent_mean_length"] == 3.0
    assert st["inconsistent_share"] == 4 / (3 * n + 4)
    assert st["mean_length"] == (3 * n + 4) / (n + 1)


def _chained_views(offset_px=6.0):
    """Ten 3-view tracks over A, B, C, plus one point that A's keypoints in pairs (A, B) and
    (A, C) place `offset_px` apart (beyond the merge radius): merged, B-C closes the chain
    A0 - B - C - A1, one track with two keypoints of A. The (A, C) match of that point has the
    worst descriptor distance."""
    rng = np.random.default_rng(0)
    pts = {k: rng.uniform(0, 400, (10, 2)).astype(np.float32) for k in "ABC"}
    odd = {"A": np.array([[500.0, 500.0]], np.float32), "B": np.array([[520.0, 480.0]], np.float32),
           "C": np.array([[540.0, 470.0]], np.float32)}
    k = {n: np.vstack([pts[n], odd[n]]) for n in "ABC"}
    kA_ac = k["A"].copy()
    kA_ac[10] += [offset_px, 0.0]  # the same point, found offset_px away in pair (A, C)
    m = np.stack([np.arange(11), np.arange(11)], 1)
    dist = np.full(11, 10.0, np.float32)
    worst = dist.copy()
    worst[10] = 90.0
    pairs = [PairMatches("A", "B", k["A"], k["B"], m, dist), PairMatches("B", "C", k["B"], k["C"], m, dist),
             PairMatches("A", "C", kA_ac, k["C"], m, worst)]
    return pairs


def test_merge_alone_chains_two_keypoints_of_one_image_consistent_tracks_do_not():
    mt = merge_tracks(_chained_views(), 2.0)
    assert len(mt.keypoints["A"]) == 12  # the offset point stays two keypoints of A
    st = track_stats(_nk(mt), mt.pairs, mt.matches)
    assert st["inconsistent"] == 1 and st["inconsistent_share"] == 4 / 34  # A0-B-C-A1
    ct = consistent_tracks(mt)
    st = track_stats(_nk(ct), ct.pairs, ct.matches)
    assert st["inconsistent"] == 0 and st["inconsistent_share"] == 0.0
    assert st["num_tracks"] == 11 and st["max_length"] == 3
    assert ct.stats.dropped_conflicts == 1 and ct.stats.num_output_matches == 32
    # the dropped match is the worst one: the offset point's (A, C) match; the others are untouched
    assert [len(m) for m in ct.matches] == [11, 11, 10]
    a_far = int(np.argmin(np.linalg.norm(ct.keypoints["A"] - [506.0, 500.0], axis=1)))
    assert a_far not in ct.matches[2][:, 0].tolist()
    assert all(np.array_equal(x, y) for x, y in zip(ct.matches[:2], mt.matches[:2]))
    assert ct.keypoints is mt.keypoints


def test_consistent_tracks_prefer_trusted_matches_over_descriptor_distance():
    mt = merge_tracks(_chained_views(), 2.0)
    # distrust the (A, B) match of the offset point: it goes, although its distance is lowest
    trusted = [np.ones(len(m), bool) for m in mt.matches]
    a_near = int(np.argmin(np.linalg.norm(mt.keypoints["A"] - [500.0, 500.0], axis=1)))
    trusted[0][mt.matches[0][:, 0] == a_near] = False
    ct = consistent_tracks(mt, trusted)
    assert [len(m) for m in ct.matches] == [10, 11, 11]
    assert a_near not in ct.matches[0][:, 0].tolist()
    assert len(ct.distances[0]) == 10 and track_stats(_nk(ct), ct.pairs, ct.matches)["inconsistent"] == 0


def test_consistent_tracks_keep_a_clean_graph_whole():
    pairs, _ = _three_view_pairs()
    mt = merge_tracks(pairs, 2.0)
    ct = consistent_tracks(mt, [np.ones(len(m), bool) for m in mt.matches])
    assert ct.stats.dropped_conflicts == 0
    assert all(np.array_equal(x, y) for x, y in zip(ct.matches, mt.matches))


def test_epipolar_inliers_flag_matches_off_the_epipolar_lines():
    """Two views of random 3D points (a real F): matches moved 30 px off are flagged, the rest fit."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-2, 2, (80, 2)), rng.uniform(4, 8, 80)]
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    R = np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]])
    x0 = (K @ X.T).T
    x1 = (K @ (R @ X.T + np.array([[-1.0], [0.1], [0.2]]))).T
    k0 = (x0[:, :2] / x0[:, 2:]).astype(np.float32)
    k1 = (x1[:, :2] / x1[:, 2:]).astype(np.float32)
    k1[:10] += [0.0, 30.0]  # vertical shift: off the (near-horizontal) epipolar lines
    m = np.stack([np.arange(80), np.arange(80)], 1)
    mt = merge_tracks([PairMatches("A", "B", k0, k1, m)], 0.0)
    assert np.array_equal(mt.matches[0], m)  # no merging: the matcher's own indices
    inl = epipolar_inliers(mt, 1.0)[0]
    assert not inl[:10].any() and inl[10:].mean() > 0.95


@pytest.mark.requires_shared("scenes/castle_P30/images")
def test_real_scene_matches_give_consistent_tracks():
    """Three castle_P30 photos matched as `recon run` matches them (640 px): merged alone, some
    tracks hold two keypoints of one image (measured: 16 tracks, 4.3 % of the observations);
    after `consistent_tracks` none does, and only those conflicting matches went."""
    from matching.store import FeatureStore
    from recon.core.paircache import result_to_full_res
    from recon.core.scene import scan_scene
    from recon.core.stages.match import make_matcher

    scene, grays = scan_scene(SHARED_DATA / "scenes" / "castle_P30", max_size=640, workers=1)
    names = ["0000.jpg", "0001.jpg", "0002.jpg"]
    store = FeatureStore()
    for n in names:
        store.add_image(n, grays[n])
    matcher = make_matcher("extra-affine", seed=0, inner_workers=1)
    pairs = []
    for a, b in (("0000.jpg", "0001.jpg"), ("0000.jpg", "0002.jpg"), ("0001.jpg", "0002.jpg")):
        r = result_to_full_res(matcher.match(store, a, b), scene.image(a), scene.image(b))
        pairs.append(PairMatches(a, b, r.kpts0, r.kpts1, r.matches, r.distances))
    scale = 1.0 / min(scene.image(names[0]).scale_xy)  # working px -> full-resolution px
    mt = merge_tracks(pairs, 2.0 * scale)
    before = track_stats(_nk(mt), mt.pairs, mt.matches)
    assert before["inconsistent"] > 0
    ct = consistent_tracks(mt, epipolar_inliers(mt, 4.0 * min(scale, 3.0)))
    after = track_stats(_nk(ct), ct.pairs, ct.matches)
    assert after["inconsistent"] == 0 and after["inconsistent_share"] == 0.0
    kept = sum(len(m) for m in ct.matches)
    assert kept == sum(len(m) for m in mt.matches) - ct.stats.dropped_conflicts
    assert 0 < ct.stats.dropped_conflicts <= 0.05 * kept


def test_tracks_config_checks_trust_px():
    from recon.config import TracksConfig
    from recon.errors import UserError

    assert TracksConfig().consistent is True and TracksConfig(trust_px=2).trust_px == 2.0
    for bad in (0, -1.0, True):
        with pytest.raises(UserError, match="trust_px"):
            TracksConfig(trust_px=bad)
    assert TracksConfig().refine_robust_rounds == 2 and TracksConfig(refine_robust_rounds=0).refine_robust_rounds == 0
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(UserError, match="refine_robust_rounds"):
            TracksConfig(refine_robust_rounds=bad)


def test_distinct_correspondences_count_a_repeated_pair_of_positions_once():
    """Two keypoints at one position (two orientations) matched to two at another count once."""
    from recon.core.tracks import distinct_correspondences

    k0 = np.array([[10.0, 20.0], [10.0, 20.0], [30.0, 40.0], [30.004, 40.0]], np.float32)
    k1 = np.array([[11.0, 21.0], [11.0, 21.0], [31.0, 41.0], [50.0, 60.0]], np.float32)
    m = np.array([[0, 0], [1, 1], [2, 2], [3, 2], [2, 3]])
    # (0,0) and (1,1) repeat one correspondence; (3,2) is (2,2) within 0.01 px; (2,3) is another
    assert distinct_correspondences(k0, k1, m) == 3
    assert distinct_correspondences(k0, k1, m, decimals=3) == 4
    assert distinct_correspondences(k0, k1, np.zeros((0, 2), np.int64)) == 0


def test_conflict_order_by_distance_drops_the_far_match_not_the_small_pair():
    """A wrong match (a0, b0) with a large descriptor distance in the pair with most matches, and a
    right chain a1 - c0 - b0 through two one-match pairs. Pair by pair, (A, B) goes first and its
    wrong match drops (b0, c0); by distance over all pairs, the wrong match is the one dropped."""
    kp = np.zeros((3, 2), np.float32)
    mt = MergedTracks({"A": kp, "B": kp, "C": kp[:1]},
                      [np.array([[0, 0], [2, 2]], np.uint32), np.array([[0, 0]], np.uint32),
                       np.array([[1, 0]], np.uint32)],
                      [("A", "B"), ("B", "C"), ("A", "C")],
                      distances=[np.array([300.0, 50.0], np.float32), np.array([40.0], np.float32),
                                 np.array([30.0], np.float32)])
    trusted = [np.ones(len(m), bool) for m in mt.matches]
    by_pairs = consistent_tracks(mt, trusted, "pairs")
    assert [m.tolist() for m in by_pairs.matches] == [[[0, 0], [2, 2]], [], [[1, 0]]]
    by_distance = consistent_tracks(mt, trusted, "distance")
    assert [m.tolist() for m in by_distance.matches] == [[[2, 2]], [[0, 0]], [[1, 0]]]
    assert by_pairs.stats.dropped_conflicts == by_distance.stats.dropped_conflicts == 1
    with pytest.raises(ValueError, match="order_by"):
        consistent_tracks(mt, trusted, "random")


def test_conflict_order_by_support_drops_the_match_no_third_image_confirms():
    """One point seen as a0, b0, c0, d0 in four images, matched in five pairs (not B-D), and a
    wrong match b0 - d1 with the lowest descriptor distance in the pair with most matches (B-D,
    whose other match b2 - d2 is a point only B and D see). Pair by pair and by distance, the wrong
    match settles first and the right (A, D) and (C, D) matches drop; by triangle support (a0-c0
    closes two triangles, through b0 and d0; b0-d1 none) only the wrong one drops."""
    from recon.core.tracks import match_graph, triangle_support

    kp = np.zeros((3, 2), np.float32)
    pairs = [("B", "D"), ("A", "B"), ("A", "C"), ("A", "D"), ("B", "C"), ("C", "D")]
    matches = [np.array([[0, 1], [2, 2]], np.uint32)] + [np.array([[0, 0]], np.uint32)] * 5
    distances = [np.array([10.0, 90.0], np.float32)] + [np.array([50.0], np.float32)] * 5
    mt = MergedTracks({n: kp for n in "ABCD"}, matches, pairs, distances=distances)
    assert triangle_support(match_graph(mt)).tolist() == [0, 0, 1, 2, 1, 1, 1]
    trusted = [np.ones(len(m), bool) for m in mt.matches]
    for order in ("pairs", "distance"):
        kept = consistent_tracks(mt, trusted, order)
        assert kept.matches[0].tolist() == [[0, 1], [2, 2]]
        assert kept.matches[3].tolist() == kept.matches[5].tolist() == []
    by_support = consistent_tracks(mt, trusted, "support")
    assert [m.tolist() for m in by_support.matches] == [[[2, 2]]] + [[[0, 0]]] * 5
    assert by_support.stats.dropped_conflicts == 1
    assert track_stats(_nk(by_support), by_support.pairs, by_support.matches)["inconsistent"] == 0
    from recon.core.tracks import confirmed_counts

    # per pair, the matches that close a triangle: none in (B, D), all in the five others
    assert confirmed_counts(mt.keypoints, mt.pairs, mt.matches) == [0, 1, 1, 1, 1, 1]
    assert confirmed_counts(mt.keypoints, mt.pairs[:1], mt.matches[:1]) == [0]


def test_triangle_support_predicts_right_matches_on_a_rendered_facade(rendered_scene):
    """Nine rendered facade views (19.5 deg apart), OpenCV SIFT once per image, every pair matched
    (ratio 0.8, a loose 2 px F RANSAC, so wrong matches stay): against the exact transfer through
    the rendered planes, the matches that third images confirm are right more often than those
    none confirms (measured: 86.5 % right without a triangle, 98.8 % with three or more), which
    is why the consistency check admits them first (`conflict_order` = "support")."""
    import itertools
    import json

    import cv2

    from recon.core.tracks import match_graph, triangle_support
    from recon.eval.gt import read_colmap_text
    from recon.eval.gt_planes import correct_matches, rects_from_scene

    scene = rendered_scene("facade-9x78")
    rects = rects_from_scene(json.loads((scene / "gt" / "scene.json").read_text()))
    cams = read_colmap_text(scene / "gt")
    names = sorted(cams)
    sift = cv2.SIFT.create()
    feats = {n: sift.detectAndCompute(cv2.imread(str(scene / "images" / n), cv2.IMREAD_GRAYSCALE), None)
             for n in names}
    pairs = []
    for a, b in itertools.combinations(names, 2):
        (k0, d0), (k1, d1) = feats[a], feats[b]
        good = np.array([(m.queryIdx, m.trainIdx, m.distance) for m, n in cv2.BFMatcher().knnMatch(d0, d1, k=2)
                         if m.distance < 0.8 * n.distance]).reshape(-1, 3)
        p0, p1 = (np.float32([k.pt for k in kp]) for kp in (k0, k1))
        if len(good) < 8:
            continue
        cv2.setRNGSeed(0)
        F, mask = cv2.findFundamentalMat(p0[good[:, 0].astype(int)], p1[good[:, 1].astype(int)], cv2.FM_RANSAC, 2.0,
                                         0.999)
        if F is not None:
            good = good[mask.ravel().astype(bool)]
            pairs.append(PairMatches(a, b, p0, p1, good[:, :2].astype(np.int64), good[:, 2].astype(np.float32)))
    mt = merge_tracks(pairs, 0.5)  # one detection per image: a keypoint has one position in all its pairs
    support = triangle_support(match_graph(mt))
    right = np.concatenate([correct_matches(rects, cams[a], cams[b], mt.keypoints[a][m[:, 0]], mt.keypoints[b][m[:, 1]],
                                            np.sqrt(3.0)) for (a, b), m in zip(mt.pairs, mt.matches)])
    assert len(support) == len(right) > 2000
    alone, confirmed = support == 0, support >= 3
    assert alone.sum() > 200 and confirmed.sum() > 200
    assert right[confirmed].mean() > 0.97
    assert right[confirmed].mean() - right[alone].mean() > 0.06
