"""The run report (recon.core.report): report.json round trip, the console summary table, atomic writing."""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest
from rich.console import Console

from recon.core.report import PairRow, RunReport, summary_table, write_report


def _report(**kw) -> RunReport:
    """A report as a finished run fills it (numbers as the pipeline produces them, numpy included)."""
    rep = RunReport(scene="/data/scène 1", out="/data/scène 1/recon", num_images=4, num_models=1, model_sizes=[3],
                    tracks={"merged": {"num_tracks": 120, "mean_length": 3.4, "consistent_mean_length": 3.1,
                                       "inconsistent_share": 0.25},
                            "unmerged": {"mean_length": 2.0}},
                    merge={"num_keypoints": 900, "track_refine": {"tracks": 100, "aligned": 220, "moved": 200,
                                                                  "median_shift_px": 0.384, "seconds": 0.5}},
                    final_ba={"loss": "cauchy", "applied": True, "scale_px": 0.4123, "auto_scale": True,
                              "mean_reprojection_error_before": 0.9021, "mean_reprojection_error_after": 0.84,
                              "observations_dropped": 3, "seconds": 0.2},
                    seconds_total=12.25, peak_mb=np.float64(812.4),
                    stages={"load": 0.5, "match": np.float32(9.5), "sfm": 2.25},
                    pairs_computed=2, pairs_cached=1, features_computed=4, features_reused=2,
                    camera_mode_used="single", sfm_options={"init_min_tri_angle": 4.0},
                    sfm_growth=[{"step": 0, "model": 0, "image": "b.png", "registered_images": 2, "num_points3D": 50,
                                 "initial_pair": ["a.png", "b.png"]}],
                    pairs=[PairRow("a.png", "b.png", reference="a.png", best_view={"t": 2.0, "phi": 36.0, "s": 1.0},
                                   raw_matches=np.int64(300), merged_matches=280, verified_inliers=250,
                                   confirmed_inliers=155, two_view_config="CALIBRATED", seconds=1.5),
                           PairRow("a.png", "c.png", raw_matches=90, merged_matches=85, verified_inliers=60,
                                   cached=True),
                           PairRow("b.png", "c.png", reason="no match")],
                    skipped=[{"name": "broken.JPG", "reason": "not a readable image"}],
                    warnings=["broken.JPG: not a readable image"], config={"method": "extra-affine", "seed": 0})
    rep.set_model({"registered_images": 3, "num_points3D": 450, "mean_track_length": 3.2,
                   "mean_reprojection_error": 0.84}, ["a.png", "b.png", "c.png"])
    for k, v in kw.items():
        setattr(rep, k, v)
    return rep


def _from_json(data: dict) -> RunReport:
    return RunReport(**{**data, "pairs": [PairRow(**p) for p in data["pairs"]]})


def test_report_json_round_trip(tmp_path):
    rep = _report()
    path = tmp_path / "report.json"
    write_report(rep, path)
    data = json.loads(path.read_text(encoding="utf-8"))
    assert set(data) == {f.name for f in fields(RunReport)}  # every field, always
    assert data["scene"] == "/data/scène 1" and "scène" in path.read_text(encoding="utf-8")  # UTF-8, not \u escapes
    assert data["stages"]["match"] == 9.5 and data["pairs"][0]["raw_matches"] == 300  # numpy -> JSON numbers
    assert data["pairs"][0]["best_view"] == {"t": 2.0, "phi": 36.0, "s": 1.0}
    assert _from_json(data) == rep  # nothing lost: the JSON rebuilds the same report
    assert data == json.loads(json.dumps(rep.to_dict(), default=float))


def test_non_finite_numbers_become_null(tmp_path):
    path = tmp_path / "report.json"
    write_report(_report(mean_reprojection_error=float("nan"), peak_mb=np.float32("inf")), path)
    data = json.loads(path.read_text(encoding="utf-8"))  # strict JSON: no NaN / Infinity tokens
    assert data["mean_reprojection_error"] is None and data["peak_mb"] is None
    assert "NaN" not in path.read_text(encoding="utf-8")


