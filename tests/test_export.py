"""`recon export` (recon.export): each format read back the way the next tool reads it.

A small rendered scene (the corner preset at 400 x 300, SIFT for speed) is reconstructed once;
its exports are then read by readers written here, independent of pycolmap's writers:

* a classic COLMAP binary reader (struct-based, the layout of COLMAP's
  scripts/python/read_write_model.py, which graphdeco's gaussian-splatting and gsplat copy);
* a nerfstudio-style transforms.json loader (what nerfstudio's `nerfstudio-data` dataparser
  reads: shared or per-frame intrinsics, OpenGL camera-to-world matrices, images by file_path,
  the ply of initial points).
"""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from recon.core.pipeline import RunConfig, run_scene
from recon.errors import UserError
from recon.export import ExportConfig, export_run
from recon.export.target import EXPORT_MARKER
from scenes.render import render_scene

SIZE = (400, 300)


# the scene and its runs -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("corner") / "scene"
    render_scene(root, "corner", seed=0, image_size=SIZE)
    return root


def _run(scene: Path, out: Path, **kw) -> Path:
    rep = run_scene(scene, RunConfig.from_options(out=out, method="sift", progress=False, **kw))
    assert rep.ok and rep.registered_images >= 4
    return out


@pytest.fixture(scope="module")
def run_dir(scene, tmp_path_factory) -> Path:
    return _run(scene, tmp_path_factory.mktemp("run") / "out")


@pytest.fixture(scope="module")
def model(run_dir) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))


# a classic COLMAP binary reader (read_write_model.py's layout) ---------------------------------
CAMERA_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}


def _read(f, fmt: str):
    return struct.unpack("<" + fmt, f.read(struct.calcsize("<" + fmt)))


def read_cameras_bin(path: Path) -> dict[int, dict]:
    cams = {}
    with open(path, "rb") as f:
        (n,) = _read(f, "Q")
        for _ in range(n):
            cid, model_id, w, h = _read(f, "iiQQ")
            name, nparams = CAMERA_MODELS[model_id]
            cams[cid] = {"model": name, "width": w, "height": h, "params": np.array(_read(f, "d" * nparams))}
    return cams


def read_images_bin(path: Path) -> dict[int, dict]:
    images = {}
    with open(path, "rb") as f:
        (n,) = _read(f, "Q")
        for _ in range(n):
            iid, qw, qx, qy, qz, tx, ty, tz, cid = _read(f, "idddddddi")
            name = b""
            while (c := f.read(1)) != b"\x00":
                name += c
            (npts,) = _read(f, "Q")
            flat = np.array(_read(f, "ddq" * npts), np.float64).reshape(-1, 3)
            images[iid] = {"qvec": np.array([qw, qx, qy, qz]), "tvec": np.array([tx, ty, tz]), "camera_id": cid,
                           "name": name.decode("utf-8"), "xys": flat[:, :2], "point3D_ids": flat[:, 2].astype(np.int64)}
    return images


def read_points3D_bin(path: Path) -> dict[int, np.ndarray]:
    pts = {}
    with open(path, "rb") as f:
        (n,) = _read(f, "Q")
        for _ in range(n):
            pid, x, y, z, _r, _g, _b, _err = _read(f, "QdddBBBd")
            (tl,) = _read(f, "Q")
            _read(f, "ii" * tl)
            pts[pid] = np.array([x, y, z])
    return pts


