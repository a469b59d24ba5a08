"""Accuracy of a reconstruction against ground-truth cameras (`recon.eval.gt`), matched by image NAME.

`evaluate_model(estimate, gt)`:

* `estimate`: a `pycolmap.Reconstruction` (its registered images) or a plain
  `{image name: cam_from_world}` (3x4 [R | t] or 4x4, world -> camera), so the metrics are
  testable without pycolmap. Images are always paired with GT by name, never by id.
* `gt`: `{image name: GtCamera}` (or `{name: cam_from_world}`).

Relative pose, over every unordered pair of GT images (i, j) (names sorted):
  R_ij = R_j R_i^T, t_ij = t_j - R_ij t_i (camera i -> camera j). The rotation error is the angle
  of R_ij,est R_ij,gt^T; the translation error is the angle between t_ij,est and t_ij,gt (SfM
  fixes the sign, so no min(e, 180 - e) folding). Both are invariant to the model's similarity
  gauge. A pair with an image that the model did not register counts as an infinite error.
  `rel_rot_err_deg_median` / `rel_trans_err_deg_median` are over the pairs the model has (both
  registered); the AUCs are over all GT pairs, so they also measure completeness.
* `auc_5/10/20`: area under the recall-vs-error curve of max(rot err, trans err), integrated
  from 0 to the threshold and divided by it (SuperGlue / LoFTR / IMC "pose AUC": sort errors,
  recall = rank / n, trapezoids, the curve held flat at its last value up to the threshold).

Absolute cameras: the estimated camera centres are aligned to the GT centres with a least-squares
similarity (Umeyama 1991, pycolmap's `estimate_sim3d`) over the registered images that have GT (>= 3 and
not collinear); `center_err_median` is the median distance after alignment, in GT units, and
`center_err_rel_median` divides by the GT scene extent (the largest distance between two GT
camera centres).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

AUC_THRESHOLDS = (5.0, 10.0, 20.0)


# inputs -----------------------------------------------------------------------------------------
def _as_pose(x: Any) -> NDArray[np.float64]:
    """3x4 cam_from_world from a GtCamera, a 3x4 / 4x4 array or a pycolmap Rigid3d."""
    if hasattr(x, "cam_from_world") and not callable(x.cam_from_world):
        x = x.cam_from_world  # GtCamera
    if hasattr(x, "matrix") and callable(x.matrix):
        x = x.matrix()  # pycolmap.Rigid3d
    P = np.asarray(x, np.float64)
    if P.shape == (4, 4):
        P = P[:3]
    if P.shape != (3, 4):
        raise ValueError(f"expected a 3x4 or 4x4 cam_from_world, got shape {P.shape}")
    return P


def poses_from_estimate(estimate: Any) -> dict[str, NDArray[np.float64]]:
    """{name: 3x4 cam_from_world} of a pycolmap.Reconstruction's registered images, or of a dict."""
    if isinstance(estimate, Mapping):
        return {str(k): _as_pose(v) for k, v in estimate.items()}
    out: dict[str, NDArray[np.float64]] = {}
    for iid in estimate.reg_image_ids():
        im = estimate.image(iid)
        if getattr(im, "has_pose", True):
            out[im.name] = _as_pose(im.cam_from_world())
    return out


