"""Rerun logging (`recon run --rerun`, `recon match --rerun`, `recon view`): read the recording back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")

from recon.cli import main  # noqa: E402
from recon.viz.rerun_log import camera_entity, coarse_grid, heatmap_image, pair_entity, parse_sink  # noqa: E402


def _columns(rrd: Path) -> dict[str, set[str]]:
    """{entity path: column names} of the recording store in `rrd`."""
    from rerun.chunk import RrdReader

    cols: dict[str, set[str]] = {}
    for c in RrdReader(rrd).stream().to_chunks():
        cols.setdefault(str(c.entity_path), set()).update(c.to_record_batch().schema.names)
    return cols


@pytest.fixture()
def scene(corner_wide_scene) -> Path:
    """corner-wide at 480 x 360, rendered once per session (conftest)."""
    return corner_wide_scene


@pytest.fixture(scope="module")
def runs(corner_wide_cli_run, tmp_path_factory) -> dict:
    """The session's fresh run with the default sink (it built the model, so it recorded the
    growth replay; conftest), then two copies of its output run again: one without its
    recording and with --rerun none, one with the default sink (all reused)."""
    import shutil

    scene = corner_wide_cli_run["scene"]
    base = tmp_path_factory.mktemp("rr")
    out_none, out = base / "out-none", base / "out"
    shutil.copytree(corner_wide_cli_run["out"], out_none)
    (out_none / "recording.rrd").unlink()
    rc_none = main(["run", str(scene), "--out", str(out_none), "--no-progress", "--rerun", "none"])
    rrds_after_none = sorted(p.name for p in out_none.rglob("*.rrd"))
    rc_save = corner_wide_cli_run["rc"]
    shutil.copytree(corner_wide_cli_run["out"], out)
    fresh = _columns(out / "recording.rrd")
    rc_reused = main(["run", str(scene), "--out", str(out), "--no-progress"])
    return {"out": out, "rc_none": rc_none, "rrds_after_none": rrds_after_none, "rc_save": rc_save,
            "rc_reused": rc_reused, "fresh_columns": fresh,
            "report": json.loads((out / "report.json").read_text(encoding="utf-8"))}


@pytest.mark.slow
def test_rerun_none_writes_no_recording(runs):
    assert runs["rc_none"] == 0
    assert runs["rrds_after_none"] == []


@pytest.mark.slow
def test_run_recording_has_model_pairs_plots_and_summary(runs):
    assert runs["rc_save"] == 0
    out, report = runs["out"], runs["report"]
    rrd = out / "recording.rrd"
    assert rrd.is_file() and rrd.stat().st_size > 0
    assert not list(out.glob(".*tmp-*"))  # the temporary file was moved into place
    cols = _columns(rrd)
    assert report["registered"], report
    for name in report["registered"]:  # every registered image: pose, intrinsics, picture
        ent = camera_entity(name)
        assert {"Transform3D:translation", "Transform3D:mat3x3", "Transform3D:relation"} <= cols[f"/{ent}"]
        assert {"Pinhole:image_from_camera", "Pinhole:resolution", "EncodedImage:blob"} <= cols[f"/{ent}/image"]
    assert {"Points3D:positions", "Points3D:colors", "reprojection_error", "track_length"} <= cols["/world/points"]
    assert len(report["pairs"]) == 6
    for p in report["pairs"]:  # every pair: match picture, Markdown info, COLMAP verdict
        base = "/" + pair_entity(p["image0"], p["image1"])
        assert "EncodedImage:blob" in cols[f"{base}/matches/images"]
        assert "LineStrips2D:strips" in cols[f"{base}/matches/inliers"]
        assert "LineStrips2D:strips" in cols[f"{base}/matches/outliers"]
        assert "TextDocument:text" in cols[f"{base}/info"]
        assert {"verified_inliers", "confirmed_inliers"} <= cols[f"{base}/verified"]
    for k in ("raw_matches", "inliers", "verified_inliers"):
        assert {"Scalars:scalars", "pair"} <= cols[f"/plots/pair/{k}"]
    assert {"Scalars:scalars", "pair"} <= cols["/plots/pair_seconds/seconds"]  # its own plot: not on the counts' axis
    assert "/plots/pair/seconds" not in cols
    assert "TextDocument:text" in cols["/summary"]

    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    assert reader.blueprints(), "the default blueprint is sent with the recording"
    # the camera pose is COLMAP's cam_from_world, logged as the child-from-parent relation
    import pycolmap

    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    img = next(iter(model.images.values()))
    chunk = next(c for c in reader.stream().to_chunks()
                 if str(c.entity_path) == f"/{camera_entity(img.name)}"
                 and "Transform3D:translation" in c.to_record_batch().schema.names)
    batch = chunk.to_record_batch()
    t = np.asarray(batch.column("Transform3D:translation").to_pylist()[0]).reshape(-1)
    np.testing.assert_allclose(t, img.cam_from_world().translation, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_growth_replay_and_plots(runs):
    """The fresh run records the model growing image by image; the reused run rebuilds that
    replay from report.json and keeps the plots."""
    report = runs["report"]
    growth = report["sfm_growth"]
    assert runs["rc_reused"] == 0 and report["model_reused"]
    assert [g["step"] for g in growth] == list(range(len(growth)))
    assert growth[0]["registered_images"] == 2  # the initial pair
    assert growth[-1]["registered_images"] == report["registered_images"]
    # one step per registration after the pair, each naming a different registered image
    assert len(growth) == report["registered_images"] - 1
    assert len({g["image"] for g in growth}) == len(growth) and {g["image"] for g in growth} <= set(report["registered"])
    assert [g["registered_images"] for g in growth] == list(range(2, report["registered_images"] + 1))
    fresh = runs["fresh_columns"]
    for name in report["registered"]:
        ent = f"/growth/cameras/{name}"
        assert {"Transform3D:translation", "registration"} <= fresh[ent]
        assert "Pinhole:image_from_camera" in fresh[f"{ent}/image"]
    assert {"Points3D:positions", "registration"} <= fresh["/growth/points"]
    assert "TextDocument:text" in fresh["/growth/info"]
    reused = _columns(runs["out"] / "recording.rrd")
    for name in report["registered"]:  # the reused model's replay, rebuilt from report.json
        assert {"Transform3D:translation", "registration"} <= reused[f"/growth/cameras/{name}"]
    assert {"Points3D:positions", "registration"} <= reused["/growth/points"]
    for ent in ("/plots/growth/registered_images", "/plots/growth/points3D", "/plots/bars/verified_inliers"):
        assert any(c.startswith("BarChart:") for c in reused[ent])


@pytest.mark.slow
def test_match_logs_one_pair_with_coarse_heatmap(scene, tmp_path):
    imgs = sorted((scene / "images").iterdir())[:2]
    rrd = tmp_path / "pair.rrd"
    # the paper's variant always runs the coarse grid (the adaptive default may match two close
    # views on their originals alone, with no coarse search and so no heat map)
    assert main(["match", str(imgs[0]), str(imgs[1]), "--variant", "paper", "--rerun", f"save:{rrd}"]) == 0
    cols = _columns(rrd)
    base = "/" + pair_entity(imgs[0].name, imgs[1].name)
    assert "EncodedImage:blob" in cols[f"{base}/matches/images"]
    assert "LineStrips2D:strips" in cols[f"{base}/matches/inliers"]
    assert "TextDocument:text" in cols[f"{base}/info"]
    assert "EncodedImage:blob" in cols[f"{base}/coarse"]
    assert any(c.startswith("Tensor:") for c in cols[f"{base}/coarse_scores"])


def test_coarse_grid_marks_the_chosen_view():
    from matching.types import CoarseScore, PairResult, ViewParams

    views = [ViewParams(1.0, 0.0), ViewParams(2.0, 0.0), ViewParams(2.0, 45.0), ViewParams(2.0, 90.0)]
    r = PairResult.empty("x", "")
    r.coarse_scores = [CoarseScore(v, m, 0, float(m)) for v, m in zip(views, (5, 9, 30, 2))]
    r.best_views = [views[2]]
    grid, labels, chosen = coarse_grid(r)
    assert grid.shape == (2, 3) and np.isnan(grid[0, 1]) and grid[1, 1] == 30
    assert labels == ["t=1.00", "t=2.00"] and chosen == [(1, 1)]
    assert heatmap_image(grid, chosen, cell=10).shape == (20, 30, 3)


def test_sink_parsing_and_view_errors(tmp_path, monkeypatch, capsys):
    assert parse_sink("save", tmp_path / "r.rrd").target == str(tmp_path / "r.rrd")
    assert parse_sink("save:x.rrd").target == "x.rrd"
    assert parse_sink("connect").kind == "connect" and not parse_sink("none").enabled
    with pytest.raises(ValueError):
        parse_sink("bogus")
    with pytest.raises(ValueError):
        parse_sink("save")  # recon match: no default file
    # recon view: a folder without a recording, then a missing viewer: one-line errors, exit 2
    assert main(["view", str(tmp_path)]) == 2
    assert "no recording.rrd" in capsys.readouterr().err
    (tmp_path / "recording.rrd").write_bytes(b"")
    monkeypatch.setattr("recon.viz.rerun_log.find_viewer", lambda: None)
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "Rerun viewer" in err and len(err.splitlines()) == 1


@pytest.mark.slow
def test_a_failing_sink_never_costs_the_reconstruction(scene, tmp_path, capsys):
    """The recording cannot be written (its folder is a file): one warning, logging stops, and
    the run still ends with its model and report."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "--no-progress", "--rerun", f"save:{blocker}/rec.rrd"]) == 0
    err = capsys.readouterr().err
    assert err.count("Rerun logging stopped") == 1
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["status"] == "ok" and report["registered_images"] == report["num_images"]
    assert (out / "sparse" / "0").is_dir()
