"""`recon render-scene OUT_DIR`: render a project-made extreme-viewpoint scene with ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

from recon.cli._options import check_textures
from recon.cli.options import flag, seed_option
from recon.cli.options import image_size as parse_image_size


def render_command(
    out_dir: Optional[Path] = typer.Argument(None, help="Folder to write images/ and gt/ into.", show_default=False,
                                             metavar="OUT_DIR"),
    preset: str = typer.Option("corner", "--preset", help="Scene preset (see --list-presets)."),
    texture: Optional[list[Path]] = typer.Option(None, "--texture", help="Photo(s) to texture the planes with (repeatable)."),
    image_size: Optional[str] = typer.Option(None, "--image-size", help="Rendered size WxH, e.g. 800x600 (default: "
                                                                        "the preset's)."),
    seed: Annotated[int, seed_option("Seed of the procedural textures and sensor noise.")] = 0,
    overwrite: Annotated[bool, flag("--overwrite", help="Replace OUT_DIR/images and OUT_DIR/gt (nothing else).")]
        = False,
    list_presets: Annotated[bool, flag("--list-presets", help="List the presets and exit.")] = False,
) -> None:
    """Render piecewise-planar scenes from cameras with viewing angles up to 80+ degrees."""
    from recon.core.outdir import output_lock
    from recon.errors import UserError
    from scenes.presets import PRESETS, get_preset
    from scenes.render import check_render_target, render_scene

    console = Console(highlight=False)
    if list_presets:
        for p in PRESETS.values():
            console.print(f"{p.name:15s} {len(p.cameras.azimuths_deg)} views, step {p.azimuth_step:.0f} deg: {p.description}")
        return
    if out_dir is None:
        raise UserError("missing OUT_DIR (the folder to write images/ and gt/ into)")
    try:
        get_preset(preset)
    except ValueError as e:
        raise UserError(str(e)) from None
    size = parse_image_size(image_size)
    check_textures(texture)
    out_dir = out_dir.expanduser().absolute()
    check_render_target(out_dir, overwrite)  # read-only: a user's images/ or gt/ is refused untouched
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    ok = False
    try:
        with output_lock(out_dir):  # one render (or run) at a time in this folder
            scene = render_scene(out_dir, preset, texture or None, seed, overwrite=overwrite, image_size=size)
        ok = True
    finally:
        if not ok and created:  # nothing half-made left behind
            import shutil

            if all(p.name == ".recon.lock" for p in out_dir.iterdir()):
                shutil.rmtree(out_dir, ignore_errors=True)
    all_angles = [a for d in scene.viewing_angles_deg for a in d.values()]
    console.print(f"rendered {len(scene.image_paths)} images of '{scene.preset}' into {scene.out_dir}; "
                  f"viewing angles {min(all_angles):.0f}-{max(all_angles):.0f} deg; ground truth in {scene.out_dir / 'gt'}")


def register(app: typer.Typer) -> None:
    app.command("render-scene")(render_command)
