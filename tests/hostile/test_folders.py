"""Output folders: foreign folders are refused untouched, one run per folder (the lock), nothing
left behind by a refused command, and a scene can be fixed after a failed run."""

from __future__ import annotations

import json
import os
import shutil

import pytest

from hostile_tools import FAST, Snapshot, check, finish, model_figures, recon, start, wait_for


def _colmap_folder(d):
    """What a plain COLMAP project looks like: database.db, sparse/0 and sparse/1, images."""
    (d / "sparse" / "0").mkdir(parents=True)
    (d / "sparse" / "1").mkdir(parents=True)
    for sub in ("0", "1"):
        (d / "sparse" / sub / "cameras.bin").write_bytes(os.urandom(64))
    (d / "database.db").write_bytes(b"SQLite format 3\0" + os.urandom(4000))
    return d


@pytest.mark.parametrize("overwrite", [False, True], ids=["plain", "overwrite"])
def test_a_colmap_folder_is_never_touched(scene, tmp_path, overwrite):
    out = _colmap_folder(tmp_path / "colmap")
    snap = Snapshot(tmp_path)
    res = check(recon("run", scene, "--out", out, *FAST, *(["--overwrite"] if overwrite else [])), 2,
                text="COLMAP project")
    assert "database.db" in res.error_lines[0]
    snap.assert_unchanged()


def test_a_folder_of_user_files_is_refused(scene, tmp_path):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"\xff\xd8 not really")
    (out / "cache").mkdir()
    snap = Snapshot(tmp_path)
    check(recon("run", scene, "--out", out, *FAST, "--overwrite"), 2, text="not a recon output folder")
    snap.assert_unchanged()


def test_a_file_as_out(scene, tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    snap = Snapshot(tmp_path)
    check(recon("run", scene, "--out", tmp_path / "notes.txt", *FAST), 2, text="not a folder")
    snap.assert_unchanged()


def test_out_below_a_file_says_not_a_folder(scene, tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    snap = Snapshot(tmp_path)
    res = check(recon("run", scene, "--out", tmp_path / "notes.txt" / "sub", *FAST), 2, text="not a folder")
    assert "read-only" not in res.err
    snap.assert_unchanged()


def test_read_only_out_parent(scene, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o555)
    try:
        snap = Snapshot(tmp_path)
        check(recon("run", scene, "--out", ro / "out", *FAST), 2, text="read-only")
        snap.assert_unchanged()
    finally:
        os.chmod(ro, 0o755)


def test_compare_into_a_file(scene, tmp_path):
    (tmp_path / "cmp").write_text("mine")
    snap = Snapshot(tmp_path)
    check(recon("compare", scene, "--out", tmp_path / "cmp", "--max-size", "320", "--rerun", "none"), 2,
          text="not a folder")
    snap.assert_unchanged()


def test_compare_on_an_empty_folder_leaves_nothing_behind(tmp_path):
    (tmp_path / "empty").mkdir()
    snap = Snapshot(tmp_path)
    check(recon("compare", tmp_path / "empty", "--max-size", "320", "--rerun", "none"), 2, text="no images")
    snap.assert_unchanged()  # no compare/ and no compare/stock-default/


def test_render_overwrite_never_deletes_user_photos(scene, tmp_path):
    user = tmp_path / "user"
    shutil.copytree(scene / "images", user / "images")  # the user's photos, not made by render-scene
    snap = Snapshot(tmp_path, skip=(scene,))
    check(recon("render-scene", user, "--preset", "corner-wide", "--overwrite"), 2, text="did not make")
    snap.assert_unchanged()


def test_a_second_run_into_the_same_folder_is_refused_while_the_first_runs(scene, tmp_path):
    out = tmp_path / "out"
    flag = tmp_path / "flag"
    first = start("run", scene, "--out", out, *FAST, inject=True,
                  env={"RECON_HOSTILE": "match:pause", "RECON_HOSTILE_FLAG": str(flag)})
    try:
        wait_for(flag.with_name("flag.paused"), first)
        snap = Snapshot(tmp_path, skip=(out,))
        second = check(recon("run", scene, "--out", out, *FAST), 2, text="another recon run is using")
        assert f"pid {first.pid}" in second.error_lines[0]
        over = check(recon("run", scene, "--out", out, *FAST, "--overwrite"), 2, text="another recon run")
        assert over.rc == 2
        snap.assert_unchanged()
    finally:
        flag.with_name("flag.go").touch()
    res = check(finish(first), 0)
    rep = json.loads((out / "report.json").read_text())
    assert rep["status"] == "ok" and rep["registered_images"] == rep["num_images"], res.err


def test_fixing_the_scene_after_a_failed_run(scene, tmp_path, reference):
    """A failed (here: terminated) run pins nothing: removing the corrupt file and adding the
    missing photo is accepted without --overwrite, and the cached pairs are reused."""
    names = sorted(p.name for p in (scene / "images").iterdir())
    out, aside = tmp_path / "out", tmp_path / "aside"
    aside.mkdir()
    shutil.move(scene / "images" / names[-1], aside / names[-1])
    (scene / "images" / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    check(recon("run", scene, "--out", out, *FAST, inject=True, env={"RECON_HOSTILE": "sfm:SIGTERM"}), 143)
    (scene / "images" / "broken.png").unlink()
    shutil.move(aside / names[-1], scene / "images" / names[-1])
    res = check(recon("run", scene, "--out", out, *FAST), 0)
    rep = json.loads((out / "report.json").read_text())
    assert rep["pairs_cached"] == 3 and rep["pairs_computed"] == 3, res.err  # the first three images' pairs
    assert model_figures(rep) == model_figures(reference)


def test_a_finished_model_is_not_silently_replaced_by_another_image_list(scene, tmp_path):
    out = tmp_path / "out"
    check(recon("run", scene, "--out", out, *FAST), 0)
    gone = sorted((scene / "images").iterdir())[-1]
    gone.unlink()
    before = Snapshot(out, ignore=(".recon.lock",))  # the lock file records each run's pid
    check(recon("run", scene, "--out", out, *FAST), 2, text="--overwrite")
    before.assert_unchanged()


def test_overwrite_keeps_the_match_cache_unless_clean_cache(scene, tmp_path):
    out = tmp_path / "out"
    check(recon("run", scene, "--out", out, *FAST), 0)
    check(recon("run", scene, "--out", out, *FAST, "--overwrite"), 0)
    rep = json.loads((out / "report.json").read_text())
    assert rep["pairs_computed"] == 0 and rep["pairs_cached"] == len(rep["pairs"])
    check(recon("run", scene, "--out", out, *FAST, "--overwrite", "--clean-cache"), 0)
    rep = json.loads((out / "report.json").read_text())
    assert rep["pairs_cached"] == 0 and rep["pairs_computed"] == len(rep["pairs"])
