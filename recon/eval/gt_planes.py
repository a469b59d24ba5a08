"""Exact correspondences in the rendered scenes: where a pixel of one view lands in another.

The scenes of `scenes/` are textured rectangles seen by pinhole cameras (`scenes.render`), so a
pixel's true match is known exactly: cast its ray from the camera centre, take the nearest
rectangle it meets from the front (the renderer draws front faces only, with a z-buffer), and
project that point into the other view, where it must again be the nearest front face along
that camera's ray (else it is hidden there). `correct_matches` says which matched keypoint
pairs land within `max_px` of that transfer; `transfer_errors` measures a run's verified
matches (its `database.db`) against it, `correct_counts` counts the correct ones per pair and
`correct_error_median` says how precisely they are localised. COLMAP's verified-inlier count only says a match
fits the pair's epipolar geometry (a wrong match along the right line passes), and it counts a
correspondence once per copy of a keypoint; this counts the correspondences that are right.

Coordinates: OpenCV pixels (the centre of the top-left pixel at (0, 0), `GtCamera`'s K), world
metres; rectangles as `gt/scene.json` stores them (`corners_m`: origin, +u, +u+v, +v; `normal`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from matching.metrics import DEFAULT_TH
from recon.eval.gt import GtCamera

CORRECT_PX = DEFAULT_TH
"""A verified correspondence is correct within this many px of the exact transfer (the pair
benchmark's threshold: the 3x3 neighbourhood of the true point)."""


@dataclass(frozen=True)
class Rect:
    """A rectangle: corner `origin`, edge vectors `u` and `v` (m), unit `normal` (its front side)."""

    origin: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    normal: NDArray[np.float64]


def rects_from_scene(meta: Mapping[str, Any]) -> list[Rect]:
    """The rectangles of a rendered scene's `gt/scene.json` (`planes`: `corners_m`, `normal`)."""
    out = []
    for p in meta.get("planes", []):
        c = np.asarray(p["corners_m"], np.float64).reshape(4, 3)
        n = np.asarray(p["normal"], np.float64)
        out.append(Rect(c[0], c[1] - c[0], c[3] - c[0], n / np.linalg.norm(n)))
    return out


def first_hit(rects: Sequence[Rect], origin: NDArray, dirs: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(points (N, 3), ray parameters (N,)): where the rays `origin + s * dirs[i]` (s > 0) first
    meet a rectangle from its front side; NaN points and inf parameters where none is met."""
    o = np.asarray(origin, np.float64).reshape(3)
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    pts = np.full((len(d), 3), np.nan)
    for r in rects:
        if float((o - r.origin) @ r.normal) <= 0:  # seen from behind: the renderer does not draw it
            continue
        den = d @ r.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((r.origin - o) @ r.normal) / den
        X = o + np.where(np.isfinite(s), s, 0.0)[:, None] * d
        rel = X - r.origin
        G = np.array([[r.u @ r.u, r.u @ r.v], [r.u @ r.v, r.v @ r.v]])
        a, b = np.linalg.solve(G, np.stack([rel @ r.u, rel @ r.v]))  # X = origin + a u + b v on the plane
        eps = 1e-9
        ok = np.isfinite(s) & (s > 1e-9) & (s < best) & (a >= -eps) & (a <= 1 + eps) & (b >= -eps) & (b <= 1 + eps)
        best[ok] = s[ok]
        pts[ok] = X[ok]
    return pts, best


def transfer(rects: Sequence[Rect], cam0: GtCamera, cam1: GtCamera, pts0: NDArray) -> NDArray[np.float64]:
    """(N, 2): where the scene points seen at `pts0` in view 0 appear in view 1; NaN where the ray
    meets nothing, or the point is hidden from or behind camera 1."""
    p = np.asarray(pts0, np.float64).reshape(-1, 2)
    rays = np.c_[p, np.ones(len(p))] @ np.linalg.inv(cam0.K).T @ cam0.R  # R^T K^-1 [x, y, 1], world frame
    X, _ = first_hit(rects, cam0.center, rays)
    _, s1 = first_hit(rects, cam1.center, X - cam1.center)  # s1 = 1 where X is the first thing camera 1 sees
    x_cam = X @ cam1.R.T + cam1.t
    uvw = x_cam @ cam1.K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:3]
    seen = np.isfinite(s1) & (np.abs(s1 - 1.0) < 1e-6) & (x_cam[:, 2] > 0)
    uv[~seen] = np.nan
    return uv


def correct_matches(rects: Sequence[Rect], cam0: GtCamera, cam1: GtCamera, pts0: NDArray, pts1: NDArray,
                    max_px: float) -> NDArray[np.bool_]:
    """(N,): which matches (pts0[i] in view 0, pts1[i] in view 1) lie within `max_px` of the
    exact transfer of pts0[i] (False where it has none)."""
    uv = transfer(rects, cam0, cam1, pts0)
    err = np.linalg.norm(uv - np.asarray(pts1, np.float64).reshape(-1, 2), axis=1)
    return np.asarray(np.isfinite(err) & (err <= max_px), bool)


def correct_per_pair(pairs: Sequence[Mapping[str, Any]], correct: dict[tuple[str, str], int] | None) -> float | None:
    """Mean correct correspondences (`correct_counts`) over the verified pairs of a run
    report's pair rows; None without them."""
    verified = [p for p in pairs if p.get("verified_inliers", 0) > 0]
    if correct is None or not verified:
        return None
    return sum(correct.get(pair_key(p), 0) for p in verified) / len(verified)


def pair_key(p: Mapping[str, Any]) -> tuple[str, str]:
    """(image0, image1) of a report pair row, in name order (`transfer_errors`' keys)."""
    return _ordered(p["image0"], p["image1"])


def _ordered(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a <= b else (b, a)


def transfer_errors(run_dir: str | Path | None, scene_dir: str | Path | None
                    ) -> dict[tuple[str, str], NDArray[np.float64]] | None:
    """{(name0, name1) in name order: the distance (px) of each distinct verified correspondence
    of the pair from the exact transfer of its first keypoint (inf where it has none)} of the
    run's `database.db` (keypoints in full-resolution px, the rendered size), or None without the
    database or a readable `gt/` with the scene's planes (a real scene, a moved or trimmed
    benchmark folder, a damaged ground truth: `recon compare` warns about that one)."""
    import pycolmap

    from matching.errors import InputError
    from recon.core.database import read_keypoints_opencv, read_verified
    from recon.eval.gt import read_colmap_text

    if not run_dir or not scene_dir:
        return None
    db_path, meta_path = Path(run_dir) / "database.db", Path(scene_dir) / "gt" / "scene.json"
    if not db_path.is_file() or not meta_path.is_file():
        return None
    try:
        rects = rects_from_scene(json.loads(meta_path.read_text(encoding="utf-8")))
        cams = read_colmap_text(Path(scene_dir) / "gt")
    except (InputError, OSError, ValueError, KeyError, TypeError):
        return None
    if not rects:
        return None
    db = pycolmap.Database.open(str(db_path))
    try:
        names = {int(im.image_id): im.name for im in db.read_all_images()}
    finally:
        db.close()
    kpts = {i: read_keypoints_opencv(db_path, i) for i in names}
    out: dict[tuple[str, str], NDArray[np.float64]] = {}
    for (a, b), (n, _conf, m) in read_verified(db_path).items():
        if n == 0 or names[a] not in cams or names[b] not in cams:
            continue
        # distinct position pairs, as `recon.core.tracks.distinct_correspondences` counts them
        pairs = np.unique(np.round(np.c_[kpts[a][m[:, 0]], kpts[b][m[:, 1]]], 2), axis=0)
        err = np.linalg.norm(transfer(rects, cams[names[a]], cams[names[b]], pairs[:, :2]) - pairs[:, 2:], axis=1)
        out[_ordered(names[a], names[b])] = np.where(np.isfinite(err), err, np.inf)
    return out


def correct_counts(errors: Mapping[tuple[str, str], NDArray] | None, max_px: float = CORRECT_PX
                   ) -> dict[tuple[str, str], int] | None:
    """{pair: correspondences within `max_px` of the exact transfer} of `transfer_errors`."""
    return None if errors is None else {k: int(np.sum(e <= max_px)) for k, e in errors.items()}


def correct_error_median(errors: Mapping[tuple[str, str], NDArray] | None, max_px: float = CORRECT_PX) -> float | None:
    """Median distance (px) from the exact transfer over every pair's correct correspondences:
    how precisely the right matches are localised; None without any."""
    if errors is None:
        return None
    ok = [e[e <= max_px] for e in errors.values()]
    ok = [e for e in ok if len(e)]
    return float(np.median(np.concatenate(ok))) if ok else None

