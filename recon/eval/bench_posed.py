"""Real wide-baseline pairs with ground-truth cameras: relative pose and epipolar precision per
viewing angle, every method side by side.

The homography benchmarks judge planar pairs (eight EVD pairs whose ground truths are partly a few
px off; rendered tilt pairs); the scene benchmarks judge whole reconstructions. Here each pair is
two real photos of a 3D scene whose `gt/` holds cameras (Strecha's fountain_P11 and castle_P30),
and the truth is the two cameras:

* **pose**: every method's final matches go through the *same* filter, an essential-matrix RANSAC
  on coordinates normalised by the true intrinsics (`POSE_RANSAC_PX` px at the working size,
  seeded), and `cv2.recoverPose`; the pose error is the larger of the rotation error and the
  angle between the translation directions (degrees; IMC's convention). A pair is **solved** when
  it is at most `SOLVED_POSE_DEG`.
* **correct**: the filter's inliers whose symmetric epipolar distance under the true fundamental
  matrix is at most `th` px (sqrt(3), the pair benchmark's threshold), and their share
  (**precision**).

Pairs: every pair of each scene whose optical axes converge in front of both cameras at a point
inside both images (`covisible`: a cheap overlap test; cameras around a courtyard can still face
opposite walls, so pairs that no method solves are counted apart), binned by the angle between
the cameras (`angle_deg`, the relative rotation's angle), at most `per_bin` per 15° bin, spread over
the bin's pairs in a fixed order. Images are read at `max_size` px (intrinsics scaled with them,
pixel-centre convention). Methods run in this process, one after the other on each pair, each on
a fresh `FeatureStore`, so `seconds` include feature extraction and ratios within one run are
comparable on a noisy machine.
"""

from __future__ import annotations

import itertools
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.fine import epipolar_pair_distance
from matching.io import load_gray, resize_max
from matching.memory import PeakRss
from matching.registry import PairMatcher
from matching.store import FeatureStore
from recon.core.jsonio import to_jsonable
from recon.eval.bench_pairs import write_json
from recon.eval.evaluate import pose_auc, relative_pose, rotation_angle_deg, vector_angle_deg
from recon.eval.gt import GtCamera, find_gt

BIN_DEG = 15.0
SOLVED_POSE_DEG = 5.0  # a pair is solved when its pose error is at most this
POSE_RANSAC_PX = 1.0  # the common essential-matrix filter's threshold, px at the working size
MIN_POSE_MATCHES = 8  # fewer final matches: no pose (the pair counts as failed)


@dataclass(frozen=True, eq=False)
class PosedPair:
    """Two photos of one scene and their true cameras (at the images' original size)."""

    scene: str
    name0: str
    name1: str
    path0: Path
    path1: Path
    cam0: GtCamera
    cam1: GtCamera

    @property
    def name(self) -> str:
        return f"{self.scene} {Path(self.name0).stem}-{Path(self.name1).stem}"

    @property
    def angle_deg(self) -> float:
        """Angle of the relative rotation between the two cameras, degrees."""
        return rotation_angle_deg(self.cam1.R @ self.cam0.R.T)


