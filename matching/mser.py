"""Affine-covariant MSER features and the local-affine-frame (LAF) check (issue 13, item 1).

MODS, the strongest view-synthesis matcher, pools detectors: besides Hessian-Affine on simulated
views it matches OpenCV-style MSER regions normalised to a canonical frame. An MSER (maximally
stable extremal region) is an affine-covariant *shape*: its second moments C fix an ellipse, and
the map x = mu + m * 2 * sqrtm(C) * u (u on the unit disc, m = `measurement_scale`) takes the disc
onto the region's measurement region in any affine view of it, up to a rotation. So each region
is resampled into a `patch` x `patch` tile in which it is a disc of radius `disc_px`, the rotation
is fixed by the tile's dominant gradient orientation (SIFT's 36-bin histogram), and OpenCV's SIFT
describes the tile (RootSIFT). Affine invariance comes from the detector here; a region stays
stable only under moderate foreshortening, so the `mser` level (`matching.mserlevel`) detects in
a few views (t <= 4) rather than the SIFT levels' grid.

Each feature keeps its local affine frame `frames[i]` (2x2, image px per tile px, columns = the
frame's axes after the orientation): a true match (i, j) under a homography H satisfies
inv(F_j) @ J_H(x_i) @ F_i ~ identity, which `laf_consistent` checks (angle and scale tolerances).
Position-only RANSAC accepts any match that lands near the model; the LAF check also rejects a
match whose regions do not correspond in shape (a blob matched to a similar blob nearby).

Coordinates: keypoints are (x, y) in original image px, OpenCV's pixel-centre convention.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .features import Features
from .refine import local_affines_from_homography
from .views import GridConfig


@dataclass(frozen=True)
class MserConfig:
    """MSER regions, their normalised SIFT description and the LAF check (module doc)."""

    enabled: bool = True
    """Run the `mser` escalation level (`matching.mserlevel`)."""
    grid: GridConfig = field(default_factory=lambda: GridConfig(a=2.0, n=2, ds=0.0, scale_mode="none"))
    """Views of both images the level detects regions in (MODS' MSER step: t = 1, 2, 4, longitude
    step 72 deg / t, 18 views): a region is an affine-covariant shape only while it stays a
    stable extremal region, which strong foreshortening breaks; on EVD grand the originals alone
    give 1 RANSAC inlier within 5 px of the ground truth, these views 34 (docs/decisions.md)."""
    delta: int = 2
    """MSER's stability step in grey levels (OpenCV's default 5 finds 7 regions on EVD adam,
    2 finds 500)."""
    min_area: int = 20
    """Smallest region, px."""
    max_area_frac: float = 0.02
    """Largest region, as a fraction of the image area."""
    max_variation: float = 0.5
    """MSER's maximal relative area change over `delta` (OpenCV's default 0.25)."""
    min_diversity: float = 0.1
    """MSER's minimal diversity between nested regions (OpenCV's default 0.2)."""
    max_elongation: float = 10.0
    """Regions whose ellipse axes differ by more than this factor are dropped (lines, not blobs)."""
    measurement_scale: float = 2.0
    """Measurement region = this multiple of the region's equivalent ellipse (semi-axes 2 sigma)."""
    patch: int = 78
    """Side of the normalised tile, px: the SIFT support around the disc (2.5 sqrt(2) `disc_px`)
    plus 6 px that the mosaic's blur may reach from the neighbouring tiles (`describe_tiles`)."""
    disc_px: float = 9.0
    """Radius r of the measurement region in the tile, px. The SIFT descriptor (`describe_tiles`)
    reads pixels up to 2.5 * sqrt(2) * r from the centre (its rotated 4x4 grid of r-wide cells
    plus interpolation). At r = 12 in the first version's 64 px tiles its corners read the
    neighbouring tiles of the mosaic; r = 9 in self-contained tiles gives more matches within
    sqrt(3) px of the ground truth on the hard EVD pairs (docs/decisions.md, "The `mser` level")."""
    ratio: float = 0.85
    """FGINN ratio of the region matches (`twosided.fginn_match`): nested regions share a centre,
    so the second neighbour must lie `fginn_px` away."""
    fginn_px: float = 8.0
    """FGINN's distance between the first and the counted second neighbour, px."""
    laf_max_angle_deg: float = 30.0
    """LAF check: largest rotation between a match's frames mapped by H, degrees."""
    laf_max_scale: float = 2.0
    """LAF check: largest singular-value ratio (either way) between the mapped frames."""
    pool: Literal["best", "verified"] = "best"
    """What the regions are pooled with: "best" = the best attempt so far (all its matches);
    "verified" = that and the verified matches of every other attempt of the escalation (MODS
    accumulates every step's correspondences), so that which of several weak attempts verified a
    few more matches does not decide what the level builds on (`mserlevel.earlier_verified`)."""