def qvec2rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
                     [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
                     [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


# a nerfstudio-style transforms.json loader ----------------------------------------------------
NERFSTUDIO_MODELS = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE"}


def load_transforms(data_dir: Path) -> dict:
    """Per frame: image, intrinsics (shared or per frame), c2w, distortion; plus the ply points."""
    meta = json.loads((data_dir / "transforms.json").read_text(encoding="utf-8"))
    assert meta.get("camera_model", "OPENCV") in NERFSTUDIO_MODELS
    frames = []
    for fr in sorted(meta["frames"], key=lambda fr: fr["file_path"]):
        def get(k: str, default=None, fr=fr):  # shared (top-level) value first, then the frame's
            return meta[k] if k in meta else fr.get(k, default)

        img = cv2.imread(str(data_dir / fr["file_path"]), cv2.IMREAD_COLOR)
        assert img is not None, fr["file_path"]
        frames.append({"file_path": fr["file_path"], "image": img, "c2w": np.array(fr["transform_matrix"], np.float64),
                       "fx": float(get("fl_x")), "fy": float(get("fl_y")), "cx": float(get("cx")),
                       "cy": float(get("cy")), "w": int(get("w")), "h": int(get("h")),
                       "dist": np.array([float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")])})
    import open3d as o3d  # nerfstudio reads the ply with open3d

    ply = o3d.io.read_point_cloud(str(data_dir / meta["ply_file_path"]))
    return {"meta": meta, "frames": frames, "ply_xyz": np.asarray(ply.points),
            "applied_transform": np.array(meta.get("applied_transform", np.eye(4)[:3]), np.float64)}


def undo_nerfstudio(c2w: np.ndarray) -> np.ndarray:
    """COLMAP world_from_cam (4x4) from a nerfstudio transform_matrix: colmap_to_json's steps undone."""
    M = c2w.copy()
    M[2, :] *= -1
    M = M[np.array([0, 2, 1, 3]), :]
    M[0:3, 1:3] *= -1
    return M


def project_nerfstudio(fr: dict, X_ns: np.ndarray) -> np.ndarray:
    """Pixels (COLMAP / nerfstudio convention, pixel centres at +0.5) of nerfstudio-world points
    through an OpenGL camera (x right, y up, looking down -z) with the frame's distortion."""
    R, t = fr["c2w"][:3, :3], fr["c2w"][:3, 3]
    p = (X_ns - t) @ R  # R^T (X - t), row-wise
    x, y = p[:, 0] / -p[:, 2], -p[:, 1] / -p[:, 2]  # OpenCV-style normalised coordinates
    K = np.array([[fr["fx"], 0, fr["cx"]], [0, fr["fy"], fr["cy"]], [0, 0, 1]])
    uv, _ = cv2.projectPoints(np.stack([x, y, np.ones_like(x)], 1), np.zeros(3), np.zeros(3), K, fr["dist"])
    return uv.reshape(-1, 2)


def observations(rec: pycolmap.Reconstruction, max_err_px: float):
    """Per registered image: (name, xy observed (COLMAP px), X world) of observations whose
    reprojection error in `rec` is below max_err_px."""
    out = []
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        cam = rec.camera(im.camera_id)
        xy, X = [], []
        for p2 in im.points2D:
            if p2.has_point3D():
                Xw = rec.point3D(p2.point3D_id).xyz
                proj = cam.img_from_cam(im.cam_from_world() * Xw)
                if np.linalg.norm(proj - p2.xy) < max_err_px:
                    xy.append(p2.xy)
                    X.append(Xw)
        out.append((im.name, np.array(xy).reshape(-1, 2), np.array(X).reshape(-1, 3)))
    return out


# 3dgs ----------------------------------------------------------------------------------------
def test_3dgs_read_back_with_a_classic_colmap_reader(run_dir, model, scene, tmp_path):
    res = export_run(ExportConfig(run_dir, "3dgs", to=tmp_path / "gs"))
    d = tmp_path / "gs"
    assert res.path == d and res.camera_models == ["PINHOLE"]
    cams = read_cameras_bin(d / "sparse" / "0" / "cameras.bin")
    images = read_images_bin(d / "sparse" / "0" / "images.bin")
    pts = read_points3D_bin(d / "sparse" / "0" / "points3D.bin")
    assert cams and all(c["model"] in ("PINHOLE", "SIMPLE_PINHOLE") for c in cams.values())
    assert len(images) == model.num_reg_images() == res.num_images
    assert sorted(im["name"] for im in images.values()) == sorted(model.image(i).name for i in model.reg_image_ids())
    assert len(pts) == model.num_points3D()
    on_disk = sorted(p.relative_to(d / "images").as_posix() for p in (d / "images").rglob("*") if p.is_file())
    assert on_disk == sorted(im["name"] for im in images.values())
    errs = []
    for im in images.values():
        cam = cams[im["camera_id"]]
        img = cv2.imread(str(d / "images" / im["name"]))
        assert img.shape[:2] == (cam["height"], cam["width"])  # undistorted size == camera size
        fx, fy, cx, cy = cam["params"] if cam["model"] == "PINHOLE" else cam["params"][[0, 0, 1, 2]]
        R, t = qvec2rotmat(im["qvec"]), im["tvec"]
        # the camera centre is the model's: undistortion changes intrinsics, never poses
        C = -R.T @ t
        assert np.allclose(C, model.find_image_with_name(im["name"]).projection_center(), atol=1e-9)
        sel = im["point3D_ids"] >= 0
        X = np.array([pts[int(i)] for i in im["point3D_ids"][sel]])
        pc = X @ R.T + t
        uv = np.stack([fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy], 1)
        errs.append(np.linalg.norm(uv - im["xys"][sel], axis=1))
    errs = np.concatenate(errs)
    # pinhole projection of the exported points lands on the exported (undistorted) keypoints
    assert len(errs) > 500 and np.median(errs) < 0.5 and np.mean(errs) < 1.0
    assert json.loads((d / EXPORT_MARKER).read_text())["format"] == "3dgs"


# nerfstudio ----------------------------------------------------------------------------------
def _check_nerfstudio(d: Path, model: pycolmap.Reconstruction, undistorted: bool, scene: Path) -> dict:
    ds = load_transforms(d)
    frames, A = ds["frames"], ds["applied_transform"]
    names = sorted(model.image(i).name for i in model.reg_image_ids())
    assert [fr["file_path"] for fr in frames] == [f"images/{n}" for n in names]
    for fr in frames:
        assert fr["image"].shape[:2] == (fr["h"], fr["w"])
        world_from_cam = undo_nerfstudio(fr["c2w"])
        im = model.find_image_with_name(fr["file_path"][len("images/"):])
        assert np.allclose(world_from_cam[:3, 3], im.projection_center(), atol=1e-9)
        assert np.allclose(world_from_cam[:3, :3], im.cam_from_world().rotation.matrix().T, atol=1e-9)
        # the applied_transform maps COLMAP's world to the frame's world
        assert np.allclose(fr["c2w"][:3, 3], A[:, :3] @ im.projection_center() + A[:, 3], atol=1e-9)
        if not undistorted:  # the original photos, byte for byte
            assert (d / fr["file_path"]).read_bytes() == (scene / "images" / im.name).read_bytes()
    # the ply holds the model's points in nerfstudio's world
    X = np.array([p.xyz for p in model.points3D.values()])
    X_ns = X @ A[:, :3].T + A[:, 3]
    assert len(ds["ply_xyz"]) == len(X)
    from scipy.spatial import cKDTree

    assert cKDTree(X_ns).query(ds["ply_xyz"])[0].max() < 1e-4  # float32 in the file
    # projecting model points with the exported camera lands on their keypoints (< 1 px)
    # (undistorted: the keypoint's ray through the original camera, imaged by the PINHOLE camera
    # COLMAP's undistorter made for that image, read from the export's colmap/sparse/0)
    by_name = {fr["file_path"][len("images/"):]: fr for fr in frames}
    und = pycolmap.Reconstruction(str(d / "colmap" / "sparse" / "0")) if undistorted else None
    n_checked = 0
    for name, xy, Xw in observations(model, max_err_px=0.5):
        fr = by_name[name]
        uv = project_nerfstudio(fr, Xw @ A[:, :3].T + A[:, 3])
        if und is not None:
            ray = model.camera(model.find_image_with_name(name).camera_id).cam_from_img(xy)
            xy = und.camera(und.find_image_with_name(name).camera_id).img_from_cam(
                np.concatenate([ray, np.ones((len(ray), 1))], 1))
        err = np.linalg.norm(uv - xy, axis=1)
        assert err.max() < 1.0, (name, err.max())
        n_checked += len(err)
    assert n_checked > 300
    return ds


def test_nerfstudio_read_back_like_nerfstudio(run_dir, model, scene, tmp_path):
    res = export_run(ExportConfig(run_dir, "nerfstudio", to=tmp_path / "ns"))
    ds = _check_nerfstudio(tmp_path / "ns", model, undistorted=True, scene=scene)
    meta = ds["meta"]
    assert meta["camera_model"] == "PINHOLE" and "k1" not in meta
    assert "fl_x" in meta and "fl_x" not in meta["frames"][0]  # one camera: shared intrinsics
    # the model the json describes sits where ns-process-data leaves it
    rec = pycolmap.Reconstruction(str(tmp_path / "ns" / "colmap" / "sparse" / "0"))
    assert res.model_dir == tmp_path / "ns" / "colmap" / "sparse" / "0"
    assert {c.model.name for c in rec.cameras.values()} == {"PINHOLE"}
    assert not (tmp_path / "ns" / "sparse").exists() and not (tmp_path / "ns" / "stereo").exists()


def test_nerfstudio_keep_distortion_writes_opencv_params(run_dir, model, scene, tmp_path):
    export_run(ExportConfig(run_dir, "nerfstudio", to=tmp_path / "ns", keep_distortion=True))
    ds = _check_nerfstudio(tmp_path / "ns", model, undistorted=False, scene=scene)
    meta = ds["meta"]
    cam = next(iter(model.cameras.values()))
    assert cam.model.name == "SIMPLE_RADIAL"
    assert meta["camera_model"] == "OPENCV" and meta["k1"] == cam.params[3] != 0.0 and meta["k2"] == 0.0
    assert (meta["w"], meta["h"]) == SIZE


def test_nerfstudio_per_frame_intrinsics_when_cameras_differ(scene, tmp_path):
    out = _run(scene, tmp_path / "out", camera_mode="per-image")
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert model.num_cameras() > 1
    export_run(ExportConfig(out, "nerfstudio"))
    d = out / "export" / "nerfstudio"  # the default destination
    ds = _check_nerfstudio(d, model, undistorted=True, scene=scene)
    assert "fl_x" not in ds["meta"] and all("fl_x" in fr for fr in ds["meta"]["frames"])
    assert len({fr["fx"] for fr in ds["frames"]}) > 1


# colmap-text ---------------------------------------------------------------------------------
def test_colmap_text_reads_back_as_the_same_model(run_dir, model, tmp_path):
    from recon.eval.gt import read_colmap_text

    res = export_run(ExportConfig(run_dir, "colmap-text", to=tmp_path / "txt"))
    d = tmp_path / "txt" / "sparse" / "0"
    assert res.model_dir == d and {p.name for p in d.iterdir()} >= {"cameras.txt", "images.txt", "points3D.txt"}
    back = pycolmap.Reconstruction()
    back.read_text(str(d))
    assert back.num_reg_images() == model.num_reg_images() and back.num_points3D() == model.num_points3D()
    gt = read_colmap_text(d)  # an independent line parser of cameras.txt / images.txt
    for iid in model.reg_image_ids():
        im = model.image(iid)
        assert np.allclose(gt[im.name].cam_from_world, im.cam_from_world().matrix(), atol=1e-12)


def test_colmap_text_warns_about_names_with_spaces(run_dir, scene, tmp_path):
    """COLMAP's text readers end a name at its first space: the export says so (the 3dgs and
    nerfstudio exports, binary and json, keep such names)."""
    rec = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    (tmp_path / "photos").mkdir()
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        new = f"my {im.name}"
        shutil.copy(scene / "images" / im.name, tmp_path / "photos" / new)
        im.name = new
    (tmp_path / "out" / "sparse" / "0").mkdir(parents=True)
    rec.write(str(tmp_path / "out" / "sparse" / "0"))
    (tmp_path / "out" / ".recon_scene.json").write_text(json.dumps({"image_dir": str(tmp_path / "photos")}))
    res = export_run(ExportConfig(tmp_path / "out", "colmap-text"))
    assert len(res.warnings) == 1 and "first space" in res.warnings[0] and "'my view_00.png'" in res.warnings[0]
    res = export_run(ExportConfig(tmp_path / "out", "3dgs"))
    assert not res.warnings
    assert any(im["name"] == "my view_00.png" for im in read_images_bin(res.model_dir / "images.bin").values())


def test_a_flat_scene_exports_into_its_run_folder(tmp_path):
    """Photos directly in SCENE_DIR are listed from its top level only: the default destination
    under SCENE_DIR/recon is allowed there (it was refused as "inside the image folder"), while
    a subfolder of an images/ folder is still refused (`recon run` lists those recursively)."""
    from recon.export.target import check_target

    flat = tmp_path / "flat"
    (flat / "recon").mkdir(parents=True)
    dst = check_target(flat / "recon" / "export" / "3dgs", flat / "recon", flat, overwrite=False)
    assert dst == (flat / "recon" / "export" / "3dgs").resolve()
    nested = tmp_path / "nested"
    (nested / "images").mkdir(parents=True)
    with pytest.raises(UserError, match="inside the scene's image folder"):
        check_target(nested / "images" / "gs", nested / "recon", nested / "images", overwrite=False)
    with pytest.raises(UserError, match="would replace the scene's image folder"):
        check_target(flat, tmp_path / "elsewhere", flat, overwrite=True)


# errors and atomicity ------------------------------------------------------------------------
def test_user_errors(run_dir, scene, tmp_path):
    with pytest.raises(UserError, match="no model"):
        export_run(ExportConfig(scene, "3dgs", to=tmp_path / "a"))
    with pytest.raises(UserError, match="choose one of colmap-text, 3dgs, nerfstudio"):
        ExportConfig(run_dir, "ply")
    with pytest.raises(UserError, match="nerfstudio only"):
        ExportConfig(run_dir, "3dgs", keep_distortion=True)
    with pytest.raises(UserError, match="inside the scene's image folder"):
        export_run(ExportConfig(run_dir, "3dgs", to=scene / "images" / "gs"))
    with pytest.raises(UserError, match="would replace the run folder"):
        export_run(ExportConfig(run_dir, "3dgs", to=run_dir, overwrite=True))
    with pytest.raises(UserError, match="would replace the scene's image folder"):
        export_run(ExportConfig(run_dir, "3dgs", to=scene, overwrite=True))
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match="not empty; pass --overwrite"):
        export_run(ExportConfig(run_dir, "colmap-text", to=busy))
    with pytest.raises(UserError, match="holds no earlier export"):  # never delete somebody's folder
        export_run(ExportConfig(run_dir, "colmap-text", to=busy, overwrite=True))
    assert (busy / "notes.txt").read_text() == "mine"
    # photos that are no longer the model's (here: rotated): one line, never COLMAP's abort
    fake = tmp_path / "fake"
    (fake / "photos").mkdir(parents=True)
    shutil.copytree(run_dir / "sparse", fake / "out" / "sparse")
    for p in (scene / "images").iterdir():
        cv2.imwrite(str(fake / "photos" / p.name), cv2.rotate(cv2.imread(str(p)), cv2.ROTATE_90_CLOCKWISE))
    (fake / "out" / ".recon_scene.json").write_text(json.dumps({"scene": str(fake), "image_dir": str(fake / "photos")}))
    with pytest.raises(UserError, match=r"view_00\.png: 300x400 px, but the model's camera is 400x300 px"):
        export_run(ExportConfig(fake / "out", "3dgs"))
    assert sorted(p.name for p in (fake / "out").iterdir()) == [".recon_scene.json", "sparse"]  # nothing left
    # an export is replaced with --overwrite
    export_run(ExportConfig(run_dir, "colmap-text", to=tmp_path / "txt"))
    export_run(ExportConfig(run_dir, "colmap-text", to=tmp_path / "txt", overwrite=True))
    assert (tmp_path / "txt" / "sparse" / "0" / "images.txt").is_file()


def test_cli_one_line_errors_exit_2(run_dir, tmp_path, capsys):
    from recon.cli import main

    assert main(["export", str(tmp_path), "--format", "3dgs"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("recon: error:") and "no model" in err and len(err.splitlines()) == 1
    assert main(["export", str(run_dir), "--format", "ply"]) == 2  # typer's choice check
    assert "'ply' is not one of" in capsys.readouterr().err
    assert main(["export", str(run_dir), "--format", "colmap-text", "--to", str(tmp_path / "t")]) == 0
    assert main(["export", str(run_dir), "--format", "colmap-text", "--to", str(tmp_path / "t")]) == 2
    assert "pass --overwrite" in capsys.readouterr().err


def test_failed_export_keeps_the_previous_one_and_leaves_no_temp(run_dir, tmp_path, monkeypatch):
    from recon.export import api

    dst = tmp_path / "ns"
    export_run(ExportConfig(run_dir, "nerfstudio", to=dst))
    before = (dst / "transforms.json").read_bytes()

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(api, "write_nerfstudio", boom)
    with pytest.raises(KeyboardInterrupt):
        export_run(ExportConfig(run_dir, "nerfstudio", to=dst, overwrite=True))
    assert (dst / "transforms.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ns"]  # no temporary folder left
