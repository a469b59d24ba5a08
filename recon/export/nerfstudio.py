"""nerfstudio's dataset format: `transforms.json` + `images/` + `sparse_pc.ply`.

Written the way nerfstudio's own `ns-process-data` writes it (`nerfstudio/process_data/
colmap_utils.py`: `colmap_to_json`, `parse_colmap_camera_params`, `create_ply_from_colmap`), so
nerfstudio's `nerfstudio-data` dataparser reads it unchanged:

* per frame: `file_path` ("images/NAME"), `transform_matrix` (4x4 camera-to-world, see
  `nerfstudio_transform_matrix`), `colmap_im_id`; frames sorted by name;
* intrinsics `w, h, fl_x, fl_y, cx, cy` in pixels, at the top level when all registered images
  share one camera and per frame otherwise (nerfstudio reads either); `cx, cy` keep COLMAP's
  convention (centre of the top-left pixel at (0.5, 0.5)), which is nerfstudio's too (its rays
  go through pixel centres at +0.5);
* `camera_model` at the top level (nerfstudio reads it only there): "PINHOLE" for undistorted
  (SIMPLE_PINHOLE / PINHOLE) cameras, "OPENCV" with `k1, k2, p1, p2` for SIMPLE_RADIAL, RADIAL
  and OPENCV cameras (nerfstudio's mapping); other COLMAP models are refused (undistort first);
* `applied_transform` (3x4): the world change nerfstudio applies to COLMAP's world, and
  `ply_file_path` ("sparse_pc.ply": the model's points in that changed world, float xyz + uchar
  rgb, written by pycolmap's `export_PLY`), which splatfacto uses as its initial Gaussians.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from numpy.typing import NDArray

from recon.errors import UserError

PLY_NAME = "sparse_pc.ply"
TRANSFORMS_NAME = "transforms.json"

# nerfstudio's colmap_to_json: applied_transform = eye(4)[:3][[0, 2, 1]]; applied_transform[2] *= -1
# (world x stays, world z becomes y, world y becomes -z), a proper rotation (det +1)
APPLIED_TRANSFORM: NDArray[np.float64] = np.array([[1.0, 0.0, 0.0, 0.0],
                                                   [0.0, 0.0, 1.0, 0.0],
                                                   [0.0, -1.0, 0.0, 0.0]])


def nerfstudio_transform_matrix(cam_from_world: NDArray[np.float64]) -> NDArray[np.float64]:
    """nerfstudio's `transform_matrix` of a COLMAP pose (3x4 cam_from_world, x_cam = R X + t).

    Exactly nerfstudio's `colmap_to_json` (keep_original_world_coordinate=False):
    c2w = inverse of [R | t]; `c2w[0:3, 1:3] *= -1` (COLMAP's camera axes x right, y down,
    z forward -> OpenGL's x right, y up, z backward); `c2w = c2w[[0, 2, 1, 3], :]` and
    `c2w[2, :] *= -1` (the world change `APPLIED_TRANSFORM`, applied on the left). The inverse
    is taken in closed form ([R^T | -R^T t]) instead of np.linalg.inv: the same matrix to
    rounding.
    """
    P = np.asarray(cam_from_world, np.float64).reshape(3, 4)
    R, t = P[:, :3], P[:, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = -R.T @ t
    c2w[0:3, 1:3] *= -1
    c2w = c2w[np.array([0, 2, 1, 3]), :]
    c2w[2, :] *= -1
    return c2w


def camera_fields(camera: pycolmap.Camera) -> tuple[str, dict[str, Any]]:
    """(nerfstudio camera_model, {w, h, fl_x, fl_y, cx, cy[, k1, k2, p1, p2]}) of a COLMAP camera."""
    model = camera.model.name
    p = [float(v) for v in camera.params]
    out: dict[str, Any] = {"w": int(camera.width), "h": int(camera.height)}
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        out.update(fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2])
    elif model in ("PINHOLE", "OPENCV"):
        out.update(fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3])
    else:
        raise UserError(f"camera model {model} has no nerfstudio equivalent here; export undistorted images "
                        "(the default, without --keep-distortion)")
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return "PINHOLE", out
    if model == "SIMPLE_RADIAL":
        out.update(k1=p[3], k2=0.0, p1=0.0, p2=0.0)
    elif model == "RADIAL":
        out.update(k1=p[3], k2=p[4], p1=0.0, p2=0.0)
    else:
        out.update(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    return "OPENCV", out


def transforms_json(rec: pycolmap.Reconstruction, image_prefix: str = "images",
                    ply_name: str = PLY_NAME) -> dict[str, Any]:
    """The content of transforms.json for the registered images of `rec` (see module doc)."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    cam_ids = sorted({int(im.camera_id) for im in images})
    fields = {cid: camera_fields(rec.camera(cid)) for cid in cam_ids}
    models = {m for m, _ in fields.values()}
    out: dict[str, Any] = {"camera_model": "OPENCV" if "OPENCV" in models else "PINHOLE"}
    single = len(cam_ids) == 1
    if single:
        out.update(fields[cam_ids[0]][1])
    frames = []
    for im in images:
        frame: dict[str, Any] = {
            "file_path": f"{image_prefix}/{im.name}",
            "transform_matrix": nerfstudio_transform_matrix(im.cam_from_world().matrix()).tolist(),
            "colmap_im_id": int(im.image_id),
        }
        if not single:
            frame.update(fields[int(im.camera_id)][1])
        frames.append(frame)
    out["frames"] = frames
    out["applied_transform"] = APPLIED_TRANSFORM.tolist()
    out["ply_file_path"] = ply_name
    return out


def write_points_ply(rec: pycolmap.Reconstruction, path: Path) -> None:
    """The model's points in nerfstudio's world (`APPLIED_TRANSFORM`), as pycolmap's PLY."""
    moved = pycolmap.Reconstruction(rec)  # a copy: the caller's model keeps its world
    moved.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(APPLIED_TRANSFORM[:, :3]), APPLIED_TRANSFORM[:, 3]))
    moved.export_PLY(str(path))


def write_nerfstudio(rec: pycolmap.Reconstruction, dst: Path) -> dict[str, Any]:
    """`dst/transforms.json` and `dst/sparse_pc.ply` for `rec` (images go to `dst/images` separately);
    returns the json content."""
    meta = transforms_json(rec)
    write_points_ply(rec, dst / PLY_NAME)
    tmp = dst / f".{TRANSFORMS_NAME}.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(meta, indent=4), encoding="utf-8")
    os.replace(tmp, dst / TRANSFORMS_NAME)
    return meta
