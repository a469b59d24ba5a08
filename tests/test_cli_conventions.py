"""CLI conventions (issue 14, item 2): -h, --version, shared options spelled alike, typed choices,
render-scene --image-size, --camera-model, EXIF orientation, subfolders of images/."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import typer

from recon.cli import _register_commands, app, main

SHARED = {  # option -> the commands that must offer it, spelled exactly so
    "--workers": ["run", "compare", "match", "export", "bench scenes", "bench difficulty"],
    "--seed": ["run", "compare", "match", "render-scene", "bench pairs", "bench scenes", "bench difficulty"],
    "--progress": ["run", "compare", "bench pairs", "bench scenes", "bench difficulty"],
    "--no-progress": ["run", "compare", "bench pairs", "bench scenes", "bench difficulty"],
    "--stock-presets": ["compare", "bench scenes", "bench difficulty"],
}


def _commands() -> dict[str, object]:
    """{"run": click command, "bench pairs": ..., ...} of the whole app."""
    _register_commands()
    root = typer.main.get_command(app)
    out = {}
    for name, cmd in root.commands.items():  # type: ignore[attr-defined]
        sub = getattr(cmd, "commands", None)
        if sub:
            out.update({f"{name} {n}": c for n, c in sub.items()})
        else:
            out[name] = cmd
    return out


def _help(capsys, *args: str) -> str:
    assert main([*args]) == 0
    return re.sub(r"\x1b\[[0-9;]*m", "", capsys.readouterr().out)


def test_every_command_takes_h_and_help_and_lists_the_shared_options_alike(capsys):
    commands = _commands()
    assert {"run", "compare", "match", "export", "view", "render-scene", "bench pairs"} <= set(commands)
    for name, cmd in commands.items():
        short, long_ = _help(capsys, *name.split(), "-h"), _help(capsys, *name.split(), "--help")
        assert short == long_ and f" {name} [OPTIONS]" in short
        flags = {o for p in cmd.params for o in (*p.opts, *getattr(p, "secondary_opts", ())) if o.startswith("-")}
        hidden = {o for p in cmd.params if getattr(p, "hidden", False) for o in p.opts}
        for option, owners in SHARED.items():
            if name in owners:
                assert option in flags, f"recon {name} has no {option}"
                assert re.search(rf"(^|\s){re.escape(option)}(\s|$)", short, re.M), f"{name} --help: {option}"
        # no other spelling of the shared options
        assert not (flags - hidden) & {"--stock-preset", "--num-workers", "--threads", "--random-seed"}, name
        # typed choices, no <bool> for a flag (only click's own --help line may show one)
        assert "<bool>" not in "\n".join(x for x in short.splitlines() if "Show this message" not in x), name
    run_help = _help(capsys, "run", "-h")
    for choices in ("extra-affine|sift", "auto|single|per-i", "SIMPLE_RADIAL|PIN"):
        assert choices in run_help
    assert "<extra-affine|sift" in _help(capsys, "match", "-h")


def test_version_is_the_distribution_version(capsys):
    from recon.cli import version

    assert main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    assert out == f"recon {version()}" and re.fullmatch(r"recon \d+\.\d+.*", out)


def test_stock_presets_one_spelling_and_the_old_one_warns(capsys):
    from recon.cli.options import stock_presets
    from recon.errors import UserError

    assert stock_presets("default, high,default") == ["default", "high"]
    assert stock_presets("default", "high") == ["high"]
    assert "--stock-preset is deprecated" in capsys.readouterr().err
    with pytest.raises(UserError, match="choose from default, high"):
        stock_presets("bogus")
    # the CLI refuses an unknown preset in one line, exit 2, under both spellings
    for flag in ("--stock-presets", "--stock-preset"):
        assert main(["compare", ".", flag, "bogus"]) == 2
        assert "choose from default, high" in capsys.readouterr().err


def test_render_scene_image_size(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["render-scene", str(out), "--preset", "corner", "--image-size", "200x150"]) == 0
    imgs = sorted((out / "images").glob("*.png"))
    assert imgs and all(cv2.imread(str(p)).shape[:2] == (150, 200) for p in imgs)
    assert main(["render-scene", str(tmp_path / "t"), "--image-size", "200by150"]) == 2
    assert "WxH" in capsys.readouterr().err


def _photo(path: Path, w: int, h: int, seed: int = 0, orientation: int | None = None) -> None:
    from PIL import Image

    rgb = (np.random.default_rng(seed).random((h, w, 3)) * 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    kw = {}
    if orientation is not None:
        exif = Image.Exif()
        exif[0x0112] = orientation
        kw["exif"] = exif
    Image.fromarray(rgb).save(path, quality=95, **kw)


def test_exif_rotated_photo_is_used_as_stored_like_colmap(tmp_path):
    """A 120x80 JPEG tagged "rotate 90" (orientation 6): COLMAP's camera is 120x80 (it ignores the
    tag), and so are our image size and keypoint frame; the run warns about the tag."""
    from recon.core.database import import_scene_images
    from recon.core.scene import exif_orientation, scan_scene

    images = tmp_path / "images"
    _photo(images / "rot.jpg", 120, 80, 0, orientation=6)
    _photo(images / "plain.jpg", 120, 80, 1)
    assert exif_orientation(images / "rot.jpg") == 6 and exif_orientation(images / "plain.jpg") == 1
    scene, grays = scan_scene(tmp_path, max_size=0)
    im = scene.image("rot.jpg")
    assert (im.width, im.height) == (120, 80) and grays["rot.jpg"].shape == (80, 120)
    assert any("EXIF rotation (rot.jpg)" in w for w in scene.warnings)
    assert not any("plain.jpg" in w for w in scene.warnings)
    ids, _, missing = import_scene_images(tmp_path / "db.db", images, scene.names, "per-image")
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    try:
        cams = {im.name: db.read_camera(im.camera_id) for im in db.read_all_images()}
    finally:
        db.close()
    assert not missing and (cams["rot.jpg"].width, cams["rot.jpg"].height) == (120, 80)


def test_subfolders_of_images_are_searched_and_names_keep_the_relative_path(tmp_path):
    from recon.core.database import import_scene_images
    from recon.core.scene import scan_scene

    _photo(tmp_path / "images" / "cam1" / "a.jpg", 96, 64, 0)
    _photo(tmp_path / "images" / "cam2" / "deeper" / "b.jpg", 96, 64, 1)
    _photo(tmp_path / "images" / "c.jpg", 96, 64, 2)
    _photo(tmp_path / "images" / ".hidden" / "d.jpg", 96, 64, 3)
    scene, _ = scan_scene(tmp_path, max_size=0)
    assert scene.names == ["c.jpg", "cam1/a.jpg", "cam2/deeper/b.jpg"]
    ids, _, missing = import_scene_images(tmp_path / "db.db", tmp_path / "images", scene.names, "auto")
    assert not missing and set(ids) == set(scene.names)  # COLMAP's names are the same relative paths
    # photos directly in SCENE_DIR: top level only (SCENE_DIR also holds gt/ and the outputs)
    flat = tmp_path / "flat"
    _photo(flat / "x.jpg", 96, 64, 4)
    _photo(flat / "recon" / "y.jpg", 96, 64, 5)
    assert scan_scene(flat, max_size=0)[0].names == ["x.jpg"]


def test_symlinked_subfolders_are_entered_once_and_loops_end(tmp_path):
    """Links back to a parent once made the listing recurse ~40 levels (two of them: without
    end); a second link to one folder listed its photos twice."""
    from recon.core.scene import list_candidates

    images = tmp_path / "images"
    _photo(images / "a.jpg", 96, 64, 0)
    _photo(tmp_path / "elsewhere" / "b.jpg", 96, 64, 1)
    (images / "loop1").symlink_to("..")
    (images / "loop2").symlink_to(".")
    (images / "linked").symlink_to(tmp_path / "elsewhere")
    (images / "linked_again").symlink_to(tmp_path / "elsewhere")
    names, _ = list_candidates(images)
    assert names[0] == "a.jpg" and names.count("linked/b.jpg") == 1 and "linked_again/b.jpg" not in names
    # the link to the scene folder is entered once (it holds images/ itself, already seen)
    assert all(n.count("/") <= 2 for n in names)


@pytest.mark.parametrize("model,num_params", [("PINHOLE", 4), ("SIMPLE_PINHOLE", 3), ("OPENCV", 8)])
def test_camera_model_reaches_the_database(tmp_path, model, num_params):
    from recon.config import RunConfig
    from recon.core.database import import_scene_images

    _photo(tmp_path / "images" / "a.jpg", 96, 64, 0)
    cfg = RunConfig.from_options(camera_model=model)
    ids, _, _ = import_scene_images(tmp_path / "db.db", tmp_path / "images", ["a.jpg"], "auto",
                                    cfg.database.camera_model)
    db = pycolmap.Database.open(str(tmp_path / "db.db"))
    try:
        cam = db.read_all_cameras()[0]
    finally:
        db.close()
    assert cam.model.name == model and len(cam.params) == num_params


def test_camera_model_unknown_is_refused_in_one_line(tmp_path, capsys):
    from recon.config import RunConfig
    from recon.errors import UserError

    with pytest.raises(UserError, match="--camera-model 'FISHEYE'"):
        RunConfig.from_options(camera_model="FISHEYE")
    assert main(["run", str(tmp_path), "--camera-model", "FISHEYE", "--rerun", "none"]) == 2
    err = capsys.readouterr().err
    assert "FISHEYE" in err and "Traceback" not in err


@pytest.mark.slow
def test_run_with_pinhole_cameras(corner_scene, tmp_path):
    """`recon run --camera-model PINHOLE` on the rendered corner: the model's cameras are PINHOLE."""
    scene = tmp_path / "corner"
    shutil.copytree(corner_scene, scene)
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "--method", "sift", "--camera-model", "PINHOLE",
                 "--no-progress", "--rerun", "none"]) == 0
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_reg_images() >= 3 and {c.model.name for c in rec.cameras.values()} == {"PINHOLE"}
