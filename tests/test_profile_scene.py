"""`benchmarks/profile_scene.py`: a finished run's stage seconds and its pairs' matcher stages."""

from __future__ import annotations

import importlib.util

from matching.types import PairResult
from recon.core.paircache import save_pair_result
from recon.core.report import RunReport, write_report
from shared_paths import REPO

_spec = importlib.util.spec_from_file_location("profile_scene", REPO / "benchmarks" / "profile_scene.py")
assert _spec is not None and _spec.loader is not None
profile_scene = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(profile_scene)


def test_sums_pair_stages_without_counting_nested_refine_twice(tmp_path, capsys):
    rep = RunReport(scene=str(tmp_path), out=str(tmp_path))
    rep.seconds_total, rep.stages, rep.pairs_computed = 10.0, {"match": 8.0, "sfm": 2.0}, 2
    write_report(rep, tmp_path / "report.json")
    for i, t in enumerate(({"fine": 3.0, "ransac": 1.5, "refine": 0.5, "total": 4.5},
                           {"fine": 2.0, "ransac": 1.0, "refine": 0.25, "total": 3.0})):
        r = PairResult.empty("extra-affine", "")
        r.timings = t
        save_pair_result(tmp_path / "cache" / "pairs" / f"{i}.npz", r)
    p = profile_scene.profile(tmp_path)
    assert p["pairs_read"] == 2 and p["stages"] == {"match": 8.0, "sfm": 2.0}
    assert p["pair_stages"] == {"fine": 5.0, "ransac": 1.75, "refine": 0.75, "total": 7.5}
    text = profile_scene.table(p)
    assert "7.5 pair-thread s" in text and "(without refine)" in text and "stage match" in text
    assert profile_scene.main([str(tmp_path / "nothing")]) == 2
    assert "no report.json" in capsys.readouterr().err
