"""The `steep` escalation level: one-sided views tilted beyond the paper's grid (t = 8 .. 22.6).

The paper's grid stops at t = 4 sqrt(2) = 5.66, and the two-sided levels reach a transition tilt
of 5.66^2 only where both images can be tilted towards each other. A pair whose target sees the
surface at a grazing angle (EVD cafe 11.9, mag 20.5, fox 22.7: the singular-value ratio of the
ground-truth homography at the image centre) needs the *detailed* image compressed by that much
along one direction: what the target lost cannot be simulated back, but the reference can be
degraded to look like the target. Views at such tilts are narrow (area 1/t of the original), so
a whole tilt level costs about 2.5 originals of SIFT.

Each view's SIFT is matched against the target's original SIFT (ratio test) and scored by
RANSAC homography inliers; scores at these tilts are small and noisy (a right view of EVD cafe
has 12 inliers, wrong ones 4-10), so the `candidates` best views are each re-matched under their
own homography (`fine.guided_match`) and the one that verifies most wins. The side simulated is
the reference first, then the other image while the first verifies fewer than `min_inliers`.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from numpy.typing import NDArray

from .context import Attempt, MatchContext
from .escalation import SteepConfig
from .features import DetectorConfig, Features, detect
from .fine import FineMatches, guided_match
from .geometry import homography_jacobian
from .matching_utils import ransac_homography, ratio_match, unique_train
from .types import ViewParams
from .verify import plausible_homography
from .viewfeatures import away_from_canvas_edge, original_features, view_features


def steep_views(cfg: SteepConfig) -> list[ViewParams]:
    """The level's views, tilt by tilt: phi = j b / t < 180 deg, no zoom (s = 1)."""
    views = []
    for t in cfg.tilts:
        j = 0
        while j * cfg.b / t < 180.0 - 1e-9:
            views.append(ViewParams(t=round(t, 6), phi=round(j * cfg.b / t, 6), s=1.0))
            j += 1
    return views


def _side_attempt(ctx: MatchContext, ref: int, cfg: SteepConfig, label: str) -> Attempt:
    """Image `ref` simulated over `steep_views`; the view whose own homography verifies most."""
    det = ctx.cfg.fine.detector
    name, target = ctx.names[ref], ctx.names[1 - ref]
    ft = original_features(ctx.store, target, det)
    views = steep_views(cfg)

    def score(v: ViewParams) -> tuple[int, ViewParams, np.ndarray | None]:
        fv = view_features(ctx.store, name, v, det, "linear", True)
        if len(fv) < cfg.min_matches or len(ft) < cfg.min_matches:
            return 0, v, None
        m, _ = ratio_match(fv.descriptors, ft.descriptors, det.norm, cfg.ratio, seed=ctx.cfg.seed)
        if len(m) < cfg.min_matches:
            return 0, v, None
        H, inl = ransac_homography(fv.kpts[m[:, 0]], ft.kpts[m[:, 1]], cfg.ransac_px, seed=ctx.cfg.seed)
        if H is None or not plausible_homography(H, fv.kpts[m[inl, 0]]):
            return 0, v, None
        return int(inl.sum()), v, H

    scored = [s for s in ctx.map(score, views, min_items=2) if s[2] is not None]
    scored.sort(key=lambda s: (-s[0], s[1]))
    seeds: list[tuple[Attempt, NDArray[np.float64]]] = []
    for _, v, H in scored[: cfg.candidates]:
        assert H is not None  # filtered above
        fv = view_features(ctx.store, name, v, det, "linear", True)
        gm, gd = guided_match(fv.kpts, fv.descriptors, ft.kpts, ft.descriptors, H, cfg.guided_px, cfg.guided_ratio)
        if len(gm) < 4:
            continue
        gm, gd = unique_train(gm, gd)
        fm = FineMatches(kpts_ref=fv.kpts, kpts_target=ft.kpts, matches=gm, distances=gd, per_view={v.key: len(gm)})
        n_verified, mask = ctx.verify(fv.kpts[gm[:, 0]], ft.kpts[gm[:, 1]])
        if n_verified >= 8:
            H_fit = ransac_homography(fv.kpts[gm[mask, 0]], ft.kpts[gm[mask, 1]], cfg.ransac_px, seed=ctx.cfg.seed)[0]
            seeds.append((Attempt(label=label, reference=ref, fine=fm, views=[v], coarse=[], verified=n_verified),
                          H if H_fit is None else H_fit))
    seeds.sort(key=lambda s: -s[0].verified)
    best = seeds[0][0] if seeds else Attempt(label=label, reference=ref, fine=_empty(ft.kpts), views=[], coarse=[],
                                             verified=0)
    if cfg.rectify_rounds > 0:
        rectified = []
        for att, H_seed in seeds[: cfg.rectify_candidates]:
            rect = rectified_round(ctx, ref, H_seed, cfg)
            if rect is not None:
                rectified.append(Attempt(label=label, reference=ref, fine=rect[0], views=att.views, coarse=[],
                                         verified=rect[1]))
        best = max([best, *rectified], key=lambda a: a.verified)
    return best


