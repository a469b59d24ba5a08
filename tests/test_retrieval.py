"""Retrieval pairs (`recon.core.retrieval`) and the retrieval specs of `--pairs`."""

from __future__ import annotations

import numpy as np
import pytest

from matching.store import FeatureStore
from recon.core import retrieval as R
from recon.core.pairs import make_pairs, parse_pairs_spec
from recon.core.scene import scan_scene


# specs ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("spec", ["retrieval:0", "retrieval:x", "sequential:-1", "foo", "retrieval",
                                  "retrieval:3+retrieval:2", "retrieval:2+sequential:0", "retrieval:2+bar:1"])
def test_bad_specs_raise_one_line(spec):
    with pytest.raises(ValueError) as e:
        parse_pairs_spec(spec)
    msg = str(e.value)
    assert "\n" not in msg and spec in msg


def test_good_specs():
    assert str(parse_pairs_spec("retrieval:5")) == "retrieval:5"
    s = parse_pairs_spec("sequential:2+retrieval:4")
    assert (s.kind, s.k, s.sequential, str(s)) == ("retrieval", 4, 2, "retrieval:4+sequential:2")
    a = parse_pairs_spec("auto")
    assert (a.kind, a.k) == ("auto", R.AUTO_K)
    assert parse_pairs_spec("exhaustive").kind == "exhaustive"
    assert parse_pairs_spec("sequential:3").k == 3


def test_retrieval_named_file_is_a_file(tmp_path):
    f = tmp_path / "retrieval_pairs.txt"
    f.write_text("a b\n")
    assert parse_pairs_spec(str(f)).kind == "file"


def test_make_pairs_needs_retrieve_for_retrieval():
    with pytest.raises(ValueError):
        make_pairs(parse_pairs_spec("retrieval:2"), ["a", "b", "c"])
    got, w = make_pairs(parse_pairs_spec("retrieval:2"), ["a", "b", "c"], retrieve=lambda s, n: [(n[0], n[2])])
    assert got == [("a", "c")] and w == []


def test_auto_is_exhaustive_for_small_scenes_without_features():
    names = [f"{i:03d}.jpg" for i in range(R.AUTO_EXHAUSTIVE_MAX_IMAGES)]

    def boom(_name):
        raise AssertionError("small scenes must not compute retrieval features")

    pairs = R.pairs_for_spec(parse_pairs_spec("auto"), names, boom)
    assert len(pairs) == len(names) * (len(names) - 1) // 2
    assert make_pairs(parse_pairs_spec("auto"), names)[0] == pairs  # no `retrieve` needed either
    with pytest.raises(ValueError):
        make_pairs(parse_pairs_spec("auto"), names + ["zzz.jpg"])


# ranking ----------------------------------------------------------------------------------------
def test_top_k_pairs_bounds_order_and_ties():
    rng = np.random.default_rng(1)
    names = [f"im{i}" for i in range(12)]
    sim = rng.random((12, 12))
    for k in (1, 3, 5):
        pairs = R.top_k_pairs(names, sim, k)
        assert len(pairs) <= k * len(names)
        idx = [(names.index(a), names.index(b)) for a, b in pairs]
        assert all(i < j for i, j in idx) and idx == sorted(idx) and len(set(idx)) == len(idx)
        for i in range(12):  # every image keeps its own k best
            row = sim[i].copy()
            row[i] = -np.inf
            for j in np.argsort(-row, kind="stable")[:k]:
                assert (min(i, j), max(i, j)) in set(idx)
    # all-equal scores: ties go to the earliest images
    assert R.top_k_pairs(["a", "b", "c", "d"], np.ones((4, 4)), 1) == [("a", "b"), ("a", "c"), ("a", "d")]


