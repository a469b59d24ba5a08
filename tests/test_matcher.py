"""The extra-affine matcher end to end on real pairs with ground-truth homographies, and the
shape of the matching package (no import cycle, private names stay private)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

import matching
from matching.io import load_gray, read_homography
from matching.matcher import ExtraAffineMatcher, MatcherConfig
from matching.metrics import precision
from matching.registry import get_matcher
from matching.store import FeatureStore


def _store(shared_data, *names):
    store = FeatureStore()
    for n in names:
        store.add_image(n, load_gray(shared_data / "oxford" / "graf" / f"{n}.png"))
    return store


def test_graf_1_4_precision_above_90_percent(shared_data):
    store = _store(shared_data, "img1", "img4")
    # the full grid on every pair (the adaptive paths send graf 1-4 to the views near its
    # estimated tilt: tests/test_adaptive.py)
    result = get_matcher("extra-affine", adaptive=False).match(store, "img1", "img4")
    rep = precision(result, read_homography(shared_data / "oxford" / "graf" / "H1to4p"))
    assert rep.points >= 400
    assert rep.precision >= 0.90
    assert result.reference == 0  # the frontal image 1 is the closer, more detailed view
    assert result.best_view is not None and result.best_view.t > 1.0  # a tilted view won
    # the coarse-to-fine search (CoarseConfig.search) scores part of the 45-view grid
    assert 20 <= len(result.coarse_scores) < 45
    assert result.escalation == ""
    assert {"reference", "coarse", "fine", "total"} <= set(result.timings)


@pytest.mark.slow
def test_results_are_deterministic_and_views_are_reused(shared_data):
    store = _store(shared_data, "img1", "img3", "img4")
    m = ExtraAffineMatcher(MatcherConfig(seed=7))
    r1 = m.match(store, "img1", "img3")
    misses_after_first = store.misses
    r2 = m.match(store, "img1", "img4")  # same reference image: its views come from the cache
    assert store.misses - misses_after_first < misses_after_first / 2
    fresh = _store(shared_data, "img1", "img3")
    r1b = ExtraAffineMatcher(MatcherConfig(seed=7)).match(fresh, "img1", "img3")
    np.testing.assert_array_equal(r1.matches, r1b.matches)
    np.testing.assert_array_equal(r1.inlier_mask, r1b.inlier_mask)
    assert r2.num_inliers > 100


@pytest.mark.slow
def test_swapped_inputs_give_the_same_geometry(shared_data):
    store = _store(shared_data, "img1", "img3")
    m = get_matcher("extra-affine")
    ab, ba = m.match(store, "img1", "img3"), m.match(store, "img3", "img1")
    assert ab.reference == 0 and ba.reference == 1
    H = read_homography(shared_data / "oxford" / "graf" / "H1to3p")
    assert precision(ba, np.linalg.inv(H)).precision >= 0.9


@pytest.mark.slow
def test_a_pair_that_does_not_match_returns_a_reason_not_an_error(shared_data):
    rng = np.random.default_rng(0)
    noise = (rng.random((480, 640)) * 255).astype(np.uint8)
    store = _store(shared_data, "img1")
    store.add_image("noise", noise)
    cfg = MatcherConfig.from_overrides(escalation__two_sided=False)
    r = ExtraAffineMatcher(cfg).match(store, "img1", "noise")
    assert r.num_inliers < 20
    assert r.reason or r.num_matches < 20


def test_paper_variant_is_selectable():
    cfg = MatcherConfig.from_overrides(variant="paper")
    assert cfg.reference.mode == "paper" and cfg.fine_top_k == 1 and not cfg.escalation.enabled
    assert cfg.coarse.rank_by == "matches"
    with pytest.raises(ValueError, match="unknown"):
        MatcherConfig.from_overrides(nonsense=1)


@pytest.mark.slow
def test_view_threads_do_not_change_the_result(shared_data):
    """workers = 1 (no pool) and workers = 2 (views on a thread pool) give the identical result."""
    results = []
    for workers in (1, 2):
        m = ExtraAffineMatcher(MatcherConfig(workers=workers))
        try:
            results.append(m.match(_store(shared_data, "img1", "img3"), "img1", "img3"))
        finally:
            m.close()
    a, b = results
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if f.name == "timings":
            assert va.keys() == vb.keys()
        elif isinstance(va, np.ndarray):
            assert np.array_equal(va, vb), f.name
        else:
            assert va == vb, f.name
    assert a.num_inliers > 500


PACKAGE = Path(matching.__file__).parent


def _matching_imports(path: Path) -> set[str]:
    """Modules of `matching` that `path` imports anywhere (top level, functions, TYPE_CHECKING)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level == 1 or mod == "matching" or mod.startswith("matching."):
                base = mod.removeprefix("matching").lstrip(".") if node.level == 0 else mod
                if base:
                    out.add(base.split(".")[0])
                else:  # from . import x / from matching import x
                    out.update(a.name for a in node.names if (PACKAGE / f"{a.name}.py").exists())
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[1] for a in node.names if a.name.startswith("matching."))
    return out


def test_matching_has_no_import_cycle():
    graph = {p.stem: _matching_imports(p) for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert {"matcher", "strategies", "escalation", "context", "reference"} <= graph.keys()
    # the matcher sits on top: only the method registry above it imports it, no stage does
    assert {m for m, deps in graph.items() if "matcher" in deps} == {"registry"}
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for dep in sorted(graph.get(m, ())):
            assert state.get(dep) != 1, "import cycle: " + " -> ".join([*path, m, dep])
            if dep not in state:
                visit(dep, [*path, m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_no_module_uses_another_modules_private_names():
    repo = PACKAGE.parent
    files = [*PACKAGE.glob("*.py"), *repo.glob("recon/**/*.py"), *repo.glob("tests/*.py")]
    bad = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("matching")):
                bad += [f"{path.name}: import {a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
            if (path.parent == PACKAGE and isinstance(node, ast.Attribute) and node.attr.startswith("_")
                    and not node.attr.startswith("__")
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
                bad.append(f"{path.name}:{node.lineno}: {ast.unparse(node)}")
    assert not bad, bad