def antialias_blur(img: NDArray[np.uint8], J_t_from_r: NDArray[np.float64]) -> NDArray[np.uint8]:
    """`img` blurred along the directions the 2x2 local affine `J_t_from_r` compresses, by
    ASIFT's 0.8 sqrt(1/s^2 - 1) for each singular value s < 1 (an oriented Gaussian)."""
    _, sv, Vt = np.linalg.svd(J_t_from_r)
    sig = np.array([0.8 * np.sqrt(1.0 / x**2 - 1.0) if 0 < x < 1 else 0.0 for x in sv])
    if sig.max() < 0.3:
        return img
    cov = Vt.T @ np.diag(np.maximum(sig, 0.3) ** 2) @ Vt
    half = int(np.ceil(3 * sig.max()))
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    d = np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float64)
    k = np.exp(-0.5 * np.einsum("ij,jk,ik->i", d, np.linalg.inv(cov), d)).reshape(xx.shape)
    return cv2.filter2D(img, -1, (k / k.sum()).astype(np.float32), borderType=cv2.BORDER_REFLECT)


def rectify_detector(ctx: MatchContext, cfg: SteepConfig) -> DetectorConfig:
    """The fine stage's SIFT with the rectified rounds' lower contrast threshold."""
    return dataclasses.replace(ctx.cfg.fine.detector, contrast=cfg.rectify_contrast)


def rectified_features(ctx: MatchContext, ref: int, H_t_from_r: NDArray[np.float64],
                       centre_ref: NDArray, det: DetectorConfig) -> Features:
    """SIFT of image `ref` warped by the full homography into the target's frame (anti-aliased
    around `centre_ref`), keypoints mapped back to `ref`'s original pixels: the closest view
    of the reference to the target that the pair's geometry can synthesise."""
    img = ctx.store.image(ctx.names[ref])
    w, h = ctx.size(1 - ref)
    warped = cv2.warpPerspective(antialias_blur(img, homography_jacobian(H_t_from_r, centre_ref)), H_t_from_r, (w, h),
                                 flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    mask = cv2.warpPerspective(np.full(img.shape[:2], 255, np.uint8), H_t_from_r, (w, h), flags=cv2.INTER_NEAREST)
    mask = cv2.erode(mask, np.ones((7, 7), np.uint8))
    f = detect(warped, det, mask)
    f = f.subset(away_from_canvas_edge(f.kpts, f.sizes, mask))
    q = np.c_[f.kpts.astype(np.float64), np.ones(len(f))] @ np.linalg.inv(H_t_from_r).T
    f.kpts = (q[:, :2] / q[:, 2:3]).astype(np.float32)
    return f


def rectified_round(ctx: MatchContext, ref: int, H_t_from_r: NDArray[np.float64], cfg: SteepConfig
                    ) -> tuple[FineMatches, int] | None:
    """Guided matching of `rectified_features` against the target's original SIFT, repeated
    `cfg.rectify_rounds` times with the homography re-fitted each round; (the best round's
    matches, its verified count), or None when no round is trustworthy.

    Verified = matches within `rectify_inlier_px` of the re-fitted homography. Guided matching
    under a *wrong* homography still pairs keypoints inside the search radius, and a loose RANSAC
    finds "inliers" among them; true geometry puts most rectified matches within a pixel or two,
    chance puts (inlier_px / rectify_px)^2 of them there (6 % at 1.5 / 6 px), so a round also
    needs `rectify_min_ratio` of its matches verified."""
    det = rectify_detector(ctx, cfg)
    ft = original_features(ctx.store, ctx.names[1 - ref], det)
    out: tuple[FineMatches, int] | None = None
    H = H_t_from_r
    w, h = ctx.size(ref)
    centre_ref = np.array([(w - 1) / 2, (h - 1) / 2])
    for _ in range(cfg.rectify_rounds):
        fr = rectified_features(ctx, ref, H, centre_ref, det)
        gm, gd = guided_match(fr.kpts, fr.descriptors, ft.kpts, ft.descriptors, H, cfg.rectify_px, cfg.guided_ratio)
        if len(gm) < 4:
            break
        gm, gd = unique_train(gm, gd)
        H_new, mask = ransac_homography(fr.kpts[gm[:, 0]], ft.kpts[gm[:, 1]], cfg.rectify_inlier_px, seed=ctx.cfg.seed)
        n_verified = int(mask.sum())
        if (H_new is None or n_verified < 8 or n_verified < cfg.rectify_min_ratio * len(gm)
                or not plausible_homography(H_new, fr.kpts[gm[mask, 0]])
                or (out is not None and n_verified <= out[1])):
            break
        out = (FineMatches(kpts_ref=fr.kpts, kpts_target=ft.kpts, matches=gm, distances=gd, per_view={"rectified": len(gm)}),
               n_verified)
        H = H_new
    return out


def _empty(kpts_target: np.ndarray) -> FineMatches:
    return FineMatches(kpts_ref=np.zeros((0, 2), np.float32), kpts_target=kpts_target,
                       matches=np.zeros((0, 2), np.int32), distances=np.zeros(0, np.float32), per_view={})


def steep_attempt(ctx: MatchContext, best: Attempt, cfg: SteepConfig, label: str = "steep") -> Attempt:
    """The level: the reference's steep views, then the other image's while too few verify."""
    att = _side_attempt(ctx, best.reference, cfg, label)
    if cfg.both_sides and att.verified < ctx.cfg.escalation.min_inliers:
        other = _side_attempt(ctx, 1 - best.reference, cfg, label)
        att = max(att, other, key=lambda a: a.verified)
    return att
