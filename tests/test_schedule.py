"""`match.simulate = "needed"`: the originals-only first pass and the second-pass selection."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest

from matching.config import MatcherConfig
from matching.io import load_gray
from matching.matcher import ExtraAffineMatcher
from matching.store import FeatureStore
from matching.types import ViewParams
from recon.core.schedule import ScheduleConfig, components, pairs_to_simulate


def _choices(names, weighted):
    pairs = [p for p, _ in weighted]
    out = pairs_to_simulate(names, pairs, [n for _, n in weighted], ScheduleConfig(min_partners=3))
    return {pairs[c.index]: c for c in out}


def test_components_ignore_the_edge_order():
    names = list("abcde")
    edges = [("d", "e"), ("b", "c"), ("a", "b")]
    assert components(names, edges) == components(names, edges[::-1]) == {"a": 0, "b": 0, "c": 0, "d": 3, "e": 3}


def test_weak_pairs_between_well_connected_images_are_not_simulated():
    names = list("ABCDFE")
    strong = [(p, 500) for p in itertools.combinations("ABCD", 2)] + [(("A", "F"), 300), (("B", "F"), 300),
                                                                        (("C", "F"), 300)]
    weak = [(("D", "F"), 60)] + [((x, "E"), n) for x, n in zip("ABCDF", (40, 30, 20, 10, 5))]
    ch = _choices(names, strong + weak)
    assert set(ch) == {p for p, _ in weak}  # strong pairs are not listed
    assert not ch[("D", "F")].simulate and "not simulated" in ch[("D", "F")].reason  # both have >= 3 partners
    # E has no strong partner: its 2 x 3 most promising weak pairs (here all 5) are simulated
    assert all(ch[(x, "E")].simulate for x in "ABCDF")
    assert "E has 0 strong partners (< 3)" in ch[("A", "E")].reason
    assert not any(c.bridge for c in ch.values())  # E's pairs carry its registration: the full matcher


def test_a_short_image_gets_only_its_most_promising_weak_pairs():
    names = ["hub", "x", "y", "z"] + [f"w{k}" for k in range(6)]
    strong = [(("hub", n), 400) for n in ("x", "y", "z")] + [(("x", "y"), 400), (("y", "z"), 400), (("x", "z"), 400)]
    strong += [(("x", f"w{k}"), 200) for k in range(6)] + [(("y", f"w{k}"), 200) for k in range(6)]
    strong += [(("z", f"w{k}"), 200) for k in range(6)]
    # every w has 3 strong partners; "hub" has 3 too; one more image with a single strong partner
    names.append("lonely")
    strong.append((("hub", "lonely"), 150))
    weak = [((f"w{k}", "lonely"), 90 - 10 * k) for k in range(6)]
    ch = _choices(names, strong + weak)
    chosen = [p for p, c in ch.items() if c.simulate]
    assert chosen == [("w0", "lonely"), ("w1", "lonely"), ("w2", "lonely"), ("w3", "lonely")]  # 2 x (3 - 1)


def test_two_strong_clusters_get_a_few_bridges_not_every_cross_pair():
    names = list("ABCDEFGH")
    strong = [(p, 900) for p in itertools.combinations("ABCD", 2)] + [(p, 900) for p in itertools.combinations("EFGH", 2)]
    cross = [((a, b), 10 + 3 * k) for k, (a, b) in enumerate(itertools.product("ABCD", "EFGH"))]
    ch = _choices(names, strong + cross)
    chosen = sorted((p for p, c in ch.items() if c.simulate), key=lambda p: -dict(cross)[p])
    best3 = sorted(cross, key=lambda w: -w[1])[:3]
    assert chosen == [p for p, _ in best3]
    assert all("different parts" in ch[p].reason and ch[p].bridge for p in chosen)


def test_a_cross_part_pair_of_an_image_short_of_partners_is_not_only_a_bridge():
    names = list("ABCDE")
    strong = [(p, 900) for p in itertools.combinations("ABC", 2)] + [(("D", "E"), 900)]
    weak = [(("C", "D"), 60), (("A", "E"), 50)]  # D and E have one strong partner each
    out = pairs_to_simulate(names, [p for p, _ in strong + weak], [n for _, n in strong + weak], ScheduleConfig())
    ch = {(strong + weak)[c.index][0]: c for c in out}
    assert ch[("C", "D")].simulate and ch[("A", "E")].simulate
    assert not ch[("C", "D")].bridge and not ch[("A", "E")].bridge  # their registration rests on them
    one = ScheduleConfig(min_partners=1)  # now every image has enough partners: the same pairs join two parts
    out = pairs_to_simulate(names, [p for p, _ in strong + weak], [n for _, n in strong + weak], one)
    assert [(strong + weak)[c.index][0] for c in out if c.simulate and c.bridge] == [("C", "D")]


def test_an_all_weak_scene_simulates_every_pair_of_a_small_capture_and_a_linear_number_of_a_large_one():
    small = [f"v{k}" for k in range(4)]
    pairs = list(itertools.combinations(small, 2))
    assert all(c.simulate for c in pairs_to_simulate(small, pairs, [0] * len(pairs), ScheduleConfig()))
    big = [f"v{k:02d}" for k in range(40)]
    pairs = list(itertools.combinations(big, 2))
    cfg = ScheduleConfig()
    n = sum(c.simulate for c in pairs_to_simulate(big, pairs, [5] * len(pairs), cfg))
    assert n <= 3 * cfg.min_partners * len(big) < len(pairs)


# --- the matcher's first pass ---------------------------------------------------------------------
def _store(scene, *names):
    store = FeatureStore()
    for n in names:
        store.add_image(n, load_gray(scene / "images" / n))
    return store


def _first_pass() -> MatcherConfig:
    from recon.config import MatchConfig
    from recon.core.stages.match import first_pass_overrides, make_matcher

    return make_matcher(MatchConfig(simulate="needed"), extra=first_pass_overrides(MatchConfig())).cfg


def test_first_pass_matches_only_the_originals_of_an_easy_pair(corner_scene):
    a, b = "view_02.png", "view_03.png"  # neighbouring views of the corner, 17 degrees apart
    cfg = replace(_first_pass(), workers=1)
    assert not cfg.simulate and cfg.fine.original_detector == "sift" and cfg.fine.original_contrast == 0.02
    r = ExtraAffineMatcher(cfg).match(_store(corner_scene, a, b), a, b)
    assert r.path == "originals" and r.path_reason.startswith("originals only")
    assert r.coarse_scores == [] and [v.is_identity for v in r.best_views] == [True]
    assert r.reference is None and r.escalation == ""
    assert "coarse" not in r.timings and "reference" not in r.timings
    assert r.verified >= 100 and r.num_matches >= r.verified * 0.8
    assert cfg.fine.original_cross_check


def test_first_pass_detects_each_original_once_and_the_database_takes_that_set(corner_scene):
    """Nothing is simulated in the first pass, so the target's features are the originals' one
    OpenCV SIFT set (not also the views' default set), and the database stage's descriptors come
    from the same set: one detection per image under `--simulate needed`, the default set otherwise."""
    from matching.fine import target_features
    from recon.config import MatchConfig
    from recon.core.stages.database import descriptor_detector

    a, b = "view_02.png", "view_03.png"
    cfg = replace(_first_pass(), workers=1)
    store = _store(corner_scene, a, b)
    ExtraAffineMatcher(cfg).match(store, a, b)
    assert list(target_features(store, b, cfg.fine).parts) == [cfg.fine.originals_detector.key] == ["sift0c0.02"]
    assert descriptor_detector(MatchConfig(simulate="needed"), 10) == cfg.fine.originals_detector
    assert descriptor_detector(MatchConfig(), 10).key == "sift0"  # `auto` on 10 images = `all`: the reference decision's set
    assert descriptor_detector(MatchConfig(simulate="needed", first_pass_detector="colmap-sift-plain"), 10).key == "sift0"
    budget = MatchConfig(simulate="needed", matcher={"fine": {"sift_features": 5000}})
    assert descriptor_detector(budget, 10).key == "sift5000c0.02"  # the first pass's own set, options and all
    rooted = MatchConfig(simulate="needed", matcher={"fine": {"root_sift": True}})
    assert descriptor_detector(rooted, 10).key == "sift0"  # the database's descriptors are rooted from plain ones


def test_first_pass_cross_check_keeps_the_mutual_nearest_neighbours(corner_scene):
    """The first pass's originals keep a ratio-test match only when it is also the target
    keypoint's nearest neighbour (COLMAP's cross-check): fewer raw matches, each one mutual."""
    import cv2

    from matching.fine import fine_match, target_features
    from matching.viewfeatures import original_features

    a, b = "view_00.png", "view_03.png"  # 51 degrees apart: ambiguous matches to drop
    cfg = _first_pass().fine
    store = _store(corner_scene, a, b)
    identity = [ViewParams(1.0, 0.0, 1.0)]
    checked = fine_match(store, a, b, identity, cfg)
    loose = fine_match(store, a, b, identity, replace(cfg, original_cross_check=False))
    assert 0 < len(checked.matches) < len(loose.matches)
    det = cfg.originals_detector
    fa = original_features(store, a, det)
    fb, offset = target_features(store, b, cfg).part(det)
    _, nearest_in_a = cv2.batchDistance(fb.descriptors, fa.descriptors, cv2.CV_32F, normType=cv2.NORM_L2, K=1)

    def mutual(fm) -> np.ndarray:  # the target keypoint's exact nearest reference keypoint is the match's
        back = fa.kpts[nearest_in_a.reshape(-1)[fm.matches[:, 1] - offset]]
        return np.all(back == fm.kpts_ref[fm.matches[:, 0]], axis=1)

    assert mutual(checked).all()  # fewer matched keypoints than FLANN_MIN_SIZE: an exact reverse search
    assert not mutual(loose).all()


def test_first_pass_defers_a_grazing_pair(facade_extreme_scene):
    a, b = "view_00.png", "view_01.png"  # grazing views of the facade: the originals barely match
    r = ExtraAffineMatcher(replace(_first_pass(), workers=1)).match(_store(facade_extreme_scene, a, b), a, b)
    assert r.path == "deferred", r.path_reason
    assert 0 <= r.verified < 30 and "second pass" in r.path_reason
    assert r.coarse_scores == []


def test_auto_is_needed_above_the_large_capture_size_and_all_below():
    from recon.config import MatchConfig
    from recon.core.stages.database import descriptor_detector
    from recon.core.stages.match import simulate_mode

    auto = MatchConfig()  # simulate = "auto", adaptive_above = 30
    assert auto.simulate == "auto"
    assert [simulate_mode(auto, n) for n in (2, 30, 31, 500)] == ["all", "all", "needed", "needed"]
    assert simulate_mode(auto, None) == "all"
    assert simulate_mode(MatchConfig(adaptive_above=0), 500) == "all"  # 0 = never a large capture
    assert simulate_mode(MatchConfig(adaptive_above=5), 6) == "needed"
    assert simulate_mode(MatchConfig(simulate="needed"), 3) == "needed"  # explicit choices win
    assert simulate_mode(MatchConfig(simulate="all"), 500) == "all"
    assert simulate_mode(MatchConfig(method="sift", simulate="needed"), 500) == "all"  # nothing to simulate
    # the database's descriptors follow the resolved mode: the first pass's set on a large scene
    assert descriptor_detector(auto, 31).key == "sift0c0.02" and descriptor_detector(auto, 30).key == "sift0"


# --- the stage ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_recon_run_simulates_only_the_pairs_the_scene_needs_and_resumes_from_both_passes(
        facade_extreme_scene, corner_scene, tmp_path):
    from recon.config import RunConfig
    from recon.core.pipeline import run_scene

    # grazing views: at most one strong pair, so every weak pair is simulated (no image has 3 strong partners)
    out = tmp_path / "extreme"
    rep = run_scene(facade_extreme_scene, RunConfig.from_options(out=out, progress=False, simulate="needed"))
    assert rep.ok and rep.registered_images == 4
    rows = json.loads((out / "report.json").read_text())["pairs"]
    assert len(rows) == 6 and rep.pairs_simulated >= 5
    weak = [p for p in rows if p["path"] != "originals"]
    assert len(weak) == rep.pairs_simulated
    assert all("-> simulated" in p["path_reason"] and p["path"] == "full" for p in weak)

    # the easy corner: its neighbouring pairs are strong, the rest are decided by the graph
    out = tmp_path / "corner"
    # `--simulate auto` (the default) on a scene above `match.adaptive_above` images is `needed`
    # (the second pass's matcher kept off the adaptive paths the large-capture size also selects)
    cfg = RunConfig.from_options(out=out, progress=False, workers=1,
                                 **{"match.adaptive_above": 3, "matcher.adaptive": False})
    assert cfg.match.simulate == "auto"
    rep = run_scene(corner_scene, cfg)
    assert rep.ok and rep.registered_images == rep.num_images >= 4 and rep.simulate_used == "needed"
    data = json.loads((out / "report.json").read_text())
    paths = [p["path"] for p in data["pairs"]]
    assert paths.count("originals") >= 3
    assert rep.pairs_simulated == sum(p in ("targeted", "full") for p in paths)
    for p in data["pairs"]:  # a pair is simulated exactly when the schedule said so
        assert ("-> simulated" in p["path_reason"]) == (p["path"] not in ("originals", "deferred")), p
    # a pair left weak (view_00 / view_04: 10 first-pass matches) reaches COLMAP without matches
    junk = [p for p in data["pairs"] if p["path"] == "deferred"]
    assert junk and all(p["raw_matches"] == 0 and "left unmatched" in p["reason"] for p in junk)
    again = run_scene(corner_scene, cfg)  # resumed: both passes come from the pair cache
    assert again.pairs_cached == len(paths) and again.pairs_computed == 0
    assert again.num_points3D == rep.num_points3D
    assert np.isclose(again.mean_reprojection_error, rep.mean_reprojection_error)


@pytest.mark.slow
def test_bridges_between_two_groups_of_views_get_the_cheap_matcher_and_join_the_scene(rendered_scene, tmp_path):
    import pycolmap

    from recon.config import RunConfig
    from recon.core.pipeline import run_scene
    from recon.eval.compare import load_gt
    from recon.eval.evaluate import evaluate_model

    # two groups of three views 6 deg apart, 94-118 deg between the groups: at 640 x 480 the
    # originals join the groups by no strong pair, and every image has two strong partners
    scene = rendered_scene("facade-groups", (640, 480))
    reports = {}
    for bridges in ("cheap", "full"):
        out = tmp_path / bridges
        rep = run_scene(scene, RunConfig.from_options(out=out, progress=False, simulate="needed",
                                                      **{"match.simulate_bridges": bridges}))
        assert rep.ok and rep.registered_images == 6 and rep.num_models == 1
        rows = json.loads((out / "report.json").read_text())["pairs"]
        groups = [{"view_00.png", "view_01.png", "view_02.png"}, {"view_03.png", "view_04.png", "view_05.png"}]
        simulated = [p for p in rows if p["path"] == "full"]
        assert simulated and all(not any({p["image0"], p["image1"]} <= g for g in groups) for p in simulated)
        assert all("different parts of the strong pair graph" in p["path_reason"] for p in simulated)
        assert all(("(bridge)" in p["path_reason"]) == (bridges == "cheap") for p in simulated)
        gt, _, _ = load_gt(scene)
        err = evaluate_model(pycolmap.Reconstruction(str(out / "sparse" / "0")), gt)["rel_rot_err_deg_median"]
        reports[bridges] = (rep, simulated, err)
    cheap, full = reports["cheap"], reports["full"]
    assert [p["image0"] + p["image1"] for p in cheap[1]] == [p["image0"] + p["image1"] for p in full[1]]
    # the cheap bridges: no covariant extraction of their images (fewer feature sets computed),
    # no epipolar round; the groups still join accurately
    assert cheap[0].features_computed < full[0].features_computed
    assert cheap[2] < 0.5, cheap[2]