def test_atomic_write_replaces_the_report_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "report.json"
    path.write_text("old", encoding="utf-8")
    write_report(_report(), path)
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]
    assert json.loads(path.read_text(encoding="utf-8"))["registered_images"] == 3


def test_a_failed_write_keeps_the_old_report(tmp_path):
    class Unprintable:
        def __str__(self) -> str:
            raise RuntimeError("no text")

    path = tmp_path / "report.json"
    write_report(_report(), path)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="no text"):
        write_report(_report(config={"odd": Unprintable()}), path)
    assert path.read_bytes() == before


def _table_text(rep: RunReport) -> str:
    console = Console(width=200, record=True, color_system=None)
    console.print(summary_table(rep))
    return console.export_text()


def _row(text: str, label: str) -> str:
    (line,) = [ln for ln in text.splitlines() if f" {label} " in ln]
    return line


def test_summary_table_shows_the_headline_numbers():
    text = _table_text(_report())
    assert "recon run: scène 1" in text
    assert "ok" in _row(text, "status")
    assert "4 / 1" in _row(text, "images (usable / skipped)")
    assert "3 / 4" in _row(text, "registered images")
    assert "450" in _row(text, "3D points")
    assert "3.20" in _row(text, "mean track length (model)")
    assert "3.10 / 2.00" in _row(text, "mean track length (graph, consistent tracks, merged / unmerged)")
    assert "25 %" in _row(text, "observations in inconsistent graph tracks")
    assert "0.840" in _row(text, "mean reprojection error (px)")
    assert "0.902" in _row(text, "before the final cauchy adjustment (scale 0.41 px)")
    assert "200 / 220 (median 0.38 px)" in _row(text, "observations re-localised by track refinement")
    assert "2 / 1" in _row(text, "pairs (computed / cached)")
    assert "2 / 3" in _row(text, "pairs verified")
    assert "50 % (none in 1 pair)" in _row(text, "verified inliers a third image confirms")
    assert "9.5" in _row(text, "match (s)") and "12.2" in _row(text, "total (s)")
    assert "812" in _row(text, "peak memory (MB)")


def test_summary_table_names_the_mapping_attempts_only_when_retried():
    assert "mapping attempts" not in _table_text(_report(sfm_attempts=[{"seed": 0, "registered": 3, "chosen": True}]))
    text = _table_text(_report(sfm_attempts=[{"seed": 0, "registered": 9, "chosen": False},
                                             {"seed": 1, "registered": 10, "chosen": True}]))
    assert "0: 9, 1: 10 (kept)" in _row(text, "mapping attempts (seed: images)")


def test_summary_table_of_a_run_without_model():
    rep = _report(status="no_model", message="no model", mean_reprojection_error=None, registered_images=0,
                  tracks={"merged": {"mean_length": 2.0}, "unmerged": {"mean_length": 2.0}})
    text = _table_text(rep)
    assert "no_model" in _row(text, "status")
    assert _row(text, "mean reprojection error (px)").split()[-2] == "-"
    assert "inconsistent" not in text  # the share row only when some observations are inconsistent
    assert "track refinement" not in _table_text(_report(merge={"track_refine": None}))  # off: no row
    assert "2.00 / 2.00" in text  # mean_length stands in when consistent_mean_length is absent


def test_schema_version_versions_and_the_documented_schema():
    """Every key of report.json and of a pair row is in docs/report-schema.md, with the versions."""
    import re
    from pathlib import Path

    from recon.core.report import SCHEMA_VERSION

    data = _report().to_dict()
    assert data["schema_version"] == SCHEMA_VERSION == 3
    assert set(data["versions"]) == {"recon", "python", "pycolmap", "opencv", "numpy"}
    import pycolmap

    assert data["versions"]["pycolmap"] == pycolmap.__version__
    doc = (Path(__file__).resolve().parents[1] / "docs" / "report-schema.md").read_text(encoding="utf-8")
    documented = set(re.findall(r"`([a-zA-Z0-9_]+)`", doc))
    assert set(data) <= documented, set(data) - documented
    assert set(data["pairs"][0]) <= documented, set(data["pairs"][0]) - documented
    assert "config" not in data["pairs"][0]  # no clash with the top-level config