# geometry ---------------------------------------------------------------------------------------
def rotation_angle_deg(R: NDArray[np.float64]) -> float:
    """Angle of a rotation, atan2(sin, cos) form: accurate near 0 and 180 deg (arccos is not)."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def vector_angle_deg(a: NDArray[np.float64], b: NDArray[np.float64], eps: float = 1e-12) -> float:
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na < eps or nb < eps:
        return float("nan")
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b))))


def relative_pose(Pi: NDArray[np.float64], Pj: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    """(R_ij, t_ij) with x_j = R_ij x_i + t_ij for camera-frame points of cameras i and j."""
    Ri, ti, Rj, tj = Pi[:, :3], Pi[:, 3], Pj[:, :3], Pj[:, 3]
    Rij = Rj @ Ri.T
    return Rij, tj - Rij @ ti


def center(P: NDArray[np.float64]) -> NDArray[np.float64]:
    return -P[:, :3].T @ P[:, 3]


def umeyama(src: NDArray[np.float64], dst: NDArray[np.float64], with_scale: bool = True
            ) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """(s, R, t) minimising sum |dst_k - (s R src_k + t)|^2 (Umeyama 1991). src, dst: (N, 3).

    Solved by pycolmap's `estimate_sim3d` (`estimate_rigid3d` without scale: s = 1), COLMAP's
    wrapper of Eigen's `umeyama`: the same numbers as the former numpy implementation to 2.4e-13
    relative on 2000 random noisy problems, 13x faster (11 vs 139 us for 30 points).
    Raises ValueError with fewer than 3 points or (near-)collinear points (the rotation about
    their line is then undetermined).
    """
    import pycolmap

    src = np.asarray(src, np.float64).reshape(-1, 3)
    dst = np.asarray(dst, np.float64).reshape(-1, 3)
    if len(src) != len(dst) or len(src) < 3:
        raise ValueError("umeyama needs at least 3 corresponding points")
    sv_s = np.linalg.svd(src - src.mean(0), compute_uv=False)
    if sv_s[0] <= 0 or sv_s[1] <= 1e-9 * max(sv_s[0], 1e-300):
        raise ValueError("umeyama: points are (nearly) coincident or collinear")
    est = pycolmap.estimate_sim3d(src, dst) if with_scale else pycolmap.estimate_rigid3d(src, dst)
    if est is None:
        raise ValueError("umeyama: points are (nearly) coincident or collinear")
    s = float(np.asarray(getattr(est, "scale", 1.0)).reshape(-1)[0])  # Rigid3d (no scale) when not with_scale
    return s, np.asarray(est.rotation.matrix(), np.float64), np.asarray(est.translation, np.float64)


def pose_auc(errors: Sequence[float], thresholds: Sequence[float] = AUC_THRESHOLDS) -> list[float]:
    """Area under the recall curve of `errors` up to each threshold, normalised to [0, 1].

    Infinite (or NaN) errors count as failures: they lower the recall but never enter the area.
    """
    e = np.asarray(errors, np.float64).ravel()
    if e.size == 0:
        return [0.0 for _ in thresholds]
    e = np.where(np.isnan(e), np.inf, e)
    e = np.sort(e)
    recall = np.arange(1, e.size + 1, dtype=np.float64) / e.size
    e = np.concatenate([[0.0], e])
    recall = np.concatenate([[0.0], recall])
    out = []
    for th in thresholds:
        last = int(np.searchsorted(e, th))  # e[:last] < th
        r = np.concatenate([recall[:last], [recall[last - 1]]])
        x = np.concatenate([e[:last], [th]])
        area = float(np.sum((x[1:] - x[:-1]) * (r[1:] + r[:-1]) / 2.0))
        out.append(area / th)
    return out


def _median(v: Sequence[float]) -> float | None:
    a = np.asarray([x for x in v if x is not None and math.isfinite(x)], np.float64)
    return float(np.median(a)) if a.size else None


# evaluation -------------------------------------------------------------------------------------
def evaluate_model(estimate: Any, gt: Mapping[str, Any], with_pairs: bool = True) -> dict[str, Any]:
    """Relative-pose errors, pose AUCs and aligned camera-centre errors (see module doc).

    `estimate` may be None (no model): every pair is then a failure.
    """
    est = {} if estimate is None else poses_from_estimate(estimate)
    gtp = {str(k): _as_pose(v) for k, v in gt.items()}
    names = sorted(gtp)
    common = [n for n in names if n in est]
    rot, trans, pair_max, rows = [], [], [], []
    for a_i, a in enumerate(names):
        for b in names[a_i + 1:]:
            if a in est and b in est:
                Rg, tg = relative_pose(gtp[a], gtp[b])
                Re, te = relative_pose(est[a], est[b])
                er = rotation_angle_deg(Re @ Rg.T)
                et = vector_angle_deg(te, tg)
                rot.append(er)
                trans.append(et)
                m = er if math.isnan(et) else max(er, et)  # GT baseline 0: rotation only
            else:
                er = et = m = math.inf
            pair_max.append(m)
            if with_pairs:
                rows.append({"image0": a, "image1": b, "rot_err_deg": er, "trans_err_deg": et})
    aucs = pose_auc(pair_max) if pair_max else [0.0] * len(AUC_THRESHOLDS)

    out: dict[str, Any] = {
        "num_gt_images": len(names),
        "num_registered": len(est),
        "num_registered_with_gt": len(common),
        "num_pairs": len(pair_max),
        "num_pairs_evaluated": len(rot),
        "rel_rot_err_deg_median": _median(rot),
        "rel_trans_err_deg_median": _median(trans),
        "rel_rot_err_deg_mean": float(np.mean(rot)) if rot else None,
        "rel_trans_err_deg_mean": float(np.nanmean(trans)) if trans and not np.all(np.isnan(trans)) else None,
    }
    for th, v in zip(AUC_THRESHOLDS, aucs):
        out[f"auc_{int(th)}"] = float(v)

    # absolute camera centres after a similarity alignment, by name
    gt_c = np.array([center(gtp[n]) for n in names]).reshape(-1, 3)
    extent = float(max(np.linalg.norm(gt_c[:, None] - gt_c[None], axis=-1).max(), 0.0)) if len(names) > 1 else 0.0
    out.update(center_err_median=None, center_err_rel_median=None, center_err_max=None,
               gt_extent=extent, alignment=None)
    per_image: dict[str, float] = {}
    if len(common) >= 3:
        src = np.array([center(est[n]) for n in common])
        dst = np.array([center(gtp[n]) for n in common])
        try:
            s, R, t = umeyama(src, dst)
        except ValueError as e:
            out["alignment"] = {"error": str(e)}
        else:
            err = np.linalg.norm((s * (R @ src.T)).T + t - dst, axis=1)
            per_image = {n: float(x) for n, x in zip(common, err)}
            out["center_err_median"] = float(np.median(err))
            out["center_err_max"] = float(err.max())
            out["center_err_rel_median"] = float(np.median(err) / extent) if extent > 0 else None
            out["alignment"] = {"scale": s, "R": R.tolist(), "t": t.tolist()}
    if with_pairs:
        out["center_err"] = per_image
        out["pairs"] = rows
    return out


# paired comparison of two models ---------------------------------------------------------------
BOOT_CELLS = 4_000_000
"""`paired_rotation_gap` weighs this many (draw, pair) cells at a time (32 MB of float64), so a
scene of thousands of images (millions of pairs) does not hold all 2000 draws' weights at once."""


