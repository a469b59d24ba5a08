"""Render a preset scene: textured planes seen by pinhole cameras, with exact ground truth.

Each plane's texture is warped into each camera by its plane-to-image homography
(`H_img_from_tex`), at `SUPERSAMPLE` x the output resolution and area-averaged down, so
grazing views (80 deg) do not alias; a per-pixel depth computed from the plane equation
(a z-buffer) makes nearer planes occlude farther ones, and back-facing planes are skipped.
Pixels are in OpenCV's convention while rendering (centre of the top-left pixel at (0, 0));
the ground truth is written in COLMAP's text format and convention (centre at (0.5, 0.5), so
cx = width / 2), with poses as cam_from_world (x right, y down, z forward).

Everything is written into a temporary folder beside OUT_DIR and renamed into place, so an
interrupted render never leaves half a scene; `--overwrite` replaces OUT_DIR/images and
OUT_DIR/gt only, never other files in OUT_DIR. Same preset + seed = byte-identical files.

Ownership: a render leaves `OUT_DIR/.recon_render.json` (`RENDER_MARKER`). An existing
non-empty `images/` or `gt/` is replaced (with `--overwrite`) only when that marker says this
command made them (or, for scenes rendered before the marker existed, when `gt/scene.json` is a
render's and names every file in `images/`); anything else (a user's photos, their ground
truth) is refused and never touched, with or without `--overwrite` (`check_render_target`).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.errors import InputError

from .presets import DEFAULT_PRESET, Plane, ScenePreset, get_preset, viewing_angle_deg
from .texture import photo_texture, procedural_texture

SUPERSAMPLE = 3
SKY_BGR = (225, 205, 190)
RENDER_MARKER = ".recon_render.json"  # in OUT_DIR: this command made OUT_DIR/images and OUT_DIR/gt


@dataclass
class RenderedScene:
    """What `render_scene` wrote: the folder, image paths, K (OpenCV convention) and poses."""

    out_dir: Path
    preset: str
    image_paths: list[Path]
    K: NDArray[np.float64]
    cam_from_world: list[NDArray[np.float64]]  # 3x4 [R | t] per image
    viewing_angles_deg: list[dict[str, float]]  # per image: plane name -> angle (visible planes)


def look_at_pose(centre: NDArray, target: NDArray, up=(0.0, 0.0, 1.0)) -> NDArray[np.float64]:
    """cam_from_world [R | t] of a camera at `centre` looking at `target` (x right, y down)."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.hstack([R, (-R @ np.asarray(centre, float))[:, None]])


def camera_centres(preset: ScenePreset) -> list[NDArray[np.float64]]:
    arc = preset.cameras
    el = np.radians(arc.elevation_deg)
    out = []
    for az in np.radians(arc.azimuths_deg):
        d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        out.append(np.asarray(arc.look_at, float) + arc.distance * d)
    return out


def centred_K(image_size: tuple[int, int], focal_px: float) -> NDArray[np.float64]:
    """K with the principal point at the image centre, OpenCV's pixel convention (cx = w/2 - 0.5)."""
    w, h = image_size
    return np.array([[focal_px, 0.0, w / 2.0 - 0.5], [0.0, focal_px, h / 2.0 - 0.5], [0.0, 0.0, 1.0]])


def supersampled(K: NDArray, scale: float) -> NDArray[np.float64]:
    """K of the same camera rendered at `scale` x the resolution (pixel centres kept consistent)."""
    S = np.array([[scale, 0.0, 0.5 * (scale - 1)], [0.0, scale, 0.5 * (scale - 1)], [0.0, 0.0, 1.0]])
    return S @ K


def intrinsics(preset: ScenePreset, scale: float = 1.0) -> NDArray[np.float64]:
    """K in OpenCV's pixel convention (cx = w/2 - 0.5); `scale` = supersampling factor."""
    return supersampled(centred_K(preset.image_size, preset.focal_px), scale)


def H_img_from_tex(K: NDArray, cam_from_world: NDArray, plane: Plane, px_per_m: float) -> NDArray[np.float64]:
    """Homography from texture pixels (row 0 at the top of the plane) to image pixels."""
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    u, v, o = (np.asarray(x, float) for x in (plane.u, plane.v, plane.origin))
    top_left = o + (0.5 / px_per_m) * u + (plane.height - 0.5 / px_per_m) * v
    M = np.stack([R @ u / px_per_m, -R @ v / px_per_m, R @ top_left + t], axis=1)
    return K @ M


