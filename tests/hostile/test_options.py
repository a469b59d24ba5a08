"""Bad option values: refused before any work with one line and exit 2; nothing is created."""

from __future__ import annotations

import pytest

from hostile_tools import Snapshot, check, recon

RUN_BAD = [
    (["--seed", "2147483648"], "--seed"),  # used to overflow in every pair, then a pycolmap TypeError
    (["--seed", "-1"], "--seed"),
    (["--max-size", "10"], "--max-size"),
    (["--camera-mode", "fisheye"], "--camera-mode"),
    (["--pairs", "sequential:0"], "sequential:K"),
    (["--merge-px", "nan"], "--merge-px"),
    (["--workers", "-2"], "--workers"),
    (["--method", "surf"], "surf"),
    (["--rerun", "bogus"], "--rerun"),
    (["--bogus-flag"], "No such option"),
]


@pytest.mark.parametrize("args, text", RUN_BAD, ids=[a[0] + "=" + (a[1] if len(a) > 1 else "") for a, _ in RUN_BAD])
def test_run_refuses_bad_option_before_any_work(scene, tmp_path, args, text):
    snap = Snapshot(tmp_path)
    check(recon("run", scene, "--out", tmp_path / "out", "--no-progress", *args), 2, text=text)
    assert not (tmp_path / "out").exists()
    snap.assert_unchanged()


def test_run_without_scene_argument(tmp_path):
    check(recon("run", cwd=tmp_path), 2, text="Missing argument")


def test_match_save_vis_needs_an_image_extension(scene, tmp_path):
    imgs = sorted((scene / "images").iterdir())
    check(recon("match", imgs[0], imgs[1], "-m", "sift", "--save-vis", tmp_path / "out.xyz"), 2, text=".xyz")
    assert not (tmp_path / "out.xyz").exists()


def test_match_json_into_a_folder(scene, tmp_path):
    imgs = sorted((scene / "images").iterdir())
    (tmp_path / "jsondir").mkdir()
    snap = Snapshot(tmp_path)
    check(recon("match", imgs[0], imgs[1], "-m", "sift", "--json", tmp_path / "jsondir"), 2, text="is a folder")
    snap.assert_unchanged()


def test_match_json_through_a_file(scene, tmp_path):
    imgs = sorted((scene / "images").iterdir())
    (tmp_path / "afile").write_text("x")
    snap = Snapshot(tmp_path)
    check(recon("match", imgs[0], imgs[1], "-m", "sift", "--json", tmp_path / "afile" / "r.json"), 2,
          text="not a folder")
    snap.assert_unchanged()


def test_match_threshold_must_be_positive(scene):
    imgs = sorted((scene / "images").iterdir())
    check(recon("match", imgs[0], imgs[1], "-m", "sift", "--th", "0"), 2, text="--th")


def test_compare_unknown_preset(scene, tmp_path):
    check(recon("compare", scene, "--out", tmp_path / "cmp", "--stock-preset", "ultra", "--rerun", "none"), 2,
          text="ultra")
    assert not (tmp_path / "cmp").exists()


def test_render_unknown_preset(tmp_path):
    check(recon("render-scene", tmp_path / "r", "--preset", "bogus"), 2, text="unknown preset")
    assert not (tmp_path / "r").exists()


def test_bench_pairs_json_into_a_folder(tmp_path):
    (tmp_path / "data").mkdir()
    check(recon("bench", "pairs", tmp_path / "data", "--json", tmp_path), 2, text="is a folder")