def _weighted_lower_median(values_sorted: NDArray[np.float64], weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per row of `weights` (draws x values, aligned with the ascending `values_sorted`), the
    smallest value whose cumulative weight reaches half the row's total."""
    cw = np.cumsum(weights, axis=1)
    idx = np.argmax(cw >= 0.5 * cw[:, -1:], axis=1)
    return values_sorted[idx]


def paired_rotation_gap(pairs_a: Sequence[Mapping[str, Any]], pairs_b: Sequence[Mapping[str, Any]],
                        n_boot: int = 2000, seed: int = 0, level: float = 0.95) -> dict[str, Any] | None:
    """Model a's median relative rotation error minus model b's (degrees) over the image pairs both
    evaluate (`evaluate_model(...)["pairs"]` rows, finite errors only), with a bootstrap interval
    that resamples the images, not the pairs: every pair of an image shares that camera's error, so
    a scene's pairs are far from independent samples, and a pair bootstrap's interval is too
    narrow (2.5x on castle_P30's ours-against-stock, 1.7x on image-level noise in the tests). Each
    draw picks as many images as there are, with replacement, and weighs a pair by the product of
    its two images' counts (a draw's medians are weighted lower medians). `a_below_b` counts the
    pairs where a's error is the smaller. None when fewer than 3 pairs or 3 images are shared.
    Deterministic for a `seed`. Why: two pipelines' median errors on a 30-image scene differ by
    hundredths of a degree, and whether such a gap is the models' or the particular images' is
    what a reader needs to know (README, "Consistent tracks": castle_P30's gap to stock)."""
    ea = {(str(p["image0"]), str(p["image1"])): float(p["rot_err_deg"]) for p in pairs_a}
    eb = {(str(p["image0"]), str(p["image1"])): float(p["rot_err_deg"]) for p in pairs_b}
    keys = sorted(k for k in ea.keys() & eb.keys() if math.isfinite(ea[k]) and math.isfinite(eb[k]))
    names = sorted({n for k in keys for n in k})
    if len(keys) < 3 or len(names) < 3:
        return None
    a = np.array([ea[k] for k in keys])
    b = np.array([eb[k] for k in keys])
    index = {n: i for i, n in enumerate(names)}
    i0 = np.array([index[k[0]] for k in keys])
    i1 = np.array([index[k[1]] for k in keys])
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(len(names), np.full(len(names), 1.0 / len(names)), size=n_boot).astype(np.float64)
    oa, ob = np.argsort(a, kind="stable"), np.argsort(b, kind="stable")
    parts = []
    step = max(1, BOOT_CELLS // len(keys))  # draws at a time: the weights stay within BOOT_CELLS floats
    for start in range(0, n_boot, step):
        c = counts[start:start + step]
        c = c[(c[:, i0] * c[:, i1]).sum(axis=1) > 0]  # a draw that pairs no two images says nothing
        parts.append(_weighted_lower_median(a[oa], c[:, i0[oa]] * c[:, i1[oa]])
                     - _weighted_lower_median(b[ob], c[:, i0[ob]] * c[:, i1[ob]]))
    gaps = np.concatenate(parts)
    lo, hi = np.percentile(gaps, [50 * (1 - level), 50 * (1 + level)])
    return {"num_pairs": len(keys), "num_images": len(names), "median_a": float(np.median(a)),
            "median_b": float(np.median(b)), "gap": float(np.median(a) - np.median(b)),
            "ci_low": float(lo), "ci_high": float(hi), "level": level, "a_below_b": int(np.sum(a < b)),
            "n_boot": len(gaps), "seed": seed}
