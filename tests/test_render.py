"""The scene renderer: determinism, ground truth consistent with the pixels, extreme angles."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest

from matching.errors import InputError
from recon.cli import main
from recon.eval.gt import read_colmap_text
from scenes.presets import PRESETS, get_preset
from scenes.render import H_img_from_tex, intrinsics, render_scene

SMALL = (320, 240)


def _digest(scene) -> str:
    return hashlib.sha1(b"".join(p.read_bytes() for p in scene.image_paths)).hexdigest()


@pytest.mark.slow
def test_same_seed_same_bytes_other_seed_other_images(tmp_path):
    a = render_scene(tmp_path / "a", "corner-wide", seed=3, image_size=SMALL)
    b = render_scene(tmp_path / "b", "corner-wide", seed=3, image_size=SMALL)
    c = render_scene(tmp_path / "c", "corner-wide", seed=4, image_size=SMALL)
    assert _digest(a) == _digest(b) != _digest(c)


def test_ground_truth_parses_back_to_the_rendered_poses(tmp_path):
    scene = render_scene(tmp_path / "s", "corner", seed=0, image_size=SMALL)
    gt = read_colmap_text(scene.out_dir / "gt")
    assert sorted(gt) == [p.name for p in scene.image_paths]
    for path, P in zip(scene.image_paths, scene.cam_from_world):
        cam = gt[path.name]
        np.testing.assert_allclose(cam.cam_from_world, P, atol=1e-9)
        np.testing.assert_allclose(cam.K, scene.K, atol=1e-6)  # both in OpenCV's convention
        assert cam.size == SMALL


def test_texture_homography_agrees_with_projecting_the_3d_point():
    p = get_preset("corner")
    from scenes.render import camera_centres, look_at_pose

    P = look_at_pose(camera_centres(p)[2], np.asarray(p.cameras.look_at))
    K = intrinsics(p)
    plane = p.planes[0]
    a, b = 123.0, 45.0  # a texture pixel: column a, row b (row 0 at the top of the plane)
    X = (np.asarray(plane.origin) + (a + 0.5) / p.px_per_m * np.asarray(plane.u)
         + (plane.height - (b + 0.5) / p.px_per_m) * np.asarray(plane.v))
    x = K @ (P[:, :3] @ X + P[:, 3])
    H = H_img_from_tex(K, P, plane, p.px_per_m)
    y = H @ [a, b, 1.0]
    np.testing.assert_allclose(y[:2] / y[2], x[:2] / x[2], atol=1e-6)


@pytest.mark.slow
def test_a_marked_world_point_is_drawn_where_the_ground_truth_projects_it(tmp_path):
    """Texture every plane with a photo that has one bright dot, then find the dot in the image."""
    tex = np.full((400, 400, 3), 60, np.uint8)
    cv2.circle(tex, (200, 200), 12, (255, 255, 255), -1)
    tex_path = tmp_path / "dot.png"
    cv2.imwrite(str(tex_path), tex)
    scene = render_scene(tmp_path / "s", "corner", textures=[tex_path], seed=0)
    p = get_preset("corner")
    wall = p.planes[1]  # wall_b: its copy of the photo is mirrored, which keeps a centred dot in place
    X = wall.centre  # the dot sits at the texture's centre
    P = scene.cam_from_world[0]
    x = scene.K @ (P[:, :3] @ X + P[:, 3])
    u, v = x[:2] / x[2]
    img = cv2.imread(str(scene.image_paths[0]), cv2.IMREAD_GRAYSCALE)
    ys, xs = np.nonzero(img > 200)
    near = np.hypot(xs - u, ys - v) < 40
    assert near.sum() > 20
    assert np.hypot(xs[near].mean() - u, ys[near].mean() - v) < 2.0


def test_extreme_presets_reach_grazing_viewing_angles(tmp_path):
    scene = render_scene(tmp_path / "s", "facade-extreme", seed=0, image_size=SMALL)
    angles = [a for d in scene.viewing_angles_deg for a in d.values()]
    assert max(angles) >= 75.0
    assert get_preset("facade-extreme").azimuth_step >= 50.0
    assert get_preset("facade-7x80").cameras.azimuths_deg[0] == pytest.approx(10.0)
    with pytest.raises(ValueError, match="unknown preset"):
        get_preset("nope")


def test_procedural_texture_gives_sift_plenty_of_features(corner_scene):
    img = cv2.imread(str(corner_scene / "images" / "view_00.png"), cv2.IMREAD_GRAYSCALE)  # 480 x 360
    assert len(cv2.SIFT_create().detect(img, None)) >= 200


@pytest.mark.slow
def test_cli_renders_and_rejects_bad_input(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["render-scene", str(out), "--preset", "corner-wide"]) == 0
    assert len(list((out / "images").glob("*.png"))) == len(PRESETS["corner-wide"].cameras.azimuths_deg)
    assert (out / "gt" / "cameras.txt").exists() and (out / "gt" / "images.txt").exists()
    capsys.readouterr()
    assert main(["render-scene", str(out), "--preset", "corner-wide"]) == 2  # exists, no --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["render-scene", str(tmp_path / "x"), "--preset", "bogus"]) == 2
    err = capsys.readouterr().err
    assert "unknown preset" in err and len(err.strip().splitlines()) == 1
    assert main(["render-scene", str(tmp_path / "y"), "--texture", str(tmp_path / "missing.jpg")]) == 2
    err = capsys.readouterr().err
    assert "missing.jpg" in err and "Traceback" not in err
    assert not (tmp_path / "y").exists()  # nothing half-written


def test_pixels_match_the_ground_truth_to_a_fraction_of_a_pixel(tmp_path):
    """A 4x4-texel dot at the exact centre of a wall-shaped photo (12 m x 5 m walls = 2.4:1, so
    no crop) lands where gt/ projects the wall centre, within 0.25 px: a half-pixel slip between
    the renderer's OpenCV convention and COLMAP's (cx = w/2) would fail this."""
    tex = np.zeros((200, 480, 3), np.uint8)
    tex[98:102, 238:242] = 255  # centred on (239.5, 99.5), the photo's centre
    tex_path = tmp_path / "dot.png"
    cv2.imwrite(str(tex_path), tex)
    scene = render_scene(tmp_path / "s", "corner", textures=[tex_path], seed=0, image_size=SMALL)
    gt = read_colmap_text(scene.out_dir / "gt")
    walls = get_preset("corner").planes[:2]
    checked = 0
    for path in scene.image_paths:
        cam = gt[path.name]
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(float)
        ys, xs = np.mgrid[0:img.shape[0], 0:img.shape[1]]
        for wall in walls:
            x = cam.K @ (cam.cam_from_world[:, :3] @ wall.centre + cam.cam_from_world[:, 3])
            u, v = x[:2] / x[2]
            near = (np.hypot(xs - u, ys - v) < 6) & (img > 12)
            w = img[near] - 12
            if w.sum() < 100:  # dot hidden or too foreshortened in this view
                continue
            assert abs((xs[near] * w).sum() / w.sum() - u) < 0.25, path.name
            assert abs((ys[near] * w).sum() / w.sum() - v) < 0.25, path.name
            checked += 1
    assert checked >= 8


@pytest.mark.slow
def test_overwrite_replaces_only_images_and_gt(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    render_scene(out, "corner-wide", seed=0, image_size=SMALL)  # a non-empty OUT_DIR is fine
    (out / "images" / "stale.png").write_bytes(b"x")
    with pytest.raises(InputError, match="--overwrite"):
        render_scene(out, "corner-wide", seed=1, image_size=SMALL)
    render_scene(out, "corner-wide", seed=1, image_size=SMALL, overwrite=True)
    assert (out / "notes.txt").read_text() == "keep me"
    assert not (out / "images" / "stale.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temporary folder left


@pytest.mark.slow
def test_an_interrupted_render_leaves_the_old_scene_and_no_temporary_folder(tmp_path, monkeypatch):
    import scenes.render as render

    out = tmp_path / "scene"
    first = render_scene(out, "corner-wide", seed=0, image_size=SMALL)
    before = _digest(first)
    calls = []

    def interrupted(*args, **kwargs):
        if calls:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    real = render.render_view
    monkeypatch.setattr(render, "render_view", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_scene(out, "corner-wide", seed=5, image_size=SMALL, overwrite=True)
    assert _digest(first) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_cli_lists_presets_without_an_out_dir(capsys):
    assert main(["render-scene", "--list-presets"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in PRESETS)
    assert main(["render-scene"]) == 2
    err = capsys.readouterr().err
    assert "OUT_DIR" in err and len(err.strip().splitlines()) == 1
