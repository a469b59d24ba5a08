"""Match-graph expansion (`recon.core.expansion`, `--pairs retrieval:K+expand:E`)."""

from __future__ import annotations

import json

import pytest

import recon  # noqa: F401  (cv2 before pycolmap)
from recon.core.expansion import ExpansionConfig, covisibility_scores, expansion_pairs, round_yield
from recon.core.pairs import parse_pairs_spec
from recon.core.pipeline import RunConfig, run_scene

NAMES = ["a", "b", "c", "d", "e"]


def test_chains_propose_the_missing_pair_weighted_by_the_weaker_link():
    matched = {("a", "b"): 100, ("b", "c"): 40, ("c", "d"): 200, ("a", "c"): 0}
    scores = covisibility_scores(NAMES, matched, min_matches=15)
    # a-c was matched (even with no match): never proposed again; b-d via c: min(40, 200)
    assert scores == {(1, 3): 40}
    # an edge below the threshold is no link
    assert covisibility_scores(NAMES, {("a", "b"): 14, ("b", "c"): 100}, min_matches=15) == {}
    # two common neighbours add up and can be required
    two = {("a", "b"): 50, ("b", "e"): 30, ("a", "d"): 20, ("d", "e"): 90}
    assert covisibility_scores(NAMES, two, 15)[(0, 4)] == 30 + 20
    assert (0, 4) in covisibility_scores(NAMES, two, 15, min_common=2)
    assert covisibility_scores(NAMES, {("a", "b"): 50, ("b", "e"): 30}, 15, min_common=2) == {}


def test_each_image_keeps_its_best_candidates_in_a_fixed_order():
    # a star around `a`: every pair of leaves is a candidate, scored by its weaker spoke
    star = {("a", "b"): 90, ("a", "c"): 80, ("a", "d"): 70, ("a", "e"): 20}
    one = expansion_pairs(NAMES, star, ExpansionConfig(per_image=1))
    # b, c, d each pick their best partner; e picks b (score 20 ties broken by image order)
    assert one == [("b", "c"), ("b", "d"), ("b", "e")]
    assert expansion_pairs(NAMES, dict(reversed(list(star.items()))), ExpansionConfig(per_image=1)) == one
    assert len(expansion_pairs(NAMES, star, ExpansionConfig(per_image=3))) == 6  # all leaf pairs
    assert round_yield([100, 3, 20, 0], 15) == 0.5 and round_yield([], 15) == 1.0


def test_bad_configs_and_specs():
    for bad in ({"per_image": 0}, {"per_image": 1, "max_rounds": 0}, {"per_image": 1, "min_yield": 1.5}):
        with pytest.raises(ValueError):
            ExpansionConfig(**bad)
    s = parse_pairs_spec("expand:4+retrieval:6")
    assert (s.kind, s.k, s.expand, str(s)) == ("retrieval", 6, 4, "retrieval:6+expand:4")
    for spec in ("retrieval:6+expand:0", "retrieval:6+expand:x", "retrieval:6+expand:2+expand:3"):
        with pytest.raises(ValueError) as e:
            parse_pairs_spec(spec)
        assert "\n" not in str(e.value) and spec in str(e.value)


@pytest.mark.slow
def test_expansion_finds_overlapping_pairs_retrieval_missed_and_resumes(tmp_path):
    """A 9-view facade sweep with one retrieval neighbour per image: expansion adds pairs that
    retrieval did not propose, most of them verify, and a rerun takes every pair from the cache
    with the same pairs in the same order."""
    from scenes.render import render_scene

    scene = tmp_path / "scene"
    render_scene(scene, "facade-9x60", image_size=(480, 360))
    reports = {}
    for spec in ("retrieval:1", "retrieval:1+expand:2"):
        out = tmp_path / spec.replace(":", "-").replace("+", "_")
        cfg = RunConfig.from_options(out=out, progress=False, method="sift", **{"pairs.spec": spec})
        rep = run_scene(scene, cfg)
        assert rep.ok
        reports[spec] = (rep, json.loads((out / "report.json").read_text()))
    base, grown = reports["retrieval:1"][1], reports["retrieval:1+expand:2"][1]
    base_pairs = [(p["image0"], p["image1"]) for p in base["pairs"]]
    grown_pairs = [(p["image0"], p["image1"]) for p in grown["pairs"]]
    assert grown_pairs[:len(base_pairs)] == base_pairs  # proposed first, expansion after
    added = grown["pairs"][len(base_pairs):]
    assert grown["pairs_expanded"] and sum(grown["pairs_expanded"]) == len(added) > 0
    assert not {(p["image0"], p["image1"]) for p in added} & set(base_pairs)
    verified_added = [p for p in added if p["verified_inliers"] >= 15]
    assert len(verified_added) >= len(added) / 2
    assert grown["verified_pairs"] > base["verified_pairs"]
    assert len(grown_pairs) <= (1 + 2 * ExpansionConfig(per_image=2).max_rounds) * 9
    # resume: the same command computes nothing and keeps the pairs and their order
    out = tmp_path / "retrieval-1_expand-2"
    again = run_scene(scene, RunConfig.from_options(out=out, progress=False, overwrite=True, method="sift",
                                                    **{"pairs.spec": "retrieval:1+expand:2"}))
    assert again.pairs_computed == 0 and again.pairs_expanded == grown["pairs_expanded"]
    assert [(p.image0, p.image1) for p in again.pairs] == grown_pairs
