"""Writing the COLMAP database: cameras, images, keypoints, raw matches, geometric verification.

pycolmap 4 API used here (checked against pycolmap 4.2.1):

* `pycolmap.Database.open(path)` creates/opens a database; `import_images(db_path, image_dir,
  camera_mode, image_names=[...], options=ImageReaderOptions())` needs the file to exist already
  (it does not create it) and writes cameras (focal length from EXIF where present, else
  `default_focal_length_factor * max(w, h)`), images, and the trivial rig and frame per image
  that COLMAP >= 3.12 requires. It logs and skips files it cannot read.
* `Database.write_keypoints(image_id, (N, 2) float32)` and `write_matches(id0, id1, (M, 2)
  uint32)`, inside `with pycolmap.DatabaseTransaction(db):` so a batch is all-or-nothing.
* `pycolmap.geometric_verification(db_path, GeometricVerifierOptions, ExistingMatchedPairingOptions,
  TwoViewGeometryOptions)` verifies every pair that has matches (F / E / H model selection,
  COLMAP's own RANSAC): it fills the `two_view_geometries` table that the mapper reads.

Keypoint convention: `matching/` uses OpenCV's (centre of the top-left pixel at (0, 0)); COLMAP
puts it at (0.5, 0.5), so `write_keypoints` adds 0.5 on the way in (and `read_keypoints_opencv`
subtracts it).

Atomicity: the pipeline builds the database in `database.db.tmp` and renames it over
`database.db` only when complete (`build_database`), so an interrupted run never leaves a
half-written database under the final name. A database damaged afterwards (a disk error, a
stray write) can still carry a matching fingerprint in `cache/state.json`:
`database_is_sound` (SQLite's `PRAGMA quick_check` plus the tables COLMAP reads) must pass
before one is reused, else it is rebuilt. A full disk while building is raised as
`OSError(ENOSPC)` naming the database (SQLite reports it as "database or disk is full").
"""

from __future__ import annotations

import errno
import os
import sqlite3
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pycolmap
from numpy.typing import NDArray

CAMERA_MODES: tuple[str, ...] = ("auto", "single", "per-image")
CAMERA_MODELS: tuple[str, ...] = ("SIMPLE_RADIAL", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL", "OPENCV")
"""COLMAP camera models `recon run --camera-model` offers (the first is the default, COLMAP's own);
`recon export` undistorts every one of them."""
COLMAP_PIXEL_OFFSET = 0.5  # COLMAP keypoint = OpenCV keypoint + 0.5
# the tables the pipeline and COLMAP's mapper read (pycolmap >= 3.12 schema)
REQUIRED_TABLES: tuple[str, ...] = ("cameras", "images", "keypoints", "matches", "two_view_geometries",
                                    "rigs", "frames")


def remove_database(path: str | Path) -> None:
    """Delete a database file and its SQLite side files (-journal, -wal, -shm), if present."""
    for p in (Path(path), Path(f"{path}-journal"), Path(f"{path}-wal"), Path(f"{path}-shm")):
        try:
            p.unlink()
        except FileNotFoundError:
            pass


_remove = remove_database


def database_problem(path: str | Path) -> str | None:
    """Why the database at `path` cannot be trusted (one line), or None when it is sound.

    Sound = SQLite opens it read-only, `PRAGMA quick_check` says "ok" (page-level damage, a
    truncated file, garbage bytes) and it has the tables COLMAP needs, with at least one camera
    and one image. Reads only; never modifies the file.
    """
    p = Path(path)
    if not p.is_file():
        return "missing"
    try:
        con = sqlite3.connect(f"{p.resolve().as_uri()}?mode=ro", uri=True, timeout=1.0)
    except sqlite3.Error as e:
        return f"cannot open: {e}"
    try:
        rows = con.execute("PRAGMA quick_check").fetchall()
        if [r[0] for r in rows] != ["ok"]:
            return f"SQLite integrity check failed: {rows[0][0] if rows else 'no answer'}"
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        missing = [t for t in REQUIRED_TABLES if t not in tables]
        if missing:
            return f"not a COLMAP database (no table {', '.join(missing)})"
        for t in ("cameras", "images"):
            if con.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0] == 0:
                return f"no {t}"
    except sqlite3.Error as e:
        return f"unreadable: {e}"
    finally:
        con.close()
    return None


def database_is_sound(path: str | Path) -> bool:
    """True when the database can be reused (see `database_problem`). The pipeline must check
    this before trusting a database whose fingerprint matches; rebuild it when False."""
    return database_problem(path) is None


def _is_disk_full(e: BaseException, folder: Path | None = None) -> bool:
    """True for a full-disk failure: ENOSPC, SQLite's "database or disk is full", or (COLMAP
    hides the cause: "No registered database factory succeeded") less than 1 MB free in `folder`."""
    if isinstance(e, OSError):
        return e.errno in (errno.ENOSPC, errno.EDQUOT)
    text = str(e).lower()
    if "disk is full" in text or "no space left" in text:
        return True
    if folder is not None:
        import shutil

        try:
            return shutil.disk_usage(folder).free < (1 << 20)
        except OSError:
            return False
    return False


