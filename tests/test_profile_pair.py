"""benchmarks/profile_pair.py: the per-thread timeline of one pair (needs the shared graf pair)."""

from __future__ import annotations

import importlib.util

from shared_paths import REPO

_spec = importlib.util.spec_from_file_location("profile_pair", REPO / "benchmarks" / "profile_pair.py")
assert _spec is not None and _spec.loader is not None
profile_pair = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profile_pair)


def test_profile_pair_timeline_shows_overlapping_detections(shared_data, capsys):
    """`benchmarks/profile_pair.py --timeline` on graf 1-3 (targeted): the target's full-resolution
    SIFT runs on a pool thread while ORB views are scored on the other, so their intervals overlap."""
    profile_pair.main([str(shared_data), "graf 1-3", "--timeline"])
    lines = [ln.split(maxsplit=4) for ln in capsys.readouterr().out.splitlines() if ln.startswith("    ")]
    spans = [(float(t.split("-")[0]), float(t.split("-")[1]), th, what) for t, _s, _d, th, what in lines]
    sift = [s for s in spans if s[3] == "detect:sift"]
    orb = [s for s in spans if s[3] == "detect:orb"]
    assert len(sift) == 5 and orb  # two half-size for the decision, the target, two fine views
    target = sift[2]
    assert any(o[2] != target[2] and o[0] < target[1] and o[1] > target[0] for o in orb)
