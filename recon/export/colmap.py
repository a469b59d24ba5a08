"""COLMAP layouts: the model as text, and undistorted images + a PINHOLE model (Gaussian splatting).

`write_undistorted` runs `pycolmap.undistort_images` (COLMAP's image undistorter: each camera
becomes a PINHOLE camera, every registered photo is resampled into it, 2D observations are
undistorted too; `blank_pixels=0` crops to the valid region, so no black borders reach the
trainer). COLMAP writes the model to `sparse/` plus an MVS workspace (`stereo/`, scripts); the
trainers read `sparse/0`, so the model is moved there and the MVS part dropped.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pycolmap

from recon.errors import UserError
from recon.log import quiet_colmap

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")  # what Gaussian-splatting trainers accept


def write_colmap_text(rec: pycolmap.Reconstruction, dst: Path) -> Path:
    """`dst/sparse/0/*.txt` (pycolmap's writer); returns the model folder."""
    model = dst / "sparse" / "0"
    model.mkdir(parents=True)
    rec.write_text(str(model))
    return model


def write_undistorted(model_dir: Path, image_dir: Path, dst: Path, num_threads: int = -1) -> Path:
    """`dst/images/` (undistorted photos, same names) and `dst/sparse/0/*.bin` (PINHOLE cameras);
    returns the model folder. `dst` must be empty."""
    try:
        with quiet_colmap():
            pycolmap.undistort_images(str(dst), str(model_dir), str(image_dir), output_type="COLMAP",
                                      copy_policy=pycolmap.FileCopyType.copy,
                                      undistort_options=pycolmap.UndistortCameraOptions(),
                                      num_threads=num_threads)
    except (ValueError, RuntimeError) as e:  # COLMAP's checks, e.g. a photo whose size is not its camera's
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise UserError(f"{image_dir}: COLMAP's undistorter refused the photos ({first}); are they still "
                        "the files the model was made from?") from None
    flat = dst / "sparse"
    aside = dst / ".sparse-flat"
    os.replace(flat, aside)
    (dst / "sparse").mkdir()
    os.replace(aside, dst / "sparse" / "0")
    shutil.rmtree(dst / "stereo", ignore_errors=True)
    for script in dst.glob("run-colmap-*.sh"):
        script.unlink()
    return dst / "sparse" / "0"
