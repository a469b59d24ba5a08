"""Adaptive per-pair paths switched on by the scene's size (`MatchConfig.adaptive_above`)."""

from __future__ import annotations

import json

import pytest

import recon  # noqa: F401  (cv2 before pycolmap)
from recon.config import MatchConfig
from recon.core.pipeline import RunConfig, run_scene
from recon.core.stages.match import make_matcher, matcher_identity, matcher_overrides
from recon.errors import UserError


def test_scene_size_switches_the_adaptive_paths_on():
    cfg = MatchConfig()
    assert make_matcher(cfg, 0, 1, num_images=31).cfg.adaptive is True
    assert make_matcher(cfg, 0, 1, num_images=30).cfg.adaptive is False  # the multiview variant's default
    assert make_matcher(cfg, 0, 1).cfg.adaptive is False  # size unknown: nothing switched
    # the identity (pair cache key) follows, so a cache of the other regime is not reused
    assert matcher_identity(make_matcher(cfg, 0, 1, 31)) != matcher_identity(make_matcher(cfg, 0, 1, 30))


def test_explicit_choices_win_over_the_scene_size():
    off = MatchConfig(matcher={"adaptive": False})
    assert matcher_overrides(off, 0, 1, num_images=500)["adaptive"] is False
    assert "adaptive" not in matcher_overrides(MatchConfig(adaptive_above=0), 0, 1, num_images=500)
    assert "adaptive" not in matcher_overrides(MatchConfig(method="sift"), 0, 1, num_images=500)
    for bad in (-1, 2.5, True):
        with pytest.raises(UserError):
            MatchConfig(adaptive_above=bad)


@pytest.mark.slow
def test_a_scene_above_the_size_takes_the_cheap_paths_where_they_suffice(corner_scene, tmp_path):
    """The rendered corner with the switch at 3 images: some of its pairs verify on the originals
    or near the estimated view, every image still registers; at the default size all run the grid."""
    reports = {}
    for above in (3, 30):
        out = tmp_path / f"above-{above}"
        cfg = RunConfig.from_options(out=out, progress=False, **{"match.adaptive_above": above})
        rep = run_scene(corner_scene, cfg)
        assert rep.ok and rep.registered_images == rep.num_images > 3
        reports[above] = json.loads((out / "report.json").read_text())["pairs"]
    assert {p["path"] for p in reports[30]} == {"full"}
    cheap = [p for p in reports[3] if p["path"] in ("originals", "targeted")]
    assert cheap and all(p["path_reason"] for p in cheap)