# geometry ---------------------------------------------------------------------------------------
def scaled_K(K: NDArray[np.float64], size: tuple[int, int], new_size: tuple[int, int]) -> NDArray[np.float64]:
    """Intrinsics of an image resized from `size` to `new_size` (w, h), pixel-centre convention:
    x_new = (x + 0.5) * w_new / w - 0.5 per axis."""
    fx, fy = new_size[0] / size[0], new_size[1] / size[1]
    S = np.array([[fx, 0.0, 0.5 * fx - 0.5], [0.0, fy, 0.5 * fy - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, np.float64)


def relative_pose_gt(cam0: GtCamera, cam1: GtCamera) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(R_1_from_0, t_1_from_0): x_cam1 = R x_cam0 + t for camera-frame points."""
    return relative_pose(cam0.cam_from_world, cam1.cam_from_world)


def fundamental_from_cameras(K0: NDArray[np.float64], K1: NDArray[np.float64], R: NDArray[np.float64],
                             t: NDArray[np.float64]) -> NDArray[np.float64]:
    """F_1_from_0 (x1^T F x0 = 0, pixels) of cameras related by x_cam1 = R x_cam0 + t."""
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    F = np.linalg.inv(K1).T @ tx @ R @ np.linalg.inv(K0)
    return F / np.linalg.norm(F)


def symmetric_epipolar_px(F_1_from_0: NDArray[np.float64], pts0: NDArray, pts1: NDArray) -> NDArray[np.float64]:
    """Per match, the larger of the distances of x1 to x0's epipolar line and of x0 to x1's, px
    (`matching.fine.epipolar_pair_distance` both ways)."""
    return np.maximum(epipolar_pair_distance(F_1_from_0, pts0, pts1), epipolar_pair_distance(F_1_from_0.T, pts1, pts0))


def covisible(cam0: GtCamera, cam1: GtCamera, margin: float = 0.1) -> bool:
    """True when the two optical axes pass closest to each other in front of both cameras, at a
    point inside both images (`margin` of each side excluded), and converge (their closest
    approach is shorter than half the baseline). Parallel axes never pass."""
    c0, c1 = cam0.center, cam1.center
    d0, d1 = cam0.R[2], cam1.R[2]
    w = c0 - c1
    b = float(d0 @ d1)
    den = 1.0 - b * b
    if den < 1e-9:
        return False
    s = (b * float(d1 @ w) - float(d0 @ w)) / den
    u = (float(d1 @ w) - b * float(d0 @ w)) / den
    p0, p1 = c0 + s * d0, c1 + u * d1
    if np.linalg.norm(p0 - p1) > 0.5 * np.linalg.norm(c0 - c1):
        return False
    X = 0.5 * (p0 + p1)
    for cam in (cam0, cam1):
        x = cam.K @ (cam.R @ X + cam.t)
        if x[2] <= 0:
            return False
        (uu, vv), (w_, h_) = x[:2] / x[2], cam.size
        if not (margin * w_ < uu < (1 - margin) * w_ and margin * h_ < vv < (1 - margin) * h_):
            return False
    return True


def pose_from_matches(pts0: NDArray, pts1: NDArray, K0: NDArray[np.float64], K1: NDArray[np.float64],
                      thresh_px: float = POSE_RANSAC_PX, seed: int = 0
                      ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None, NDArray[np.bool_]]:
    """(R_1_from_0, unit t_1_from_0, inlier mask) from matches in pixels, via an essential-matrix
    RANSAC (threshold `thresh_px` px, as a fraction of the mean focal length) on coordinates
    normalised by the true intrinsics; (None, None, all False) when it finds none.

    OpenCV's USAC_ACCURATE (local optimisation and a final least-squares polish, deterministic):
    plain `cv2.RANSAC` returns a minimal sample's E, whose pose is 0.5-1.9° off on neighbouring
    rendered corner views where USAC_ACCURATE is 0.01-0.1° off, an error that would drown the
    matchers' differences."""
    n = len(pts0)
    none = np.zeros(n, bool)
    if n < MIN_POSE_MATCHES:
        return None, None, none
    n0 = cv2.undistortPoints(np.asarray(pts0, np.float64).reshape(-1, 1, 2), K0, None).reshape(-1, 2)
    n1 = cv2.undistortPoints(np.asarray(pts1, np.float64).reshape(-1, 1, 2), K1, None).reshape(-1, 2)
    f = 0.25 * (K0[0, 0] + K0[1, 1] + K1[0, 0] + K1[1, 1])
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.9999,
                                   threshold=thresh_px / f, maxIters=10000)
    if E is None or mask is None or E.shape != (3, 3):
        return None, None, none
    inl = mask.ravel() > 0
    _, R, t, pose_mask = cv2.recoverPose(E, n0, n1, np.eye(3), mask=mask.copy())
    keep = inl & (pose_mask.ravel() > 0)
    return np.asarray(R, np.float64), np.asarray(t, np.float64).ravel(), keep


def pose_errors(R: NDArray[np.float64], t: NDArray[np.float64], R_gt: NDArray[np.float64],
                t_gt: NDArray[np.float64]) -> tuple[float, float]:
    """(rotation error, translation-direction error), degrees; the direction's sign is free (an
    essential matrix fixes it only through chirality, which the inliers may get wrong)."""
    rot = rotation_angle_deg(R.T @ R_gt)
    tr = vector_angle_deg(t, t_gt)
    return rot, min(tr, 180.0 - tr)


# discovery --------------------------------------------------------------------------------------
def discover_posed_pairs(root: Path, scenes: Sequence[str] | None = None, per_bin: int = 4,
                         max_angle: float = 120.0) -> list[PosedPair]:
    """Covisible pairs (`covisible`) of every scene under `root` with GT cameras (or of `root`
    itself), at most `per_bin` per `BIN_DEG` bin of `angle_deg` below `max_angle`, spread evenly
    over each bin's pairs in name order; sorted by scene, then angle."""
    from recon.core.scene import find_image_dir, list_candidates

    root = Path(root)
    dirs = [root] if (root / "gt").is_dir() else sorted(p for p in root.iterdir() if p.is_dir())
    out: list[PosedPair] = []
    for d in dirs:
        if scenes and d.name not in scenes:
            continue
        gt = find_gt(d)
        if not gt:
            continue
        image_dir = find_image_dir(d)
        names = [n for n in list_candidates(image_dir)[0] if n in gt]
        by_bin: dict[int, list[PosedPair]] = {}
        for a, b in itertools.combinations(sorted(names), 2):
            pair = PosedPair(d.name, a, b, image_dir / a, image_dir / b, gt[a], gt[b])
            ang = pair.angle_deg
            if ang < max_angle and covisible(gt[a], gt[b]):
                by_bin.setdefault(int(ang // BIN_DEG), []).append(pair)
        for k in sorted(by_bin):
            cand = by_bin[k]
            if per_bin > 0 and len(cand) > per_bin:
                idx = np.linspace(0, len(cand) - 1, per_bin).round().astype(int)
                cand = [cand[i] for i in dict.fromkeys(idx.tolist())]
            out.extend(sorted(cand, key=lambda p: p.angle_deg))
    return out


# running ----------------------------------------------------------------------------------------
def final_points(result: Any) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A result's final matches in pixels: its verified inliers where it has a mask, else all."""
    pts0, pts1 = result.matched_points(inliers_only=True)
    return np.asarray(pts0, np.float32).reshape(-1, 2), np.asarray(pts1, np.float32).reshape(-1, 2)


def evaluate_pair(pair: PosedPair, pts0: NDArray, pts1: NDArray, K0: NDArray[np.float64],
                  K1: NDArray[np.float64], th: float, seed: int = 0) -> dict[str, Any]:
    """Pose error, correct matches and precision of `pts0` <-> `pts1` (working pixels) under the
    common filter (`pose_from_matches`) and the true cameras."""
    R_gt, t_gt = relative_pose_gt(pair.cam0, pair.cam1)
    R, t, inl = pose_from_matches(pts0, pts1, K0, K1, seed=seed)
    F_gt = fundamental_from_cameras(K0, K1, R_gt, t_gt)
    final = int(inl.sum())
    correct = int(np.sum(symmetric_epipolar_px(F_gt, pts0[inl], pts1[inl]) <= th)) if final else 0
    if R is None or t is None:
        rot = tr = math.inf
    else:
        rot, tr = pose_errors(R, t, R_gt, t_gt)
    err = max(rot, tr)
    return {"matches_in": int(len(pts0)), "final": final, "correct": correct,
            "precision": correct / final if final else 0.0, "rot_err_deg": rot, "t_err_deg": tr,
            "pose_err_deg": err, "solved": bool(err <= SOLVED_POSE_DEG)}


def run_posed_bench(pairs: Sequence[PosedPair], methods: Sequence[str], matchers: dict[str, PairMatcher],
                    max_size: int = 1024, th: float = math.sqrt(3.0), seed: int = 0,
                    json_path: Path | None = None, progress: bool = True,
                    on_row: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Every method on every pair at `max_size` px; one row per (pair, method). With `json_path`
    the rows so far are rewritten atomically after each pair (an interrupted run keeps them)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    rows: list[dict[str, Any]] = []
    working: dict[Path, tuple[NDArray[np.uint8], NDArray[np.float64]]] = {}

    def load(path: Path, cam: GtCamera) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
        """(working image, its intrinsics), decoded once per photo (a photo is in many pairs)."""
        if path not in working:
            full = load_gray(path)
            img, _ = resize_max(full, max_size)
            working[path] = img, scaled_K(cam.K, (full.shape[1], full.shape[0]), (img.shape[1], img.shape[0]))
        return working[path]

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=Console(stderr=True), transient=True, disable=not progress) as prog:
        task = prog.add_task("posed pairs", total=len(pairs) * len(methods))
        for pair in pairs:
            (img0, K0), (img1, K1) = load(pair.path0, pair.cam0), load(pair.path1, pair.cam1)
            for m in methods:
                prog.update(task, description=f"{pair.name} [bold]{m}[/]")
                store = FeatureStore()
                store.add_image("0", img0)
                store.add_image("1", img1)
                with PeakRss() as mem:
                    t0 = time.perf_counter()
                    result = matchers[m].match(store, "0", "1")
                    seconds = time.perf_counter() - t0
                pts0, pts1 = final_points(result)
                row = {"pair": pair.name, "scene": pair.scene, "method": m, "angle_deg": pair.angle_deg,
                       "bin": int(pair.angle_deg // BIN_DEG) * int(BIN_DEG), "seconds": seconds,
                       "peak_mb": mem.peak_mb, "path": getattr(result, "path", ""),
                       "escalation": getattr(result, "escalation", ""), "timings": dict(result.timings),
                       "reason": result.reason, "max_size": max_size, "th": th,
                       **evaluate_pair(pair, pts0, pts1, K0, K1, th, seed)}
                rows.append(to_jsonable(row))
                if on_row is not None:
                    on_row(rows[-1])
                prog.advance(task)
            if json_path is not None:
                write_json(json_path, rows)
    return rows


# reporting --------------------------------------------------------------------------------------
def summarize_posed(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per method: pairs, solved, solved among the pairs some method solved, AUC@5/10/20 of the
    pose error, median correct matches and seconds, total seconds."""
    some = {r["pair"] for r in rows if r["solved"]}
    out: dict[str, dict[str, Any]] = {}
    for m in dict.fromkeys(r["method"] for r in rows):
        rs = [r for r in rows if r["method"] == m]
        errs = [math.inf if r["pose_err_deg"] is None else r["pose_err_deg"] for r in rs]
        out[m] = {"pairs": len(rs), "solved": sum(r["solved"] for r in rs),
                  "solvable": sum(1 for r in rs if r["pair"] in some),
                  "auc": pose_auc(errs, (5.0, 10.0, 20.0)),
                  "median_correct": statistics.median(r["correct"] for r in rs),
                  "median_seconds": statistics.median(r["seconds"] for r in rs),
                  "total_seconds": sum(r["seconds"] for r in rs)}
    return out


def posed_tables(rows: Sequence[dict[str, Any]]) -> list[Any]:
    """Rich tables: per angle bin x method (solved, median pose error, correct, precision, seconds),
    then the per-method summary."""
    from rich.table import Table

    methods = list(dict.fromkeys(r["method"] for r in rows))
    t = Table(title="Real pairs with GT cameras, per angle between the cameras "
                    f"(solved: pose error <= {SOLVED_POSE_DEG:g}°)")
    t.add_column("angle", no_wrap=True)
    t.add_column("pairs", justify="right")
    for m in methods:
        t.add_column(f"{m}\nsolved / med. err° / correct / prec. / s", justify="right", no_wrap=True)
    for b in sorted({r["bin"] for r in rows}):
        cells = []
        n = 0
        for m in methods:
            rs = [r for r in rows if r["bin"] == b and r["method"] == m]
            n = len(rs)
            errs = [math.inf if r["pose_err_deg"] is None else r["pose_err_deg"] for r in rs]
            med = statistics.median(errs)
            cells.append(f"{sum(r['solved'] for r in rs)} / {'-' if math.isinf(med) else f'{med:.2f}'} / "
                         f"{statistics.median(r['correct'] for r in rs):.0f} / "
                         f"{100 * statistics.median(r['precision'] for r in rs):.0f} % / "
                         f"{statistics.median(r['seconds'] for r in rs):.2f}")
        t.add_row(f"{b}-{b + int(BIN_DEG)}°", str(n), *cells)
    s = Table(title="Summary (solvable = pairs that at least one method solved)")
    for col in ("method", "solved", "of solvable", "AUC@5 / 10 / 20°", "median correct", "median s", "total s"):
        s.add_column(col, justify="left" if col == "method" else "right", no_wrap=True)
    for m, v in summarize_posed(rows).items():
        s.add_row(m, f"{v['solved']}/{v['pairs']}", f"{v['solved']}/{v['solvable']}",
                  " / ".join(f"{a:.3f}" for a in v["auc"]), f"{v['median_correct']:.0f}",
                  f"{v['median_seconds']:.2f}", f"{v['total_seconds']:.1f}")
    return [t, s]
