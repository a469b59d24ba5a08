"""Scene scanning (recon.core.scene) and pair lists (recon.core.pairs)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from matching.errors import InputError
from matching.io import resize_max
from recon.core.pairs import check_pairs_names, make_pairs, parse_pairs_spec, split_pairs_line
from recon.core.scene import find_image_dir, require_images, scan_scene, to_full_res
from recon.errors import UserError


def _img(seed: int, w: int = 120, h: int = 90) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 6, w // 6, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _write(path: Path, img: np.ndarray) -> None:
    ext = path.suffix.lower()
    ok, buf = cv2.imencode(ext if ext in (".png", ".jpg", ".tif", ".tiff", ".jpeg") else ".png", img)
    assert ok
    path.write_bytes(buf.tobytes())


def test_images_folder_preferred_and_extensions_any_case(tmp_path):
    (tmp_path / "images").mkdir()
    _write(tmp_path / "images" / "a.JPG", _img(1))
    _write(tmp_path / "images" / "b.Png", _img(2))
    _write(tmp_path / "images" / "c.TIFF", _img(3))
    _write(tmp_path / "images" / "d.jpeg", _img(4))
    _write(tmp_path / "ignored.png", _img(5))  # the scene root is not scanned when images/ exists
    assert find_image_dir(tmp_path) == tmp_path / "images"
    scene, grays = scan_scene(tmp_path, max_size=None)
    assert scene.names == ["a.JPG", "b.Png", "c.TIFF", "d.jpeg"]
    assert not scene.skipped and not scene.warnings
    assert all(g.dtype == np.uint8 and g.ndim == 2 for g in grays.values())


def test_bad_files_are_skipped_with_one_line_reasons(tmp_path):
    _write(tmp_path / "a.png", _img(1))
    _write(tmp_path / "b.png", _img(2))
    (tmp_path / "c copy of b.png").write_bytes((tmp_path / "b.png").read_bytes())  # duplicate
    jpg = cv2.imencode(".jpg", _img(3, 400, 300))[1].tobytes()
    (tmp_path / "broken.jpg").write_bytes(jpg[: len(jpg) // 2])  # truncated JPEG
    (tmp_path / "garbage.jpg").write_bytes(b"this is not a jpeg")
    (tmp_path / "empty.png").write_bytes(b"")
    _write(tmp_path / "tiny.png", _img(4, 20, 20))
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / ".DS_Store").write_bytes(b"\0")
    (tmp_path / "sub").mkdir()
    scene, grays = scan_scene(tmp_path, max_size=None)
    assert scene.names == ["a.png", "b.png"]
    skipped = {s.name: s.reason for s in scene.skipped}
    assert set(skipped) == {"c copy of b.png", "broken.jpg", "garbage.jpg", "empty.png", "tiny.png"}
    assert "duplicate of b.png" in skipped["c copy of b.png"]
    assert "corrupt" in skipped["broken.jpg"]
    assert any("notes.txt" in w and "non-image" in w for w in scene.warnings)
    assert all("\n" not in w for w in scene.warnings)
    assert set(grays) == {"a.png", "b.png"}


def test_missing_or_empty_scene_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="no such scene folder"):
        scan_scene(tmp_path / "nope")
    (tmp_path / "images").mkdir()
    with pytest.raises(InputError, match="no images found"):
        scan_scene(tmp_path)


def test_spaces_non_ascii_and_different_sizes(tmp_path):
    d = tmp_path / "scène à voir" / "images"
    d.mkdir(parents=True)
    _write(d / "vue 1.png", _img(1, 300, 200))
    _write(d / "ünï 2.png", _img(2, 160, 120))
    scene, grays = scan_scene(d.parent, max_size=150)
    assert sorted(scene.names) == ["vue 1.png", "ünï 2.png"]
    im = scene.image("vue 1.png")
    assert (im.width, im.height) == (300, 200) and (im.work_width, im.work_height) == (150, 100)
    assert grays["vue 1.png"].shape == (100, 150)
    assert grays["ünï 2.png"].shape == (112, 150)  # 160x120 -> 150x112.5, rounded


def test_to_full_res_is_pixel_centre_correct():
    # a bright dot at a known full-res position, downscaled by INTER_AREA, found again at the
    # working resolution and mapped back, lands on the original position (sub-pixel)
    img = np.zeros((400, 600), np.uint8)
    x, y = 301.0, 150.0
    cv2.circle(img, (int(x), int(y)), 6, 255, -1)
    work, s = resize_max(img, 200)
    m = cv2.moments(work.astype(np.float32))
    cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
    sx, sy = work.shape[1] / img.shape[1], work.shape[0] / img.shape[0]
    back = to_full_res(np.array([[cx, cy]]), (sx, sy))[0]
    assert abs(back[0] - x) < 0.3 and abs(back[1] - y) < 0.3
    assert np.array_equal(to_full_res(np.array([[3.0, 4.0]]), (1.0, 1.0)), np.array([[3.0, 4.0]], np.float32))


def test_pairs_specs():
    names = ["a", "b", "c", "d"]
    ex, _ = make_pairs(parse_pairs_spec("exhaustive"), names)
    assert ex == [("a", "b"), ("a", "c"), ("a", "d"), ("b", "c"), ("b", "d"), ("c", "d")]
    seq, _ = make_pairs(parse_pairs_spec("sequential:2"), names)
    assert seq == [("a", "b"), ("a", "c"), ("b", "c"), ("b", "d"), ("c", "d")]
    for bad in ("sequential", "sequential:0", "sequential:x", "", "no/such/file.txt"):
        with pytest.raises(ValueError):
            parse_pairs_spec(bad)


def test_pairs_file(tmp_path):
    f = tmp_path / "pairs.txt"
    f.write_text('# retrieval pairs\n"my photo.jpg" b.jpg 0.9\n\nb.jpg c.jpg\nc.jpg b.jpg\n'
                 'c.jpg c.jpg\nb.jpg gone.jpg\n', encoding="utf-8")
    pairs, warnings = make_pairs(parse_pairs_spec(str(f)), ["b.jpg", "c.jpg", "my photo.jpg"])
    assert pairs == [("my photo.jpg", "b.jpg"), ("b.jpg", "c.jpg")]
    assert any("gone.jpg" in w for w in warnings) and any("repeated" in w for w in warnings)
    bad = tmp_path / "bad.txt"
    bad.write_text("onlyone.jpg\n")
    with pytest.raises(InputError, match=r"bad.txt:1"):
        make_pairs(parse_pairs_spec(str(bad)), ["onlyone.jpg"])


@pytest.mark.parametrize("line, names", [
    ("a.jpg b.jpg", ["a.jpg", "b.jpg"]),
    ("photo#2.jpg b.jpg  # a comment after whitespace", ["photo#2.jpg", "b.jpg"]),
    ("   # a whole-line comment", []),
    ("l'église.jpg 'my photo.jpg' 0.93", ["l'église.jpg", "my photo.jpg", "0.93"]),
    ('"#starts with a hash.png" b.png', ["#starts with a hash.png", "b.png"]),
    ("my photo.jpg\tother one.jpg\t0.5", ["my photo.jpg", "other one.jpg", "0.5"]),
    ("\"quoted anyway.jpg\"\tl'été.jpg\t# note", ["quoted anyway.jpg", "l'été.jpg"]),
    ("", []),
])
def test_pairs_line_syntax(line, names):
    assert split_pairs_line(line) == names


@pytest.mark.parametrize("line", ['"unclosed.jpg b.jpg', 'a.jpg "b"c.jpg', '"" b.jpg'])
def test_malformed_pairs_lines(line):
    with pytest.raises(ValueError):
        split_pairs_line(line)


def test_pairs_file_names_are_checked_before_decoding(tmp_path):
    f = tmp_path / "pairs.txt"
    f.write_text("IMG_1.JPG IMG_2.JPG\n")
    with pytest.raises(InputError, match="IMG_1.JPG"):
        check_pairs_names(parse_pairs_spec(str(f)), ["a.jpg", "b.jpg"])
    f.write_text("a.jpg a.jpg\n")
    with pytest.raises(InputError, match="twice"):
        check_pairs_names(parse_pairs_spec(str(f)), ["a.jpg", "b.jpg"])
    f.write_text("# nothing\n")
    with pytest.raises(InputError, match="no pair"):
        check_pairs_names(parse_pairs_spec(str(f)), ["a.jpg", "b.jpg"])
    f.write_text("a.jpg gone.jpg\nb.jpg a.jpg\n")  # one usable pair is enough (the other is dropped later)
    check_pairs_names(parse_pairs_spec(str(f)), ["a.jpg", "b.jpg"])
    check_pairs_names(parse_pairs_spec("exhaustive"), [])


def test_require_images_and_entries_that_are_not_files(tmp_path):
    import os

    with pytest.raises(InputError, match="no images"):
        require_images(tmp_path)
    _write(tmp_path / "a.png", _img(0))
    with pytest.raises(UserError, match="at least 2"):
        require_images(tmp_path)
    _write(tmp_path / "b.png", _img(1))
    (tmp_path / "dir.png").mkdir()
    (tmp_path / "gone.jpg").symlink_to(tmp_path / "nowhere.jpg")
    os.mkfifo(tmp_path / "pipe.jpg")
    image_dir, names = require_images(tmp_path)
    assert image_dir == tmp_path and names == ["a.png", "b.png"]
    scene, _ = scan_scene(tmp_path, max_size=None)
    assert scene.names == ["a.png", "b.png"]
    (w,) = [w for w in scene.warnings if "not a file" in w]
    assert "dir.png (a folder)" in w and "gone.jpg (broken symbolic link)" in w and "pipe.jpg (not a regular file)" in w