def test_sequential_union():
    names = [f"{i}" for i in range(6)]
    descs = [np.random.default_rng(i).random((50, 128)).astype(np.float32) * 100 for i in range(6)]
    cfg = R.RetrievalConfig(num_words=4, views=())
    base = R.retrieval_pairs(names, descs, 1, cfg=cfg)
    both = R.retrieval_pairs(names, descs, 1, sequential=1, cfg=cfg)
    assert set(base) <= set(both)
    assert {(names[i], names[i + 1]) for i in range(5)} <= set(both)
    assert len(both) <= 2 * len(names)


def test_kmeans_deterministic():
    x = np.random.default_rng(0).random((500, 8))
    a = R.kmeans(x, 6, 10, seed=3)
    b = R.kmeans(x, 6, 10, seed=3)
    assert np.array_equal(a, b) and a.shape == (6, 8)


def test_pair_recall():
    assert R.pair_recall([("a", "b"), ("b", "c")], [("b", "a"), ("c", "d")]) == 0.5
    assert R.pair_recall([], []) == 1.0


# a rendered scene -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def facade9(tmp_path_factory):
    """A 9-view facade sweep over +-60 deg at 320x240: neighbours in name order are 15 deg apart."""
    from scenes.render import render_scene

    out = tmp_path_factory.mktemp("facade9")
    r = render_scene(out, "facade-9x60", image_size=(320, 240))
    scene, grays = scan_scene(out, max_size=None)
    store = FeatureStore()
    for n in scene.names:
        store.add_image(n, grays[n])
    return scene.names, store, r


def _gt_nearest(r) -> set[tuple[int, int]]:
    """For every view, the other view whose optical axis differs least (GT cam_from_world)."""
    axes = np.array([np.asarray(P)[2, :3] for P in r.cam_from_world])
    ang = np.degrees(np.arccos(np.clip(axes @ axes.T, -1, 1)))
    np.fill_diagonal(ang, np.inf)
    return {(min(i, int(j)), max(i, int(j))) for i, j in enumerate(np.argmin(ang, axis=1))}


def test_retrieval_proposes_true_neighbours(facade9):
    names, store, r = facade9
    cfg = R.RetrievalConfig(num_words=16, views=())
    descs = [R.image_descriptors(store, n, cfg) for n in names]
    k = 2
    pairs = R.retrieval_pairs(names, descs, k, cfg=cfg)
    assert len(pairs) <= k * len(names)
    idx = {(names.index(a), names.index(b)) for a, b in pairs}
    truth = _gt_nearest(r)
    assert len(truth) >= len(names) // 2
    assert truth <= idx, f"missed true neighbours {sorted(truth - idx)}"
    # a wide-baseline pair (60 deg apart) is not among the most similar
    assert (0, 4) not in idx and (4, 8) not in idx and (0, 8) not in idx
    # deterministic: same input, same pairs
    assert R.retrieval_pairs(names, descs, k, cfg=cfg) == pairs
    # the original's SIFT is the matcher's own store entry (the matching stage reuses it)
    assert (names[0], "sift0@orig") in store._entries


@pytest.mark.slow
def test_retrieval_with_simulated_views(facade9):
    names, store, r = facade9
    cfg = R.RetrievalConfig(num_words=16, views=((2.0, 0.0), (2.0, 90.0)))
    d0 = R.image_descriptors(store, names[0], R.RetrievalConfig())
    descs = [R.image_descriptors(store, n, cfg) for n in names]
    assert len(descs[0]) > len(d0)  # the tilted views add descriptors
    pairs = R.store_pairs(parse_pairs_spec("retrieval:2"), store, names, cfg)
    idx = {(names.index(a), names.index(b)) for a, b in pairs}
    assert _gt_nearest(r) <= idx and len(pairs) <= 2 * len(names)


@pytest.mark.parametrize("spec", ["retrieval:0", "retrieval:x", "sequential:-1", "foo"])
def test_cli_bad_retrieval_spec_is_one_line_exit_2(tmp_path, capsys, spec):
    from recon.cli import main

    rc = main(["run", str(tmp_path), "--method", "sift", "--no-progress", "--pairs", spec])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and spec in err[0]
