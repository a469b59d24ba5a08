"""Ground-truth cameras of a scene: COLMAP text models and Strecha `.camera` files.

Both readers return `{image name: GtCamera}` where `GtCamera` holds

* `K` (3x3): intrinsics in OpenCV's pixel convention (the centre of the top-left pixel is (0, 0),
  the convention of `matching/`). COLMAP puts that centre at (0.5, 0.5), so a principal point
  read from `cameras.txt` is shifted by -0.5; Strecha's K is taken as is (it is a plain
  pinhole matrix in the image's pixel grid; the evaluation uses only the poses anyway).
* `cam_from_world` (3x4): [R | t] mapping world points to camera coordinates, x_cam = R X + t
  (COLMAP's convention); the camera centre is -R^T t.
* `size`: (width, height) in pixels.

Layouts under `SCENE_DIR/gt/` (`find_gt` picks the first present):

(a) COLMAP text model: `gt/cameras.txt` + `gt/images.txt` (`points3D.txt` is not needed).
    `images.txt` holds two lines per image, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` (the
    pose is cam_from_world, quaternion Hamilton w-first) and a POINTS2D line that may be empty.
(b) Strecha (EPFL multi-view benchmark, also openMVG's copies): `gt/cameras/<image>.camera`,
    9 lines: K (3 rows), radial distortion (1 row), R (3 rows), C (camera centre, 1 row), image
    size (w h). The camera maps a world point X to K R^T (X - C), so cam_from_world =
    [R^T | -R^T C].

Any malformed file, or GT naming an image the scene lacks, raises `matching.errors.InputError`
whose message names the file (the benchmark reports it and carries on without GT).

pycolmap supplies what COLMAP defines: the camera models (parameter count, which parameters are
the focal lengths and the principal point, via `pycolmap.Camera.create_from_model_name`) and the
quaternion convention (`pycolmap.Rotation3d`). The lines themselves are read here, not by
`pycolmap.Reconstruction.read_text`, because on GT files that reader measured worse: it needs a
points3D.txt GT folders lack, reads the next image line as the POINTS2D line of an image written
without one (silently losing every other image), cuts names at the first space, accepts a zero
quaternion, and reports malformed lines without file or line number.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from numpy.typing import NDArray

from matching.errors import InputError

COLMAP_PIXEL_OFFSET = 0.5  # COLMAP pixel coordinate = OpenCV pixel coordinate + 0.5

_ROT_TOL = 1e-3  # |R R^T - I| and |det R - 1| tolerance for a rotation read from a file


@dataclass
class GtCamera:
    K: NDArray[np.float64]  # 3x3, OpenCV pixel convention
    cam_from_world: NDArray[np.float64]  # 3x4 [R | t], x_cam = R X + t
    size: tuple[int, int]  # (width, height)

    @property
    def R(self) -> NDArray[np.float64]:
        return self.cam_from_world[:, :3]

    @property
    def t(self) -> NDArray[np.float64]:
        return self.cam_from_world[:, 3]

    @property
    def center(self) -> NDArray[np.float64]:
        return -self.R.T @ self.t


# helpers ----------------------------------------------------------------------------------------
def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read ground-truth file ({getattr(e, 'strerror', None) or e})") from None


def _floats(path: Path, lineno: int, tokens: Iterable[str]) -> list[float]:
    try:
        out = [float(t) for t in tokens]
    except ValueError:
        raise InputError(f"{path}:{lineno}: expected numbers, got {' '.join(tokens)!r}") from None
    if not all(np.isfinite(out)):
        raise InputError(f"{path}:{lineno}: non-finite number in {' '.join(tokens)!r}")
    return out


def _check_rotation(path: Path, R: NDArray[np.float64], what: str = "rotation") -> None:
    if (np.abs(R @ R.T - np.eye(3)).max() > _ROT_TOL) or abs(np.linalg.det(R) - 1.0) > _ROT_TOL:
        raise InputError(f"{path}: {what} is not a rotation matrix (R R^T != I or det R != 1)")


def quat_to_rot(qw: float, qx: float, qy: float, qz: float) -> NDArray[np.float64]:
    """Rotation matrix of a Hamilton quaternion, w first (COLMAP's file order), normalised first;
    pycolmap's Rotation3d takes it x, y, z, w."""
    q = np.array([qx, qy, qz, qw], np.float64)
    return np.asarray(pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix(), np.float64)


def _colmap_camera_model(name: str) -> pycolmap.Camera | None:
    """A default camera of COLMAP's model `name` (its parameter layout), None if COLMAP has no such model."""
    if name == "INVALID" or name not in pycolmap.CameraModelId.__members__:
        return None
    return pycolmap.Camera.create_from_model_name(0, name, 1.0, 1, 1)


def _check_names(gt: dict[str, GtCamera], scene_names: Iterable[str] | None,
                 source_of: dict[str, Path]) -> None:
    if scene_names is None:
        return
    known = set(scene_names)
    for name in gt:
        if name not in known:
            raise InputError(f"{source_of[name]}: ground truth names image {name!r}, which the scene does not have")


# (a) COLMAP text --------------------------------------------------------------------------------
def read_colmap_cameras_txt(path: str | Path) -> dict[int, tuple[NDArray[np.float64], tuple[int, int]]]:
    """{camera_id: (K in OpenCV convention, (w, h))} of a COLMAP cameras.txt."""
    path = Path(path)
    cams: dict[int, tuple[NDArray[np.float64], tuple[int, int]]] = {}
    for lineno, raw in enumerate(_read_text(path).splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tok = line.split()
        if len(tok) < 5:
            raise InputError(f"{path}:{lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {line!r}")
        try:
            cid, w, h = int(tok[0]), int(tok[2]), int(tok[3])
        except ValueError:
            raise InputError(f"{path}:{lineno}: camera id, width and height must be integers: {line!r}") from None
        model = tok[1].upper()
        layout = _colmap_camera_model(model)
        if layout is None:
            raise InputError(f"{path}:{lineno}: unknown camera model {tok[1]!r}")
        n, f_idx, pp_idx = len(layout.params), layout.focal_length_idxs(), layout.principal_point_idxs()
        params = _floats(path, lineno, tok[4:])
        if len(params) != n:
            raise InputError(f"{path}:{lineno}: camera model {model} takes {n} parameters, got {len(params)}")
        if not f_idx or len(pp_idx) != 2:
            raise InputError(f"{path}:{lineno}: camera model {model} has no focal length and principal point")
        if w <= 0 or h <= 0:
            raise InputError(f"{path}:{lineno}: image size {w}x{h} must be positive")
        fx, fy = params[f_idx[0]], params[f_idx[-1]]
        cx, cy = params[pp_idx[0]], params[pp_idx[1]]
        if fx <= 0 or fy <= 0:
            raise InputError(f"{path}:{lineno}: focal length must be positive")
        if cid in cams:
            raise InputError(f"{path}:{lineno}: camera id {cid} appears twice")
        K = np.array([[fx, 0, cx - COLMAP_PIXEL_OFFSET], [0, fy, cy - COLMAP_PIXEL_OFFSET], [0, 0, 1]], np.float64)
        cams[cid] = (K, (w, h))
    if not cams:
        raise InputError(f"{path}: no cameras in the file")
    return cams


def _is_points2d_line(line: str) -> bool:
    tok = line.split()
    if len(tok) % 3:
        return False
    try:
        [float(t) for t in tok]
    except ValueError:
        return False
    return True


def read_colmap_text(gt_dir: str | Path, scene_names: Iterable[str] | None = None) -> dict[str, GtCamera]:
    """GT from `gt_dir/cameras.txt` + `gt_dir/images.txt` (see module doc)."""
    gt_dir = Path(gt_dir)
    cams = read_colmap_cameras_txt(gt_dir / "cameras.txt")
    path = gt_dir / "images.txt"
    lines = _read_text(path).splitlines()
    out: dict[str, GtCamera] = {}
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        lineno = i + 1
        i += 1
        if not line or line.startswith("#"):
            continue
        tok = line.split()
        if len(tok) < 10:
            raise InputError(f"{path}:{lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {line!r}")
        try:
            int(tok[0])
            cid = int(tok[8])
        except ValueError:
            raise InputError(f"{path}:{lineno}: image id and camera id must be integers: {line!r}") from None
        qw, qx, qy, qz, tx, ty, tz = _floats(path, lineno, tok[1:8])
        name = " ".join(tok[9:])
        if np.linalg.norm([qw, qx, qy, qz]) < 1e-9:
            raise InputError(f"{path}:{lineno}: zero quaternion for image {name!r}")
        if cid not in cams:
            raise InputError(f"{path}:{lineno}: image {name!r} uses camera {cid}, which cameras.txt lacks")
        if name in out:
            raise InputError(f"{path}:{lineno}: image {name!r} appears twice")
        # the POINTS2D line that follows (possibly empty); tolerate files written without it
        # (an image line has >= 10 tokens with a non-numeric name: never a multiple of 3 numbers)
        if i < len(lines) and (not lines[i].strip() or _is_points2d_line(lines[i])):
            i += 1
        R = quat_to_rot(qw, qx, qy, qz)
        K, size = cams[cid]
        out[name] = GtCamera(K.copy(), np.concatenate([R, np.array([[tx], [ty], [tz]])], 1), size)
    if not out:
        raise InputError(f"{path}: no images in the file")
    _check_names(out, scene_names, {n: path for n in out})
    return out


# (b) Strecha .camera ----------------------------------------------------------------------------
def read_strecha_camera(path: str | Path) -> GtCamera:
    """One Strecha `.camera` file (see module doc)."""
    path = Path(path)
    rows = [(n, ln.split()) for n, ln in enumerate(_read_text(path).splitlines(), 1) if ln.strip()]
    if len(rows) < 9:
        raise InputError(f"{path}: expected 9 lines (K 3, distortion 1, R 3, C 1, size 1), found {len(rows)}")
    vals = [_floats(path, n, tok) for n, tok in rows[:9]]
    for k, (n, _) in enumerate(rows[:9]):
        want = 2 if k == 8 else 3
        if k == 3:  # distortion: any number of coefficients
            continue
        if len(vals[k]) != want:
            raise InputError(f"{path}:{n}: expected {want} numbers, got {len(vals[k])}")
    K = np.array(vals[0:3], np.float64)
    R = np.array(vals[4:7], np.float64)
    C = np.array(vals[7], np.float64)
    w, h = vals[8]
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise InputError(f"{path}:{rows[8][0]}: image size {w} x {h} must be positive integers")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise InputError(f"{path}: K is not an upper-triangular intrinsic matrix with positive focal lengths")
    _check_rotation(path, R)
    Rcw = R.T
    return GtCamera(K, np.concatenate([Rcw, (-Rcw @ C)[:, None]], 1), (int(w), int(h)))


def read_strecha(cam_dir: str | Path, scene_names: Iterable[str] | None = None) -> dict[str, GtCamera]:
    """GT from every `<image>.camera` in `cam_dir`; the image name is the file name without
    `.camera` (e.g. `0000.jpg.camera` -> `0000.jpg`)."""
    cam_dir = Path(cam_dir)
    files = sorted(p for p in cam_dir.iterdir() if p.is_file() and p.name.endswith(".camera"))
    if not files:
        raise InputError(f"{cam_dir}: no .camera files")
    out, src = {}, {}
    for p in files:
        name = p.name[: -len(".camera")]
        out[name] = read_strecha_camera(p)
        src[name] = p
    _check_names(out, scene_names, src)
    return out


# discovery --------------------------------------------------------------------------------------
def gt_source(scene_dir: str | Path) -> tuple[str, Path] | None:
    """("colmap", gt_dir) or ("strecha", gt/cameras) when the scene has GT, else None."""
    gt = Path(scene_dir) / "gt"
    if (gt / "cameras.txt").is_file() and (gt / "images.txt").is_file():
        return "colmap", gt
    cams = gt / "cameras"
    if cams.is_dir() and any(p.name.endswith(".camera") for p in cams.iterdir()):
        return "strecha", cams
    return None


def find_gt(scene_dir: str | Path, check_names: bool = True) -> dict[str, GtCamera] | None:
    """The scene's GT (COLMAP text preferred, then Strecha), or None when it has none.

    With `check_names`, GT naming an image that is not in the scene's image folder raises
    InputError (naming the GT file); GT may cover fewer images than the scene.
    """
    from recon.core.scene import find_image_dir, list_candidates

    src = gt_source(scene_dir)
    if src is None:
        return None
    kind, where = src
    names = list_candidates(find_image_dir(scene_dir))[0] if check_names else None
    return read_colmap_text(where, names) if kind == "colmap" else read_strecha(where, names)
