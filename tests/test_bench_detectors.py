"""benchmarks/detectors_originals.py and benchmarks/bench_pairs_speed.py's matcher variants: the
scripts behind docs/decisions.md's "Covariant SIFT as an escalation level measured" and
"RootSIFT in the pair matcher measured"."""

from __future__ import annotations

import importlib.util

import pytest

from scenes.texture import procedural_texture
from scenes.tilt import TiltView, render_tilt_pair
from shared_paths import REPO


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


detectors_originals = _load("detectors_originals")
bench_pairs_speed = _load("bench_pairs_speed")


@pytest.mark.slow
def test_affine_shape_matches_a_tilted_plane_that_plain_sift_does_not():
    """A rendered plane seen at 72° (tilt 3.2) against its frontal view, originals only: COLMAP's
    SIFT with affine shape puts a homography's inliers on the true one, OpenCV's SIFT (RootSIFT)
    finds far fewer: what makes the covariant detector worth measuring as a level at all."""
    tex = procedural_texture(8.0, 6.0, 200.0, 3)
    img0, img1, H = render_tilt_pair(tex, TiltView(72.0, 0.0, 20.0), (640, 480))
    rows = {det: detectors_originals.one(img0, img1, H, det, [0.8])["r0.8"]
            for det in ("sift", "colmap-sift-affine")}
    affine, plain = rows["colmap-sift-affine"], rows["sift"]
    assert affine["inliers_within_5"] >= 30, rows
    assert affine["inliers_within_5"] >= 0.9 * affine["inliers"], rows  # the model is the true one
    assert affine["inliers_within_5"] >= 2 * plain["inliers_within_5"], rows


def test_variant_spec_types_values_and_names_section_fields():
    label, ov = bench_pairs_speed.parse_variant("root=fine.root_sift=true,fine.ratio=0.8,fine_top_k=3,guided=off")
    assert label == "root"
    assert ov == {"fine__root_sift": True, "fine__ratio": 0.8, "fine_top_k": 3, "guided": False}
    assert bench_pairs_speed.parse_variant("base=") == ("base", {})
    for bad in ("=fine.ratio=0.8", "x=fine.ratio", "x=fine.rootsift=true", "x=fine_top_k=two", "x=seed=2"):
        with pytest.raises(SystemExit):
            bench_pairs_speed.parse_variant(bad)


def test_variant_lines_count_solved_pairs_and_compare_with_the_default():
    rows = [{"pair": "a", "method": "extra-affine", "correct": 30, "precision": 0.9},
            {"pair": "b", "method": "extra-affine", "correct": 10, "precision": 0.9},
            {"pair": "a", "method": "root", "correct": 40, "precision": 0.9},
            {"pair": "b", "method": "root", "correct": 25, "precision": 0.4}]
    lines = bench_pairs_speed.variant_lines(rows, {"extra-affine": {}, "root": {}})
    assert lines[0] == "extra-affine: solved 1/2, correct 40"
    assert lines[1] == "root: solved 1/2, correct 65; against extra-affine: 2 pairs with more correct, 0 with fewer"


@pytest.mark.parametrize("method, flag", [("extra-affine-exact-blur", "ANTIALIAS_HALVING"),
                                          ("extra-affine-two-warps", "FUSED_AXIS_WARP")])
def test_flag_methods_turn_their_views_flag_off_for_their_call_only(method, flag):
    import matching.views as views

    seen = []

    class Inner:
        name = "extra-affine"

        def match(self, store, name0, name1):
            seen.append((views.ANTIALIAS_HALVING, views.FUSED_AXIS_WARP))
            if name0 == "bad":
                raise RuntimeError("boom")
            return "result"

    m = bench_pairs_speed.FlagOff(method, Inner())
    assert m.match(None, "a", "b") == "result"
    with pytest.raises(RuntimeError):
        m.match(None, "bad", "b")
    off = (flag != "ANTIALIAS_HALVING", flag != "FUSED_AXIS_WARP")  # only its own flag off
    assert seen == [off, off]
    assert views.ANTIALIAS_HALVING is True and views.FUSED_AXIS_WARP is True  # restored after each call, raising or not