def plane_depth(K: NDArray, cam_from_world: NDArray, plane: Plane, size: tuple[int, int]) -> NDArray[np.float32]:
    """Camera-frame depth z of the plane at every pixel (inf where the ray misses it in front)."""
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    n_c = R @ plane.normal
    d_c = float(plane.normal @ np.asarray(plane.origin, float)) + float(n_c @ t)
    coef = n_c @ np.linalg.inv(K)  # (a, b, c): n_c . K^-1 [x, y, 1]
    w, h = size
    xs = np.arange(w, dtype=np.float32)
    ys = np.arange(h, dtype=np.float32)
    denom = coef[0] * xs[None, :] + coef[1] * ys[:, None] + coef[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (d_c / denom).astype(np.float32)
    z[~np.isfinite(z) | (z <= 1e-3)] = np.inf
    return z


def _textures(preset: ScenePreset, textures: list[Path] | None, seed: int) -> list[NDArray[np.uint8]]:
    out = []
    for i, p in enumerate(preset.planes):
        w = int(round(p.width * preset.px_per_m))
        h = int(round(p.height * preset.px_per_m))
        if textures:
            out.append(photo_texture(textures[i % len(textures)], w, h, reuse=i // len(textures)))
        else:
            out.append(procedural_texture(p.width, p.height, preset.px_per_m, seed * 1000 + i))
    return out


def render_view(preset: ScenePreset, texs: list[NDArray[np.uint8]], cam_from_world: NDArray,
                rng: np.random.Generator) -> tuple[NDArray[np.uint8], dict[str, float]]:
    """One image (8-bit BGR) and the viewing angle of each plane it shows."""
    w, h = preset.image_size
    big = (w * SUPERSAMPLE, h * SUPERSAMPLE)
    K_big = intrinsics(preset, SUPERSAMPLE)
    img = np.empty((big[1], big[0], 3), np.uint8)
    img[:] = SKY_BGR
    zbuf = np.full((big[1], big[0]), np.inf, np.float32)
    centre = -cam_from_world[:, :3].T @ cam_from_world[:, 3]
    angles: dict[str, float] = {}
    for plane, tex in zip(preset.planes, texs):
        if float((centre - np.asarray(plane.origin)) @ plane.normal) <= 0:  # back face
            continue
        H = H_img_from_tex(K_big, cam_from_world, plane, preset.px_per_m)
        cover = cv2.warpPerspective(np.full(tex.shape[:2], 255, np.uint8), H, big, flags=cv2.INTER_NEAREST,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        z = plane_depth(K_big, cam_from_world, plane, big)
        draw = (cover > 0) & (z < zbuf)
        if not draw.any():
            continue
        col = cv2.warpPerspective(tex, H, big, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img[draw] = col[draw]
        zbuf[draw] = z[draw]
        if draw.mean() > 0.01:
            angles[plane.name] = round(viewing_angle_deg(plane, centre), 2)
    out = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    if preset.noise_sigma > 0:
        noise = rng.normal(0.0, preset.noise_sigma, out.shape)
        out = np.clip(out.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    return out, angles


def rotmat_to_qvec(R: NDArray) -> NDArray[np.float64]:
    """COLMAP's (qw, qx, qy, qz) of a rotation matrix, qw >= 0 (its `rotmat2qvec`, lower triangle)."""
    K = np.array([
        [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
        [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
        [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0],
        [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(K)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


def write_colmap_gt(gt_dir: Path, preset: ScenePreset, names: list[str], poses: list[NDArray]) -> None:
    """`cameras.txt` (one PINHOLE camera, COLMAP convention) and `images.txt` (cam_from_world)."""
    w, h = preset.image_size
    f = preset.focal_px
    gt_dir.mkdir(parents=True, exist_ok=True)
    (gt_dir / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {w} {h} {f:.6f} {f:.6f} {w / 2.0:.6f} {h / 2.0:.6f}\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, P) in enumerate(zip(names, poses), start=1):
        q = rotmat_to_qvec(P[:, :3])
        t = P[:, 3]
        lines.append(f"{i} {q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f} {t[0]:.12f} {t[1]:.12f} {t[2]:.12f} 1 {name}")
        lines.append("")
    (gt_dir / "images.txt").write_text("\n".join(lines) + "\n")



def view_names(num_views: int) -> list[str]:
    """`view_00.png` ...: two digits, more when there are over 100 views, so name order is view order."""
    width = max(2, len(str(num_views - 1)))
    return [f"view_{i:0{width}d}.png" for i in range(num_views)]


def _non_empty_dir(path: Path) -> bool:
    return path.is_dir() and any(path.iterdir())


def made_by_render(out_dir: Path) -> bool:
    """True when OUT_DIR/images and OUT_DIR/gt were made by `render_scene` (see module doc)."""
    if (out_dir / RENDER_MARKER).is_file():
        return True
    try:  # a render from before the marker existed
        meta = json.loads((out_dir / "gt" / "scene.json").read_text(encoding="utf-8"))
        rendered = set(meta["viewing_angles_deg"]) if "preset" in meta else set()
    except (OSError, ValueError, KeyError, TypeError):
        return False
    present = {p.name for p in (out_dir / "images").iterdir()} if (out_dir / "images").is_dir() else set()
    return bool(rendered) and present <= rendered


def check_render_target(out_dir: str | Path, overwrite: bool) -> None:
    """InputError (one line) unless `render_scene` may write OUT_DIR/images and OUT_DIR/gt;
    reads only (see module doc)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a folder")
    probe = out_dir
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"{out_dir}: {probe} is a file, not a folder")
    taken = [d for d in ("images", "gt") if _non_empty_dir(out_dir / d) or (out_dir / d).is_file()]
    if not taken:
        return
    if not made_by_render(out_dir):
        raise InputError(f"{out_dir / taken[0]} holds files that recon render-scene did not make; it never replaces "
                         f"them (with or without --overwrite): choose another folder")
    if not overwrite:
        raise InputError(f"{out_dir / taken[0]}: folder is not empty; pass --overwrite to replace the scene")


def _swap_into_place(tmp: Path, out_dir: Path, parts: tuple[str, ...]) -> None:
    """Move `tmp/<part>` to `out_dir/<part>` for each part, replacing only those subfolders.

    Other files in OUT_DIR (notes, a reconstruction) are never touched. Old parts are first
    renamed aside, so every step is a rename; `gt` goes before `images`, so an interruption
    leaves at worst new ground truth beside old images -- which the images/ check still guards.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    trash = tmp / ".old"
    trash.mkdir()
    for part in parts:
        dst = out_dir / part
        if dst.exists() or dst.is_symlink():
            os.replace(dst, trash / part)
        os.replace(tmp / part, dst)
    shutil.rmtree(tmp, ignore_errors=True)

def _render_into(tmp: Path, p: ScenePreset, texs: list[NDArray[np.uint8]], names: list[str],
                 poses: list[NDArray], rng: np.random.Generator) -> list[dict[str, float]]:
    """Render every view into `tmp/images` as PNG; the per-view viewing angles (deg)."""
    (tmp / "images").mkdir(parents=True)
    angles = []
    for name, P in zip(names, poses):
        img, ang = render_view(p, texs, P, rng)
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise RuntimeError(f"PNG encoding failed for {name}")
        (tmp / "images" / name).write_bytes(buf.tobytes())
        angles.append(ang)
    return angles


def textures_label(textures: Sequence[str | Path] | None) -> list[str] | str:
    """How a render's textures are recorded (OUT/gt/scene.json's `textures`, benchmark configs):
    the photos' paths, or "procedural"."""
    return [str(t) for t in textures] if textures else "procedural"


def render_scene(out_dir: str | Path, preset: str = DEFAULT_PRESET, textures: list[Path] | None = None,
                 seed: int = 0, image_size: tuple[int, int] | None = None,
                 overwrite: bool = False) -> RenderedScene:
    """Render `preset` into OUT_DIR/images and OUT_DIR/gt (see module doc).

    Raises ValueError for an unknown preset, InputError for a missing texture, a non-empty
    OUT_DIR/images or OUT_DIR/gt without `overwrite` (which replaces images/ and gt/ only), or
    ones this function did not make (see `check_render_target`).
    """
    out_dir = Path(out_dir)
    p = get_preset(preset)
    if image_size is not None:
        scale = image_size[0] / p.image_size[0]
        p = ScenePreset(p.name, p.description, p.planes, p.cameras, tuple(image_size), p.focal_px * scale,
                        p.px_per_m * max(1.0, scale) if scale > 1 else p.px_per_m, p.noise_sigma)
    check_render_target(out_dir, overwrite)
    texs = _textures(p, [Path(t) for t in textures] if textures else None, seed)
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5CE7E])
    K = intrinsics(p)
    poses = [look_at_pose(c, np.asarray(p.cameras.look_at)) for c in camera_centres(p)]
    names = view_names(len(poses))

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.rendering.{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        angles = _render_into(tmp, p, texs, names, poses, rng)
        write_colmap_gt(tmp / "gt", p, names, poses)
        meta = {
            "preset": p.name, "description": p.description, "seed": seed, "image_size": list(p.image_size),
            "focal_px": p.focal_px, "azimuths_deg": list(p.cameras.azimuths_deg), "azimuth_step_deg": p.azimuth_step,
            "textures": textures_label(textures),
            "planes": [{"name": pl.name, "corners_m": pl.corners().round(6).tolist(),
                        "normal": pl.normal.round(6).tolist()} for pl in p.planes],
            "viewing_angles_deg": dict(zip(names, angles)),
            "max_viewing_angle_deg": max((max(a.values()) for a in angles if a), default=0.0),
        }
        (tmp / "gt" / "scene.json").write_text(json.dumps(meta, indent=2))
        out_dir.mkdir(parents=True, exist_ok=True)
        # before anything is swapped in: images/ and gt/ are ours from here on
        (out_dir / RENDER_MARKER).write_text(json.dumps({"command": "render-scene", "preset": p.name,
                                                         "images": names}, indent=1))
        _swap_into_place(tmp, out_dir, ("gt", "images"))
    except BaseException:  # Ctrl-C or an error mid-render: leave no temporary folder behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return RenderedScene(out_dir, p.name, [out_dir / "images" / n for n in names], K, poses, angles)
