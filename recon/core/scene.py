"""Scene input: find the photos of a scene folder, decode them once, and flag bad ones.

A scene folder holds its photos in `SCENE_DIR/images/` (searched recursively, like COLMAP's
ImageReader: a photo in `images/cam1/a.jpg` is named `cam1/a.jpg`, with `/` on every platform) or
directly in `SCENE_DIR` (top level only: SCENE_DIR also holds gt/ and the outputs). Photos are
JPEG, PNG or TIFF with any case of extension (`.JPG`, `.Tif`).

What is skipped, and how (every case is one line in `Scene.warnings` and, for image files, one
row in `Scene.skipped`, which the run report lists under `skipped`):

* files with other extensions: skipped with one summary warning (hidden dot-files silently);
* entries with an image extension that are not regular files (a broken symbolic link, a folder
  named `x.png`, a FIFO or device, which would block or never end a read): skipped with one
  summary warning naming them;
* files that do not decode (corrupt or truncated JPEG, empty file, unknown format) or are smaller
  than `matching.io.MIN_IMAGE_SIDE`: skipped;
* duplicates, i.e. images whose decoded pixels are identical to an earlier image (in name
  order): the first is kept and the others skipped. Two identical photos have no baseline, so
  they add nothing to a reconstruction but a degenerate pair (every match "stationary", which
  COLMAP's two-view geometry cannot explain by a rigid motion), and they would double the
  matching work. Keeping one is the useful choice; the report says which was kept.

Images of different sizes are fine (each gets its own camera in `--camera-mode auto`).
Names with spaces and non-ASCII characters work: files are read as bytes and decoded with
`cv2.imdecode`, never through OpenCV's path-based readers.

EXIF orientation: not applied, on purpose. COLMAP (pycolmap 4.2's `import_images` and `Bitmap`)
ignores the tag: a 100x60 JPEG tagged "rotate 90" gets a 100x60 camera. Rotating the pixels here
would put our keypoints in a frame that does not match the database's image sizes; in the stored
frame the rotation is simply part of each camera's pose. Images with a non-trivial orientation get
one warning (their model cameras are in the stored, unrotated frame; `recon export` writes them so).

Every kept image is decoded once per run to 8-bit gray (EXIF orientation ignored, the same pixel
frame COLMAP uses) and downscaled to the working resolution (`max_size`, longer side) for
matching; `SceneImage.scale_xy` maps working-resolution pixels back to the full resolution with
the pixel-centre-correct formula `x_full = (x_work + 0.5) / sx - 0.5` (see `to_full_res`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.errors import InputError
from matching.io import MIN_IMAGE_SIDE, resize_max, to_gray_u8, to_original_px

IMAGE_EXTS: frozenset[str] = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff"})


@dataclass
class SceneImage:
    """One usable photo: its name (relative to the image folder), size and pixel digest."""

    name: str
    path: Path
    width: int  # full resolution, px
    height: int
    digest: str  # sha1 of the decoded full-resolution gray pixels (content identity)
    work_width: int = 0  # working (matching) resolution, px
    work_height: int = 0

    @property
    def scale_xy(self) -> tuple[float, float]:
        """(sx, sy) = working size / full size per axis (1.0 when not downscaled)."""
        return self.work_width / self.width, self.work_height / self.height


@dataclass
class Skipped:
    name: str
    reason: str


@dataclass
class Scene:
    """The photos of a scene after scanning: kept images, skipped files, warnings."""

    root: Path  # the SCENE_DIR given by the user (resolved)
    image_dir: Path  # where the photos are (SCENE_DIR/images or SCENE_DIR)
    candidates: list[str]  # every file with an image extension, sorted
    images: list[SceneImage] = field(default_factory=list)
    skipped: list[Skipped] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        return [im.name for im in self.images]

    def image(self, name: str) -> SceneImage:
        for im in self.images:
            if im.name == name:
                return im
        raise KeyError(name)


def find_image_dir(scene_dir: str | Path) -> Path:
    """SCENE_DIR/images when it exists, else SCENE_DIR; InputError when SCENE_DIR is not a folder."""
    root = Path(scene_dir)
    if not root.exists():
        raise InputError(f"{root}: no such scene folder")
    if not root.is_dir():
        raise InputError(f"{root}: not a folder (expected a scene folder with photos or images/)")
    sub = root / "images"
    return sub if sub.is_dir() else root


def require_images(scene_dir: str | Path, minimum: int = 2) -> tuple[Path, list[str]]:
    """(image folder, image file names) of a scene, checked before anything is decoded or
    written: InputError for a missing folder or one without image files, UserError when it
    holds fewer than `minimum` image files."""
    from recon.errors import UserError

    image_dir = find_image_dir(scene_dir)
    names, _ = list_candidates(image_dir)
    if not names:
        raise InputError(f"{image_dir}: no images found (expected .jpg, .jpeg, .png, .tif or .tiff files)")
    if len(names) < minimum:
        raise UserError(f"{image_dir}: need at least {minimum} images to reconstruct, found {len(names)} "
                        f"({', '.join(names)})")
    return image_dir, names


def not_regular_images(image_dir: Path) -> list[tuple[str, str]]:
    """[(name, what it is)] for entries with an image extension that are not regular files
    (broken symbolic links, folders, FIFOs, devices); `list_candidates` leaves them out."""
    out: list[tuple[str, str]] = []
    try:
        entries = sorted(image_dir.iterdir(), key=lambda p: p.name)
    except OSError:
        return out
    for p in entries:
        if p.name.startswith(".") or p.suffix.lower() not in IMAGE_EXTS or p.is_file():
            continue
        if p.is_symlink() and not p.exists():
            out.append((p.name, "broken symbolic link"))
        elif p.is_dir():
            out.append((p.name, "a folder"))
        else:
            out.append((p.name, "not a regular file"))
    return out


def lists_subfolders(image_dir: Path) -> bool:
    """Whether a scene's photos are read from the subfolders of `image_dir` too: yes for an
    `images/` folder (as COLMAP's image reader), no for photos directly in SCENE_DIR (which also
    holds gt/ and the outputs)."""
    return image_dir.name == "images"


def list_candidates(image_dir: Path, recursive: bool | None = None) -> tuple[list[str], list[str]]:
    """(image file names, other file names) in `image_dir`, both sorted; with `recursive` (default:
    when the folder is an `images/` folder), in its subfolders too, named by their relative path
    with `/` (hidden folders are not entered). Symlinked subfolders are followed, each real
    folder once: a link back to a parent (a loop) or a second link to the same folder is not
    entered again, so the listing ends and holds no photo twice."""
    if recursive is None:
        recursive = lists_subfolders(image_dir)
    images: list[str] = []
    others: list[str] = []
    seen: set[Path] = {image_dir.resolve()}

    def walk(folder: Path, prefix: str) -> None:
        try:
            entries = sorted(folder.iterdir(), key=lambda p: p.name)
        except OSError as e:
            raise InputError(f"{folder}: cannot list folder ({e.strerror or e})") from None
        for p in entries:
            if p.name.startswith("."):
                continue
            if recursive and p.is_dir():
                real = p.resolve()
                if real in seen:
                    continue
                seen.add(real)
                walk(p, f"{prefix}{p.name}/")
            elif p.is_file():
                (images if p.suffix.lower() in IMAGE_EXTS else others).append(prefix + p.name)

    walk(image_dir, "")
    return sorted(images), sorted(others)


def exif_orientation(path: Path) -> int:
    """The EXIF orientation tag (1-8; 1 = as stored) of a photo, read from its header; 1 when absent."""
    from PIL import Image

    try:
        with Image.open(path) as f:
            return int(f.getexif().get(0x0112, 1) or 1)
    except Exception:  # unreadable headers are reported by the decoder, not here
        return 1


def _decode_one(path: Path, max_size: int | None) -> tuple[NDArray[np.uint8], int, int, str] | str:
    """(working gray, full w, full h, digest) or a one-line reason why the file is unusable."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        return f"cannot read ({e.strerror or e})"
    if data.size == 0:
        return "empty file"
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        return "not a readable image (corrupt or truncated data, or unknown format)"
    h, w = img.shape[:2]
    if min(h, w) < MIN_IMAGE_SIDE:
        return f"image is {w}x{h} px; each side must be at least {MIN_IMAGE_SIDE} px"
    gray = to_gray_u8(img)
    del img
    digest = hashlib.sha1(gray.tobytes() + str(gray.shape).encode()).hexdigest()[:20]
    work, _ = resize_max(gray, max_size)
    return np.ascontiguousarray(work), int(w), int(h), digest