def mser_key(cfg: MserConfig) -> str:
    """The feature-store key of an image's MSER features under `cfg` (its detection options)."""
    return (f"mser_d{cfg.delta}a{cfg.min_area}f{cfg.max_area_frac:g}v{cfg.max_variation:g}q{cfg.min_diversity:g}"
            f"e{cfg.max_elongation:g}m{cfg.measurement_scale:g}p{cfg.patch}r{cfg.disc_px:g}@orig")


def mser_regions(gray: NDArray[np.uint8], cfg: MserConfig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(centres (N, 2), shape maps (N, 2, 2)): each region's mean and m * 2 * sqrtm(C), which maps
    the unit disc onto its measurement region, image px."""
    mser = cv2.MSER.create(cfg.delta, cfg.min_area, max(cfg.min_area + 1, int(cfg.max_area_frac * gray.size)),
                           cfg.max_variation, cfg.min_diversity)
    regions, _ = mser.detectRegions(gray)
    if not regions:
        return np.zeros((0, 2)), np.zeros((0, 2, 2))
    lens = np.array([len(r) for r in regions])
    pts = np.concatenate(regions).astype(np.float64)
    idx = np.repeat(np.arange(len(regions)), lens)
    mu = np.stack([np.bincount(idx, pts[:, k]) for k in (0, 1)], 1) / lens[:, None]
    d = pts - mu[idx]
    c = np.stack([np.bincount(idx, d[:, 0] * d[:, 0]), np.bincount(idx, d[:, 0] * d[:, 1]),
                  np.bincount(idx, d[:, 1] * d[:, 1])], 1) / lens[:, None]
    C = np.stack([np.stack([c[:, 0], c[:, 1]], 1), np.stack([c[:, 1], c[:, 2]], 1)], 1) + 0.25 * np.eye(2)
    w, V = np.linalg.eigh(C)
    keep = w[:, 1] <= cfg.max_elongation**2 * w[:, 0]
    sq = np.einsum("nij,nj,nkj->nik", V, np.sqrt(w), V)  # sqrtm(C)
    return mu[keep], (cfg.measurement_scale * 2.0) * sq[keep]


def dominant_orientation(tiles: NDArray[np.float32], disc_px: float) -> NDArray[np.float64]:
    """Each tile's dominant gradient direction (radians, image axes: x right, y down): the peak of
    a 36-bin histogram of gradient angles, magnitude- and Gaussian-weighted inside the disc and
    smoothed twice, with a parabolic fit around the peak (SIFT's orientation assignment). Only
    the disc's bounding box (plus a pixel for the central differences) is differentiated."""
    n, p, _ = tiles.shape
    c = (p - 1) / 2.0
    lo, hi = max(0, int(np.floor(c - disc_px)) - 1), min(p, int(np.ceil(c + disc_px)) + 2)
    gy, gx = np.gradient(tiles[:, lo:hi, lo:hi], axis=(1, 2))
    yy, xx = np.mgrid[lo:hi, lo:hi] - c
    r2 = xx**2 + yy**2
    wgt = (np.exp(-r2 / (2 * (0.75 * disc_px) ** 2)) * (r2 <= disc_px**2)).astype(np.float32)
    inside = wgt.ravel() > 0
    mag = (np.hypot(gx, gy) * wgt).reshape(n, -1)[:, inside]
    ang = np.arctan2(gy, gx).reshape(n, -1)[:, inside]
    bins = (np.floor((ang + np.pi) / (2 * np.pi) * 36).astype(np.int64) % 36) + 36 * np.arange(n)[:, None]
    h: NDArray[np.float64] = np.bincount(bins.ravel(), mag.ravel(), minlength=36 * n).reshape(n, 36).astype(np.float64)
    for _ in range(2):
        h = (np.roll(h, 1, 1) + h + np.roll(h, -1, 1)) / 3.0
    k: NDArray[np.int64] = h.argmax(1)
    rows = np.arange(n)
    left, mid, right = h[rows, (k - 1) % 36], h[rows, k], h[rows, (k + 1) % 36]
    den = left - 2 * mid + right
    off = np.where(np.abs(den) > 1e-12, 0.5 * (left - right) / np.where(den == 0, 1, den), 0.0)
    return np.asarray((k + 0.5 + off) / 36.0 * 2 * np.pi - np.pi, np.float64)


def _pyramid(gray: NDArray[np.uint8], levels: int) -> list[NDArray[np.float32]]:
    out = [gray.astype(np.float32)]
    for _ in range(levels):
        if min(out[-1].shape) < 16:
            break
        out.append(cv2.pyrDown(out[-1]))
    return out


def normalised_tiles(gray: NDArray[np.uint8], mu: NDArray[np.float64], shape: NDArray[np.float64],
                     cfg: MserConfig) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """(tiles (N, patch, patch), M (N, 2, 2) image px per tile px) of each region resampled so its
    measurement region is the disc of radius `disc_px` at the tile centre; sampled from the
    pyramid level that the map's smaller singular value allows, against aliasing."""
    pyr = _pyramid(gray, 6)
    p, c = cfg.patch, (cfg.patch - 1) / 2.0
    M = shape / cfg.disc_px
    smin = np.linalg.svd(M, compute_uv=False).min(axis=1)
    level = np.clip(np.floor(np.log2(np.maximum(smin, 1.0))), 0, len(pyr) - 1).astype(int)
    tiles = np.empty((len(mu), p, p), np.float32)
    for i in range(len(mu)):
        f = 2.0 ** level[i]
        Ml = M[i] / f
        ml = (mu[i] + 0.5) / f - 0.5
        T = np.hstack([Ml, (ml - Ml @ (c, c))[:, None]])
        tiles[i] = cv2.warpAffine(pyr[level[i]], T, (p, p), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT)
    return tiles, M


DESCRIBE_CHUNK = 1024
"""Tiles described per SIFT call: OpenCV builds a float pyramid octave of the whole mosaic (six
layers, ~25 bytes per pixel), so one call per view cost ~0.4 GB on EVD dum's 4220 tiles."""


def describe_tiles(tiles: NDArray[np.float32], theta: NDArray[np.float64], disc_px: float) -> NDArray[np.float32]:
    """RootSIFT (at OpenCV's L2 scale, ~512) of each tile's centre, rotated to `theta`: the tiles
    go side by side into mosaics of `DESCRIBE_CHUNK` and OpenCV's SIFT describes all their centres
    in one call each (keypoints given at octave 0: one pyramid octave, no upsampling). Keypoint
    size = 2/3 of the disc radius r, so a histogram cell is 3 sigma = r wide and the 4x4 cells
    span +-2r: the measurement region and as much of its surroundings. Rotated and with
    interpolation the descriptor reads up to 2.5 * sqrt(2) * r from the centre; the tile must keep
    it 6 px (the reach of SIFT's initial blur, which crosses tile borders in the mosaic) from its
    edge, so a descriptor depends on its own tile only, not on its neighbours or the chunking."""
    n, p, _ = tiles.shape
    reach = 2.5 * np.sqrt(2.0) * disc_px + 6.0
    if reach > (p - 1) / 2.0:
        raise ValueError(f"MSER tile of {p} px too small for a {disc_px:g} px disc (needs {2 * reach + 1:.0f} px)")
    out = np.empty((n, 128), np.float32)
    cols = 32
    for start in range(0, n, DESCRIBE_CHUNK):
        part = tiles[start:start + DESCRIBE_CHUNK]
        m = len(part)
        rows = (m + cols - 1) // cols
        mosaic = np.zeros((rows * p, cols * p), np.uint8)
        kps = []
        for i in range(m):
            r, c = divmod(i, cols)
            mosaic[r * p:(r + 1) * p, c * p:(c + 1) * p] = np.clip(part[i] + 0.5, 0, 255).astype(np.uint8)
            kps.append(cv2.KeyPoint(c * p + (p - 1) / 2.0, r * p + (p - 1) / 2.0, disc_px * 2.0 / 3.0,
                                    float(np.degrees(theta[start + i]) % 360.0)))
        kps_out, desc = cv2.SIFT.create().compute(mosaic, kps)
        if desc is None or len(kps_out) != m:
            raise RuntimeError(f"SIFT described {0 if desc is None else len(kps_out)} of {m} MSER tiles")
        out[start:start + m] = desc
    d = out / np.maximum(out.sum(axis=1, keepdims=True), 1e-7)
    return (np.sqrt(d) * 512.0).astype(np.float32)


def detect_mser_affine(gray: NDArray[np.uint8], cfg: MserConfig) -> Features:
    """MSER regions of `gray` as RootSIFT features with their local affine frames in
    `Features.frames` (module doc)."""
    mu, shape = mser_regions(gray, cfg)
    if len(mu) == 0:
        f = Features.empty(128, np.float32)
        f.frames = np.zeros((0, 2, 2))
        return f
    tiles, M = normalised_tiles(gray, mu, shape, cfg)
    theta = dominant_orientation(tiles, cfg.disc_px)
    desc = describe_tiles(tiles, theta, cfg.disc_px)
    rot = np.stack([np.stack([np.cos(theta), -np.sin(theta)], 1), np.stack([np.sin(theta), np.cos(theta)], 1)], 1)
    frames = M @ rot
    sizes = (2.0 * cfg.disc_px * np.sqrt(np.abs(np.linalg.det(M)))).astype(np.float32)
    angles = np.degrees(np.arctan2(frames[:, 1, 0], frames[:, 0, 0])).astype(np.float32) % 360.0
    return Features(mu.astype(np.float32), sizes, angles, desc, frames=frames)


def laf_errors(H_b_from_a: NDArray[np.float64], kpts_a: NDArray, frames_a: NDArray[np.float64],
               frames_b: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(rotation deg, scale ratio >= 1) of E = inv(F_b) @ J_H(x_a) @ F_a per match: how far the
    frame of a, carried by the homography's local affine map, is from the frame of b."""
    J = local_affines_from_homography(H_b_from_a, kpts_a)
    E = np.linalg.solve(frames_b, J @ frames_a)
    angle = np.degrees(np.abs(np.arctan2(E[:, 1, 0] - E[:, 0, 1], E[:, 0, 0] + E[:, 1, 1])))
    s = np.linalg.svd(E, compute_uv=False)
    scale = np.maximum(s[:, 0], 1.0 / np.maximum(s[:, 1], 1e-12))
    return angle, scale


def laf_consistent(H_b_from_a: NDArray[np.float64], kpts_a: NDArray, frames_a: NDArray[np.float64],
                   frames_b: NDArray[np.float64], cfg: MserConfig) -> NDArray[np.bool_]:
    """Which matches' local affine frames agree with the homography (`laf_errors` within
    `laf_max_angle_deg` and `laf_max_scale`)."""
    if len(kpts_a) == 0:
        return np.zeros(0, bool)
    angle, scale = laf_errors(H_b_from_a, kpts_a, frames_a, frames_b)
    return (angle <= cfg.laf_max_angle_deg) & (scale <= cfg.laf_max_scale)
