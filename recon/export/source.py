"""The input of an export: a `recon run` output folder, its model and the photos it was made from.

`OUT_DIR/sparse/0` holds the model (COLMAP binary); `OUT_DIR/.recon_scene.json` (written by
`recon.core.outdir`) names the scene and its image folder, from which the photos are read (the
output folder holds no copy of them). Anything missing is a one-line `UserError`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from recon.core.outdir import SCENE_MARKER
from recon.errors import UserError

MODEL_SUBDIR = Path("sparse") / "0"


@dataclass
class ExportSource:
    """A run folder resolved for export."""

    out_dir: Path  # the `recon run` output folder (resolved)
    model_dir: Path  # OUT_DIR/sparse/0
    image_dir: Path  # where the photos named in the model are (resolved)
    rec: pycolmap.Reconstruction  # the model, as read from model_dir

    @property
    def registered_names(self) -> list[str]:
        """Names of the registered images (relative to `image_dir`), sorted."""
        return sorted(self.rec.image(i).name for i in self.rec.reg_image_ids())


def _image_dir_of(out_dir: Path) -> Path:
    marker = out_dir / SCENE_MARKER
    try:
        rec = json.loads(marker.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{out_dir}: not a `recon run` output folder (no {SCENE_MARKER})") from None
    except (OSError, ValueError) as e:
        raise UserError(f"{marker}: unreadable ({getattr(e, 'strerror', None) or e}); rerun `recon run`") from None
    if rec.get("image_dir"):
        return Path(rec["image_dir"])
    if rec.get("scene"):  # written before image_dir was recorded
        from recon.core.scene import find_image_dir

        return find_image_dir(rec["scene"])
    raise UserError(f"{marker}: names no scene; rerun `recon run`")


def load_source(out_dir: str | Path) -> ExportSource:
    """Resolve OUT_DIR, read its model and check that every registered photo is on disk."""
    out = Path(out_dir).expanduser()
    if not out.is_dir():
        what = "not a folder" if out.exists() else "no such folder"
        raise UserError(f"{out_dir}: {what} (give a `recon run` output folder)")
    out = out.resolve()
    model_dir = out / MODEL_SUBDIR
    if not all((model_dir / f"{n}.bin").is_file() for n in ("cameras", "images", "points3D")):
        raise UserError(f"{out}: no model in {MODEL_SUBDIR} (did `recon run` finish with a model?)")
    image_dir = _image_dir_of(out).expanduser().resolve()
    if not image_dir.is_dir():
        raise UserError(f"{image_dir}: the scene's image folder is gone; the export reads the photos from there")
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except (ValueError, RuntimeError) as e:
        raise UserError(f"{model_dir}: cannot read the model ({str(e).splitlines()[0]})") from None
    if rec.num_reg_images() == 0:
        raise UserError(f"{model_dir}: the model has no registered image")
    src = ExportSource(out, model_dir, image_dir, rec)
    for name in src.registered_names:
        if not (image_dir / name).is_file():
            raise UserError(f"{image_dir / name}: photo of the model is missing")
    return src


def check_photo_sizes(src: ExportSource) -> None:
    """UserError naming the first registered photo whose pixel size is not its camera's.

    COLMAP's undistorter checks this too, but from a worker thread whose failure can abort the
    whole process (pycolmap 4.2: "Uncaught exceptions in thread pool destructor"), so it is
    checked here first, from the file headers (Pillow reads the size without decoding; rotation
    flags in EXIF are not applied, as COLMAP does not apply them either).
    """
    from PIL import Image, UnidentifiedImageError

    for iid in sorted(src.rec.reg_image_ids()):
        im = src.rec.image(iid)
        cam = src.rec.camera(im.camera_id)
        path = src.image_dir / im.name
        try:
            with Image.open(path) as f:
                w, h = f.size
        except (OSError, UnidentifiedImageError) as e:
            raise UserError(f"{path}: cannot read the photo ({getattr(e, 'strerror', None) or e})") from None
        if (w, h) != (cam.width, cam.height):
            raise UserError(f"{path}: {w}x{h} px, but the model's camera is {cam.width}x{cam.height} px; "
                            "the export needs the photos the model was made from")
