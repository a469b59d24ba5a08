"""Hostile input files and folders: bad images are skipped with one warning each, unusable scenes
are refused with one line, pairs files with awkward names work, and two images give a model."""

from __future__ import annotations

import json
import os
import shutil

import cv2
import numpy as np
import pytest

from hostile_tools import FAST, Snapshot, check, recon

BAD_FILES = {  # name -> what recon must say about it
    "zero.png": "empty file",
    "truncated.jpg": "not a readable image",
    "text.jpg": "not a readable image",
    "tiny.png": "must be at least",
    "dir.png": "a folder",
    "gone.jpg": "broken symbolic link",
    "pipe.jpg": "not a regular file",  # reading a FIFO would block for ever
}


def test_a_scene_full_of_bad_files_still_reconstructs(scene, tmp_path):
    images = scene / "images"
    good = sorted(images.iterdir())
    good[0].rename(images / "vue été ü ☃.png")  # unicode and spaces in a good image's name
    (images / "zero.png").write_bytes(b"")
    jpg = cv2.imencode(".jpg", cv2.imread(str(good[1])))[1].tobytes()
    (images / "truncated.jpg").write_bytes(jpg[: len(jpg) // 3])
    (images / "text.jpg").write_text("this is not a photo\n")
    cv2.imwrite(str(images / "tiny.png"), np.zeros((1, 1, 3), np.uint8))
    (images / "dir.png").mkdir()
    (images / "gone.jpg").symlink_to(tmp_path / "nowhere.jpg")
    os.mkfifo(images / "pipe.jpg")
    (images / "notes.txt").write_text("field notes")
    out = tmp_path / "out"
    snap = Snapshot(tmp_path, skip=(out,))
    res = check(recon("run", scene, "--out", out, *FAST), 0)
    for name, why in BAD_FILES.items():
        assert any(name in w and why in w for w in res.warnings), (name, res.warnings)
    assert any("notes.txt" in w for w in res.warnings)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert rep["registered_images"] == rep["num_images"] == 4
    assert "vue été ü ☃.png" in rep["registered"]
    assert {s["name"] for s in rep["skipped"]} == {"zero.png", "truncated.jpg", "text.jpg", "tiny.png"}
    snap.assert_unchanged()


def test_only_corrupt_images(tmp_path):
    d = tmp_path / "bad"
    d.mkdir()
    (d / "a.jpg").write_text("text")
    (d / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n\0\0")
    snap = Snapshot(tmp_path)
    check(recon("run", d, "--out", tmp_path / "out", *FAST), 2, text="at least 2 usable images")
    snap.assert_unchanged()


def test_a_single_image(scene, tmp_path):
    d = tmp_path / "one"
    d.mkdir()
    shutil.copy(sorted((scene / "images").iterdir())[0], d)
    snap = Snapshot(tmp_path)
    check(recon("run", d, *FAST), 2, text="at least 2 images")
    snap.assert_unchanged()  # no d/recon left behind


def test_scene_is_a_file(tmp_path):
    (tmp_path / "scene.jpg").write_text("x")
    check(recon("run", tmp_path / "scene.jpg", *FAST), 2, text="not a folder")


def test_missing_scene(tmp_path):
    check(recon("run", tmp_path / "nope", *FAST), 2, text="no such scene folder")


def test_match_a_text_file_named_jpg(scene, tmp_path):
    (tmp_path / "fake.jpg").write_text("not an image")
    img = sorted((scene / "images").iterdir())[0]
    check(recon("match", tmp_path / "fake.jpg", img, "-m", "sift"), 2, text="fake.jpg")


def test_two_images_give_a_two_view_model(scene, tmp_path):
    """COLMAP's mapper needs a third view unless two-view tracks are kept (recon.core.sfm): two
    photos (JPEG with an EXIF 35 mm focal length, as a camera writes it) give a model whose
    relative rotation matches the ground truth."""
    pytest.importorskip("PIL")
    import pycolmap
    from PIL import Image

    from recon.eval.gt import read_colmap_text

    two = tmp_path / "two"
    (two / "images").mkdir(parents=True)
    for p in sorted((scene / "images").iterdir())[:2]:
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0xA405] = 31  # FocalLengthIn35mmFilm: 286.6 px at 320 px (true: 288)
        Image.open(p).convert("RGB").save(two / "images" / f"{p.stem}.jpg", quality=95, exif=exif)
    out = tmp_path / "out"
    check(recon("run", two, "--out", out, *FAST), 0)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert rep["status"] == "ok" and rep["registered_images"] == 2 and rep["num_points3D"] > 50
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    gt = read_colmap_text(scene / "gt")
    R = {rec.image(i).name[:-4]: rec.image(i).cam_from_world().rotation.matrix() for i in rec.reg_image_ids()}
    a, b = sorted(R)
    R_est = R[b] @ R[a].T
    R_gt = gt[b + ".png"].cam_from_world[:, :3] @ gt[a + ".png"].cam_from_world[:, :3].T
    angle = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ R_gt) - 1) / 2, -1, 1)))
    # the views are 20 deg apart; a wrong two-view model is off by degrees to tens of degrees. This
    # 190-match 320 px pair measured 1.27 deg (0.91 with the plain local-affine fit in the track
    # refinement, 1.75 without track refinement; docs/decisions.md, "Robust local affines")
    assert angle < 2.0, angle


def test_pairs_file_with_hash_apostrophe_spaces_and_tabs(scene, tmp_path):
    images = scene / "images"
    old = sorted(p.name for p in images.iterdir())
    new = ["view #1.png", "l'image 2.png", "d'été#3.png", "plain 4.png"]
    for a, b in zip(old, new):
        (images / a).rename(images / b)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text('# pairs from retrieval\n'
                     '"view #1.png" "l\'image 2.png"  # a comment after whitespace\n'
                     'd\'été#3.png "plain 4.png" 0.87\n'
                     "view #1.png\td'été#3.png\n"
                     "\"l'image 2.png\"\t'plain 4.png'\n"
                     "'view #1.png' 'plain 4.png'\n", encoding="utf-8")
    out = tmp_path / "out"
    snap = Snapshot(tmp_path, skip=(out,))
    res = check(recon("run", scene, "--out", out, *FAST, "--pairs", pairs), 0)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    got = [(p["image0"], p["image1"]) for p in rep["pairs"]]
    assert got == [("view #1.png", "l'image 2.png"), ("d'été#3.png", "plain 4.png"),
                   ("view #1.png", "d'été#3.png"), ("l'image 2.png", "plain 4.png"),
                   ("view #1.png", "plain 4.png")], (got, res.warnings)
    assert rep["registered_images"] == 4
    snap.assert_unchanged()


def test_a_malformed_pairs_file_is_refused_before_any_image_is_decoded(scene, tmp_path):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("view_00.png view_01.png\n\"unclosed.png view_02.png\n")
    out = tmp_path / "out"
    check(recon("run", scene, "--out", out, *FAST, "--pairs", pairs, inject=True,
                env={"RECON_HOSTILE": "load:SIGTERM"}), 2, text="pairs.txt:2")  # no decode: no signal
    assert not out.exists()


def test_a_pairs_file_naming_no_image_of_the_scene(scene, tmp_path):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("IMG_0001.JPG IMG_0002.JPG\n")
    out = tmp_path / "out"
    check(recon("run", scene, "--out", out, *FAST, "--pairs", pairs), 2, text="IMG_0001.JPG")
    assert not out.exists()