def estimate_database_bytes(num_images: int, num_keypoints: int = 0, num_matches: int = 0, num_pairs: int = 0) -> int:
    """A generous upper bound of the disk space building a database needs (bytes): keypoints
    (24 B each, COLMAP's widest layout), raw and verified matches (8 B each), rows, SQLite's base
    size, and x3 for the write-ahead log and its checkpoint, plus 1 MB."""
    raw = 24 * num_keypoints + 16 * num_matches + 512 * (num_images + num_pairs)
    return (256 << 10) + 3 * raw + (1 << 20)


def require_free_space(db_path: str | Path, nbytes: int) -> None:
    """OSError(ENOSPC) naming `db_path` when its folder has less than `nbytes` free.

    Needed before COLMAP writes a database: a full disk inside one of pycolmap's transactions
    throws from a destructor, and the process aborts (SIGABRT and a C stack dump) instead of
    raising an exception Python could catch (pycolmap 4.2.1).
    """
    import shutil

    folder = Path(db_path).parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < nbytes:
        raise OSError(errno.ENOSPC, f"No space left on device ({free >> 10} KB free, about {nbytes >> 10} KB "
                                    f"needed)", str(db_path))


def _import(db_path: Path, image_dir: Path, names: Sequence[str], mode: pycolmap.CameraMode,
            camera_model: str) -> None:
    require_free_space(db_path, estimate_database_bytes(len(names)))
    _remove(db_path)
    pycolmap.Database.open(str(db_path)).close()
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = camera_model
    pycolmap.import_images(str(db_path), str(image_dir), mode, image_names=list(names), options=opts)


def _same_camera(cams: Sequence[pycolmap.Camera]) -> bool:
    c0 = cams[0]
    return all(c.model == c0.model and c.width == c0.width and c.height == c0.height
               and np.allclose(c.params, c0.params) for c in cams[1:])


def import_scene_images(db_path: str | Path, image_dir: str | Path, names: Sequence[str],
                        camera_mode: str = "auto", camera_model: str = "SIMPLE_RADIAL",
                        ) -> tuple[dict[str, int], str, list[str]]:
    """Create a fresh database at `db_path` with cameras and images.

    camera_mode: "single" (one shared camera; every image must have the same size), "per-image",
    or "auto": one shared camera when all images come from one camera (same size and the same
    EXIF-derived intrinsics), else one per image. Returns ({name: image_id}, mode used, names
    COLMAP could not import).
    """
    db_path, image_dir = Path(db_path), Path(image_dir)
    if camera_mode not in CAMERA_MODES:
        raise ValueError(f"camera mode {camera_mode!r}; choose one of {', '.join(CAMERA_MODES)}")
    mode = pycolmap.CameraMode.SINGLE if camera_mode == "single" else pycolmap.CameraMode.PER_IMAGE
    _import(db_path, image_dir, names, mode, camera_model)
    used = "single" if camera_mode == "single" else "per-image"
    db = pycolmap.Database.open(str(db_path))
    try:
        cams = db.read_all_cameras()
        ids = {im.name: int(im.image_id) for im in db.read_all_images()}
    finally:
        db.close()
    if camera_mode == "auto" and len(cams) > 1 and _same_camera(cams):
        _import(db_path, image_dir, names, pycolmap.CameraMode.SINGLE, camera_model)
        used = "single"
        db = pycolmap.Database.open(str(db_path))
        try:
            ids = {im.name: int(im.image_id) for im in db.read_all_images()}
        finally:
            db.close()
    missing = [n for n in names if n not in ids]
    return ids, used, missing


def write_keypoints_and_matches(db_path: str | Path, image_ids: Mapping[str, int],
                                keypoints: Mapping[str, NDArray[np.float32]],
                                pairs: Sequence[tuple[str, str]], matches: Sequence[NDArray],
                                on_item: Callable[[], None] | None = None) -> None:
    """Write keypoints (OpenCV convention in, COLMAP's +0.5 in the file) and raw matches."""
    db = pycolmap.Database.open(str(db_path))
    try:
        with pycolmap.DatabaseTransaction(db):
            for name, iid in image_ids.items():
                k = np.asarray(keypoints.get(name, np.zeros((0, 2), np.float32)), np.float32).reshape(-1, 2)
                db.write_keypoints(iid, np.ascontiguousarray(k + COLMAP_PIXEL_OFFSET, np.float32))
                if on_item:
                    on_item()
            for (a, b), m in zip(pairs, matches):
                if a in image_ids and b in image_ids and len(m):
                    db.write_matches(image_ids[a], image_ids[b], np.ascontiguousarray(m, np.uint32))
                if on_item:
                    on_item()
    finally:
        db.close()