def test_version_1_reports_are_read_as_the_current_schema(tmp_path):
    """A report written before schema 2 (pair `config`, no versions, growth without initial_pair)."""
    from recon.core.report import read_report

    old = _report().to_dict()
    del old["schema_version"], old["versions"]
    for p in old["pairs"]:
        p["config"] = p.pop("two_view_config")
    for g in old["sfm_growth"]:
        g.pop("initial_pair", None)
    path = tmp_path / "report.json"
    path.write_text(json.dumps(old, default=float), encoding="utf-8")
    rep = read_report(path)
    assert rep.schema_version == 1 and rep.versions == {}
    assert rep.pairs[0].two_view_config == "CALIBRATED" and rep.sfm_growth[0]["initial_pair"] is None
    write_report(_report(), path)  # the current version reads back unchanged
    assert read_report(path) == _report()


def test_a_real_run_names_its_initial_pair_and_writes_absolute_paths(corner_sift_run):
    """report.json of a real run (the rendered corner, SIFT): the current schema, the initial pair of the
    model named on its first growth step (two registered images, the second is `image`)."""
    from pathlib import Path

    out, rep, _ = corner_sift_run
    data = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert data["schema_version"] == 3 and data["versions"]["recon"]
    assert Path(data["out"]).is_absolute() and Path(data["scene"]).is_absolute()
    assert Path(data["out"]) == out.resolve()
    first = data["sfm_growth"][0]
    assert first["registered_images"] == 2 and len(first["initial_pair"]) == 2
    assert first["image"] in first["initial_pair"] and set(first["initial_pair"]) <= set(data["registered"])
    assert all(g["initial_pair"] is None for g in data["sfm_growth"][1:] if g["model"] == first["model"])
    assert all("two_view_config" in p and "config" not in p for p in data["pairs"])
    assert any(p["two_view_config"] for p in data["pairs"])


def test_rerun_summary_names_the_final_adjustment_when_it_ran():
    from recon.viz.rerun_log import summary_markdown

    assert "| before the final cauchy adjustment (scale 0.41 px) | 0.902 |" in summary_markdown(_report())
    assert "before the final" not in summary_markdown(_report(final_ba={"loss": "none", "applied": False}))
    with_outliers = _report(final_ba={"loss": "cauchy", "applied": True, "scale_px": 0.4123, "auto_scale": True,
                                      "mean_reprojection_error_before": 0.902, "outlier_threshold_px": 1.1,
                                      "second_scale_px": 0.3667, "outliers_dropped": 57})
    assert "(scale 0.41 px, 57 observations over 1.10 px dropped) | 0.902 |" in summary_markdown(with_outliers)


def test_summaries_say_what_the_final_adjustment_did_with_the_principal_point():
    from recon.viz.rerun_log import summary_markdown

    def with_pp(**pp) -> RunReport:
        return _report(final_ba={"loss": "cauchy", "applied": True, "scale_px": 0.4123, "auto_scale": True,
                                 "mean_reprojection_error_before": 0.902, **pp})

    freed = with_pp(principal_point="auto", principal_point_refined=True, principal_point_sigma=3.6e-5)
    kept = with_pp(principal_point="auto", principal_point_refined=False, principal_point_sigma=0.0176)
    undetermined = with_pp(principal_point="auto", principal_point_refined=False, principal_point_sigma=None)
    assert "| principal point (auto) | refined (sd 0.0036 % of the image, limit 0.2 %) |" in summary_markdown(freed)
    assert "| principal point (auto) | fixed at the image centre (sd 1.8 % of the image, limit 0.2 %) |" \
        in summary_markdown(kept)
    assert "fixed at the image centre (the views do not determine it)" in summary_markdown(undetermined)
    assert "| principal point (fixed) | fixed at the image centre |" in summary_markdown(
        with_pp(principal_point="fixed", principal_point_refined=False))
    assert "principal point" not in summary_markdown(_report())  # a report of before the field
    console = Console(record=True, width=160)
    console.print(summary_table(freed))
    text = console.export_text()
    assert "principal point (auto)" in text and "refined (sd 0.0036 % of the image" in text
