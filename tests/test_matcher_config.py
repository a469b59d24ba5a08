"""MatcherConfig (matching.config): one seed for every stage, overrides by section, a docstring
for every option of every matching config."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from matching import baselines, coarse, escalation, features, fine, reference, views
from matching.config import MatcherConfig, field_docs
from matching.matcher import ExtraAffineMatcher
from matching.store import FeatureStore

STAGE_CONFIGS = (views.GridConfig, reference.ReferenceConfig, coarse.CoarseConfig, fine.FineConfig,
                 escalation.EscalationConfig, features.DetectorConfig)
ALL_CONFIGS = (MatcherConfig, *STAGE_CONFIGS, baselines.BaselineConfig, baselines.SiftConfig, baselines.OrbConfig,
               baselines.AffineConfig, baselines.AsiftConfig, baselines.AorbConfig)


def _sub_configs(cfg) -> list:
    out = []
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out += [v, *_sub_configs(v)]
    return out


@pytest.mark.parametrize("build", [lambda: MatcherConfig(seed=7), lambda: MatcherConfig.from_overrides(seed=7),
                                   lambda: MatcherConfig.from_overrides(variant="multiview", seed=7),
                                   lambda: MatcherConfig.from_overrides(variant="3d", seed=7),
                                   lambda: dataclasses.replace(MatcherConfig.paper(), seed=7)])
def test_the_seed_has_one_source_however_the_config_is_built(build):
    cfg = build()
    assert cfg.seed == 7
    subs = _sub_configs(cfg)
    assert len(subs) >= 6  # grid, reference, coarse, fine, escalation, escalation.two_sided_grid
    assert all("seed" not in {f.name for f in dataclasses.fields(s)} for s in subs), \
        "a stage config has its own seed, which could disagree with MatcherConfig.seed"


def test_every_opencv_rng_seed_in_a_match_is_the_configured_seed(monkeypatch):
    """RANSAC, MAGSAC, FLANN: every stage seeds OpenCV's RNG right before its call; with
    MatcherConfig(seed=7) (built directly, not through from_overrides) all of them get 7,
    through the escalation levels and the guided rounds too."""
    seen: list[int] = []
    real = cv2.setRNGSeed
    monkeypatch.setattr(cv2, "setRNGSeed", lambda s: (seen.append(int(s)), real(s))[1])
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur((rng.random((180, 240)) * 255).astype(np.uint8), (0, 0), 2.0)
    warped = cv2.warpPerspective(img, np.array([[0.9, 0.1, 10], [-0.05, 0.8, 12], [1e-4, 0, 1]]), (240, 180))
    store = FeatureStore()
    store.add_image("a", img)
    store.add_image("b", warped)
    small = views.GridConfig(n=1)
    esc = escalation.EscalationConfig(min_inliers=10**6,
                                      two_sided_grid=views.GridConfig(n=1, ds=0.0, scale_mode="none"))
    planar = ExtraAffineMatcher(MatcherConfig(seed=7, workers=1, grid=small, escalation=esc)).match(store, "a", "b")
    assert "escalation" in planar.timings and planar.num_matches > 0  # every level ran
    n_planar = len(seen)
    general = MatcherConfig(seed=7, workers=1, grid=small, final_homography=False, guided_epipolar=True,
                            guided_epipolar_min_inliers=8, guided_epipolar_min_ratio=0.0)
    assert ExtraAffineMatcher(general).match(store, "a", "b").num_matches > 0
    assert n_planar > 20 and len(seen) > n_planar
    assert set(seen) == {7}


def test_from_overrides_takes_flat_sectioned_and_dotted_keys():
    cfg = MatcherConfig.from_overrides(variant="multiview", fine_top_k=3, coarse__rank_by="matches",
                                       **{"escalation.min_inliers": 12, "grid.n": 4})
    assert cfg.fine_top_k == 3 and cfg.coarse.rank_by == "matches"
    assert cfg.escalation.min_inliers == 12 and cfg.grid.n == 4
    assert not cfg.final_homography and cfg.escalation.min_coarse_inliers == 15  # the preset's, kept


def test_the_3d_preset_keeps_the_pair_escalation_without_a_homography():
    """`variant="3d"`: one 3D pair, so F verification and the covariant originals, but every
    escalation level of the pair preset (unlike `multiview`, which drops the costly ones)."""
    cfg = MatcherConfig.from_overrides(variant="3d")
    assert not cfg.final_homography and cfg.verify_model == "fundamental"
    assert cfg.fine_include_original and cfg.guided_epipolar
    assert cfg.fine.original_detector == "colmap-sift-affine"
    assert cfg.escalation == MatcherConfig().escalation and cfg.escalation.mser.enabled
    assert cfg.adaptive == MatcherConfig().adaptive
    # the README's benchmark spells the preset out as overrides of the pair preset: the same config
    assert cfg == MatcherConfig.from_overrides(final_homography=False, fine_include_original=True, guided_epipolar=True,
                                               **{"fine.original_detector": "colmap-sift-affine"})


def test_from_overrides_reaches_nested_sections():
    """`recon run --set matcher.escalation.steep.enabled=false` and the benchmarks' variants set
    fields of sections inside sections (escalation's steep and mser levels)."""
    cfg = MatcherConfig.from_overrides(**{"escalation.steep.enabled": False, "escalation__mser__pool": "verified",
                                          "escalation.steep.tilts": (8.0,), "escalation.min_inliers": 20})
    assert not cfg.escalation.steep.enabled and cfg.escalation.steep.tilts == (8.0,)
    assert cfg.escalation.mser.pool == "verified" and cfg.escalation.min_inliers == 20
    assert cfg.escalation.mser.ratio == MatcherConfig().escalation.mser.ratio  # the rest kept


@pytest.mark.parametrize("key, names", [("nonsense", "fine_top_k"), ("coarse__nonsense", "rank_by"),
                                        ("coarse.nonsense", "rank_by"), ("nosection__x", "escalation"),
                                        ("seed__x", "coarse"), ("coarse__seed", "rank_by"),
                                        ("escalation.mser.nonsense", "laf_max_angle_deg"),
                                        ("escalation.min_inliers.x", "not a section")])
def test_unknown_overrides_raise_naming_the_valid_ones(key, names):
    with pytest.raises(ValueError, match=names):
        MatcherConfig.from_overrides(**{key: 1})
    with pytest.raises(ValueError, match="multiview"):
        MatcherConfig.from_overrides(variant="nope")


@pytest.mark.parametrize("cls", ALL_CONFIGS, ids=lambda c: c.__name__)
def test_every_config_field_is_typed_and_documented(cls):
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        assert f.type not in (None, ""), f"{cls.__name__}.{f.name} has no type"
        assert len(docs.get(f.name, "")) >= 10, f"{cls.__name__}.{f.name} has no docstring"


def test_field_docs_reads_the_attribute_docstrings():
    docs = field_docs(MatcherConfig)
    assert docs["seed"].startswith("Seeds every RANSAC and FLANN")
    assert field_docs(baselines.SiftConfig)["ratio"] == field_docs(baselines.BaselineConfig)["ratio"]  # inherited