def two_view_options(seed: int = 0, max_error_px: float = 4.0, min_num_inliers: int = 15
                     ) -> pycolmap.TwoViewGeometryOptions:
    """Verification options for raw (not homography-filtered) wide-baseline matches.

    The raw matches can be outlier-heavy, so RANSAC may try more hypotheses (min_inlier_ratio
    0.1, up to 20000 trials); seeded for reproducibility; `max_H_inlier_ratio` 0.95 (see below).
    """
    o = pycolmap.TwoViewGeometryOptions()
    o.min_num_inliers = int(min_num_inliers)
    o.ransac.max_error = float(max_error_px)
    o.ransac.min_inlier_ratio = 0.1
    o.ransac.confidence = 0.9999
    o.ransac.max_num_trials = 20000
    # A view-synthesis matcher concentrates its matches on the surface its best view
    # rectifies, so >80 % of a pair's matches often fit one homography and COLMAP's default
    # (0.8) would call the pair planar and keep only that plane's inliers: pairs then share no
    # keypoints and images do not chain (measured: rendered corner, 4 views 29 deg apart, 3/4
    # registered). Above 0.95 the pair really is planar.
    o.max_H_inlier_ratio = 0.95
    o.ransac.random_seed = int(seed)
    return o


def verify(db_path: str | Path, options: pycolmap.TwoViewGeometryOptions, num_threads: int = -1) -> None:
    """COLMAP's geometric verification (F / E / H) of every matched pair in the database."""
    vopts = pycolmap.GeometricVerifierOptions()
    vopts.num_threads = int(num_threads)
    pycolmap.geometric_verification(str(db_path), vopts, pycolmap.ExistingMatchedPairingOptions(), options)


def read_verified(db_path: str | Path) -> dict[tuple[int, int], tuple[int, str, NDArray[np.uint32]]]:
    """{(image_id0, image_id1) with id0 < id1: (num inliers, configuration name, inlier matches)}."""
    db = pycolmap.Database.open(str(db_path))
    try:
        pair_ids, geoms = db.read_two_view_geometries()
    finally:
        db.close()
    out = {}
    for pid, g in zip(pair_ids, geoms):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        m = np.asarray(g.inlier_matches, np.uint32).reshape(-1, 2)
        try:
            conf = pycolmap.TwoViewGeometryConfiguration(int(g.config)).name
        except (TypeError, ValueError):
            conf = str(g.config).split(".")[-1]
        out[(int(a), int(b))] = (int(len(m)), conf, m)
    return out


def read_keypoints_opencv(db_path: str | Path, image_id: int) -> NDArray[np.float32]:
    """Keypoints of one image back in OpenCV convention (the inverse of the +0.5 on writing)."""
    db = pycolmap.Database.open(str(db_path))
    try:
        k = np.asarray(db.read_keypoints(int(image_id)), np.float32)
    finally:
        db.close()
    return (k[:, :2] - COLMAP_PIXEL_OFFSET).astype(np.float32) if len(k) else np.zeros((0, 2), np.float32)


def build_database(db_path: str | Path, image_dir: str | Path, names: Sequence[str], camera_mode: str,
                   keypoints: Mapping[str, NDArray[np.float32]], pairs: Sequence[tuple[str, str]],
                   matches: Sequence[NDArray], two_view: pycolmap.TwoViewGeometryOptions,
                   num_threads: int = -1, on_stage: Callable[[str], None] | None = None,
                   on_item: Callable[[], None] | None = None,
                   ) -> tuple[dict[str, int], str, list[str]]:
    """Build and verify the whole database in `<db_path>.tmp`, then rename it to `db_path`.

    Returns ({name: image_id}, camera mode used, names COLMAP could not import).
    """
    db_path = Path(db_path)
    tmp = db_path.with_name(db_path.name + ".tmp")
    require_free_space(db_path, estimate_database_bytes(  # the old file is replaced only at the end
        len(names), sum(len(k) for k in keypoints.values()), sum(len(m) for m in matches), len(pairs)))
    try:
        if on_stage:
            on_stage("import")
        ids, used, missing = import_scene_images(tmp, image_dir, names, camera_mode)
        if on_stage:
            on_stage("write")
        write_keypoints_and_matches(tmp, ids, keypoints, pairs, matches, on_item=on_item)
        if on_stage:
            on_stage("verify")
        verify(tmp, two_view, num_threads)
    except BaseException as e:
        _remove(tmp)
        if isinstance(e, Exception) and not isinstance(e, OSError) and _is_disk_full(e, db_path.parent):
            raise OSError(errno.ENOSPC, "No space left on device", str(db_path)) from e
        if isinstance(e, OSError) and e.filename is None:
            e.filename = str(db_path)
        raise
    for suffix in ("-journal", "-wal", "-shm"):  # a closed sqlite db leaves none; be safe
        side = Path(f"{tmp}{suffix}")
        if side.exists():
            os.replace(side, Path(f"{db_path}{suffix}"))
    os.replace(tmp, db_path)
    return ids, used, missing