def scan_scene(scene_dir: str | Path, max_size: int | None = 1600, workers: int = 1,
               on_image: Callable[[str], None] | None = None,
               ) -> tuple[Scene, dict[str, NDArray[np.uint8]]]:
    """Scan and decode a scene: (Scene, {name: working-resolution 8-bit gray image}).

    Raises InputError for a missing folder or one without any image file; a folder with only
    one usable image is returned as is (the caller decides, see `recon.core.pipeline`).
    `on_image(name)` is called after each decoded file (progress).
    """
    root = Path(scene_dir).resolve()
    image_dir = find_image_dir(root)
    names, others = list_candidates(image_dir)
    scene = Scene(root=root, image_dir=image_dir, candidates=names)
    if others:
        shown = ", ".join(others[:5]) + (f" and {len(others) - 5} more" if len(others) > 5 else "")
        scene.warnings.append(f"skipped {len(others)} non-image file(s) in {image_dir}: {shown}")
    odd = not_regular_images(image_dir)
    if odd:
        shown = ", ".join(f"{n} ({what})" for n, what in odd[:5]) + (f" and {len(odd) - 5} more" if len(odd) > 5 else "")
        scene.warnings.append(f"skipped {len(odd)} entr{'y' if len(odd) == 1 else 'ies'} with an image name that "
                              f"{'is' if len(odd) == 1 else 'are'} not a file in {image_dir}: {shown}")
    if not names:
        raise InputError(f"{image_dir}: no images found (expected .jpg, .jpeg, .png, .tif or .tiff files)")

    def job(name: str):
        out = _decode_one(image_dir / name, max_size)
        if on_image is not None:
            on_image(name)
        return out

    with ThreadPoolExecutor(max_workers=max(1, workers)) as ex:  # imdecode releases the GIL
        decoded = list(ex.map(job, names))

    grays: dict[str, NDArray[np.uint8]] = {}
    first_by_digest: dict[str, str] = {}
    for name, res in zip(names, decoded):
        if isinstance(res, str):
            scene.skipped.append(Skipped(name, res))
            scene.warnings.append(f"skipped {name}: {res}")
            continue
        work, w, h, digest = res
        if digest in first_by_digest:
            reason = f"duplicate of {first_by_digest[digest]} (identical pixels)"
            scene.skipped.append(Skipped(name, reason))
            scene.warnings.append(f"skipped {name}: {reason}")
            continue
        first_by_digest[digest] = name
        scene.images.append(SceneImage(name, image_dir / name, w, h, digest,
                                       int(work.shape[1]), int(work.shape[0])))
        grays[name] = work
    rotated = [im.name for im in scene.images if exif_orientation(im.path) != 1]
    if rotated:
        shown = ", ".join(rotated[:3]) + (f" and {len(rotated) - 3} more" if len(rotated) > 3 else "")
        scene.warnings.append(f"{len(rotated)} photo(s) carry an EXIF rotation ({shown}); used as stored, as COLMAP "
                              "does: their cameras see the unrotated pixels")
    return scene, grays


def to_working(kpts: NDArray, scale_xy: tuple[float, float]) -> NDArray[np.float64]:
    """Full-resolution keypoints (OpenCV convention) -> working resolution, the inverse of
    `to_full_res`: x_work = (x_full + 0.5) * sx - 0.5 per axis."""
    sx, sy = scale_xy
    k = np.asarray(kpts, np.float64).reshape(-1, 2)
    return np.stack([(k[:, 0] + 0.5) * sx - 0.5, (k[:, 1] + 0.5) * sy - 0.5], axis=1)


def to_full_res(kpts: NDArray, scale_xy: tuple[float, float]) -> NDArray[np.float32]:
    """Working-resolution keypoints (OpenCV convention) -> full-resolution keypoints:
    x_full = (x_work + 0.5) / sx - 0.5 per axis (`matching.io.to_original_px`, with the exact
    per-axis scale of the rounded working size)."""
    return to_original_px(kpts, scale_xy)
