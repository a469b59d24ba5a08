"""Logging a `recon compare` result to Rerun: every method's model in one frame, one colour each.

Frame: the ground truth's when the scene has one (each model is aligned to it with a similarity
from the camera centres of the images both hold, paired by image name), otherwise the frame of
the first method that has a model (stock's first preset, then ours), to which the others are
aligned the same way. A model that cannot be aligned (fewer than 3 shared, non-collinear
camera centres) is logged as is and the summary says so.

Entity layout:

* `world/<method>/points`: `Points3D` in the method's colour (`METHOD_COLORS`; the true point
  colours are in each method's own `recon run` recording);
* `world/<method>/cameras/<image>`: `Transform3D` (aligned cam_from_world, ChildFromParent)
  and `.../image`: `Pinhole` drawn in the method's colour (intrinsics scaled to 320 px);
* `world/gt/cameras/<image>`: the ground-truth cameras in grey, when there is GT;
* `plots/verified_inliers/<method>`: COLMAP-verified inliers per pair on the `pair` timeline,
  pairs in the order of our run, so the methods' curves overlay pair by pair;
* `summary`: the console table (Markdown code block) and how each model was aligned.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from recon.eval.compare import OURS_KEY, load_model, points_xyz
from recon.eval.evaluate import center, poses_from_estimate, umeyama
from recon.viz.rerun_log import Sink, _esc, log_camera

COMPARE_RECORDING = "compare.rrd"
METHOD_COLORS: dict[str, tuple[int, int, int]] = {
    OURS_KEY: (30, 144, 255),  # blue
    "stock-default": (255, 140, 0),  # orange
    "stock-high": (200, 60, 200),  # purple
}
GT_COLOR = (160, 160, 160)
FALLBACK_COLORS = ((60, 180, 75), (230, 25, 75), (128, 128, 0))


@dataclass(frozen=True)
class Sim3:
    """X_ref = s R X + t, mapping a model's world frame into the reference frame."""

    s: float
    R: NDArray[np.float64]
    t: NDArray[np.float64]

    @staticmethod
    def identity() -> Sim3:
        return Sim3(1.0, np.eye(3), np.zeros(3))

    def points(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        return (self.s * (self.R @ np.asarray(X, np.float64).reshape(-1, 3).T)).T + self.t

    def pose(self, P: NDArray[np.float64]) -> NDArray[np.float64]:
        """cam_from_world (3x4) of the same camera in the reference frame; the camera frame is
        scaled with the world (x_cam' = s x_cam), so the pose stays rigid: R' = R_c Rᵀ,
        t' = s t_c - R' t, and the centre maps like a point (c' = s R c + t)."""
        Rc, tc = P[:, :3], P[:, 3]
        R2 = Rc @ self.R.T
        return np.hstack([R2, (self.s * tc - R2 @ self.t)[:, None]])


def align_by_name(ref_centers: dict[str, NDArray], centers: dict[str, NDArray]) -> tuple[Sim3 | None, str]:
    """(similarity into the reference frame or None, one-line note)."""
    common = sorted(set(ref_centers) & set(centers))
    if len(common) < 3:
        return None, f"not aligned: {len(common)} images in common with the reference frame (need 3)"
    try:
        s, R, t = umeyama(np.array([centers[n] for n in common]), np.array([ref_centers[n] for n in common]))
    except ValueError as e:
        return None, f"not aligned: {e}"
    sim = Sim3(s, R, t)
    err = np.linalg.norm(sim.points(np.array([centers[n] for n in common])) - np.array([ref_centers[n] for n in common]),
                         axis=1)
    return sim, f"aligned on {len(common)} camera centres, median residual {float(np.median(err)):.3g}"


@dataclass
class _Model:
    method: str
    poses: dict[str, NDArray[np.float64]]  # name -> cam_from_world (3x4), in the model's frame
    intrinsics: dict[str, tuple[NDArray[np.float64], tuple[int, int]]]  # name -> (K, (w, h))
    xyz: NDArray[np.float64]


def _read(method: str, out: str | Path) -> _Model | None:
    rec = load_model(Path(out) / "sparse" / "0")
    if rec is None or rec.num_reg_images() == 0:
        return None
    poses = poses_from_estimate(rec)
    intr = {}
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        intr[im.name] = (np.asarray(im.camera.calibration_matrix(), np.float64), (im.camera.width, im.camera.height))
    return _Model(method, poses, intr, points_xyz(rec))


def summary_markdown(res: dict[str, Any], notes: dict[str, str], frame: str) -> str:
    from rich.console import Console

    from recon.eval.compare import compare_table

    console = Console(record=True, width=140, file=io.StringIO())
    console.print(compare_table(res))
    lines = [f"# recon compare: {Path(res['scene']).name}", "", f"**frame:** {frame}", "",
             "| method | colour | alignment |", "|---|---|---|"]
    for m, note in notes.items():
        c = METHOD_COLORS.get(m, GT_COLOR if m == "gt" else None)
        lines.append(f"| {m} | {'rgb' + str(tuple(c)) if c else '-'} | {note} |")
    lines += ["", "```", console.export_text().rstrip(), "```"]
    if res.get("warnings"):
        lines += ["", "## Warnings", ""] + [f"* {w}" for w in res["warnings"]]
    return "\n".join(lines) + "\n"


def log_comparison(sink: Sink, res: dict[str, Any], gt: dict[str, Any] | None = None) -> Path | None:
    """Write the comparison `res` (from `compare_scene`) to `sink`; returns the saved file or None.

    `gt`: {name: GtCamera} when the scene has ground truth (its frame is then the reference).
    """
    import rerun as rr
    import rerun.blueprint as rrb

    from recon.viz.rerun_log import RerunLogger

    if not sink.enabled:
        return None
    methods: dict[str, dict[str, Any]] = res["methods"]
    read = {m: _read(m, row["out"]) for m, row in methods.items() if row.get("status") == "ok"}
    models = {m: md for m, md in read.items() if md is not None}
    notes: dict[str, str] = {m: "no model" for m in methods if m not in models}

    if gt:
        ref_centers = {n: center(np.asarray(g.cam_from_world, np.float64)) for n, g in gt.items()}
        frame = "ground truth"
    else:
        first = next(iter(models), None)
        first_model = models[first] if first else None
        ref_centers = {n: center(P) for n, P in first_model.poses.items()} if first_model else {}
        frame = f"{first}'s model" if first else "none (no method has a model)"

    logger = RerunLogger(sink, lambda n: Path(n), application_id="recon-compare")
    ok = False
    try:
        rec = logger.open_sink()
        if gt:
            for n, g in sorted(gt.items()):
                log_camera(rec, f"world/gt/cameras/{_esc(n)}", np.asarray(g.cam_from_world, np.float64),
                           np.asarray(g.K, np.float64), tuple(g.size), color=GT_COLOR, plane_distance=0.3)
            notes["gt"] = f"{len(gt)} cameras (reference frame)"
        fallback = iter(FALLBACK_COLORS)
        for m, md in models.items():
            color = METHOD_COLORS.get(m) or next(fallback, GT_COLOR)
            sim, note = align_by_name(ref_centers, {n: center(P) for n, P in md.poses.items()})
            if sim is None:
                sim = Sim3.identity()
            notes[m] = note
            base = f"world/{_esc(m)}"
            rec.log(f"{base}/points", rr.Points3D(sim.points(md.xyz), colors=color, radii=rr.Radius.ui_points(2.0)),
                    static=True)
            for n, P in sorted(md.poses.items()):
                K, size = md.intrinsics[n]
                log_camera(rec, f"{base}/cameras/{_esc(n)}", sim.pose(P), K, size, color=color, plane_distance=0.3)
        ours = methods.get(OURS_KEY, {}).get("pairs") or next(iter(methods.values()), {}).get("pairs") or []
        order = [(p["image0"], p["image1"]) for p in ours]
        for m, row in methods.items():
            by_pair = {}
            for p in row.get("pairs") or []:
                by_pair[(p["image0"], p["image1"])] = by_pair[(p["image1"], p["image0"])] = int(p.get("verified_inliers", 0))
            for i, key in enumerate(order):
                rec.set_time("pair", sequence=i)
                rec.log(f"plots/verified_inliers/{_esc(m)}", rr.Scalars(float(by_pair.get(key, 0))))
        rec.reset_time()
        rec.log("summary", rr.TextDocument(summary_markdown(res, notes, frame), media_type=rr.MediaType.MARKDOWN),
                static=True)
        rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(
            rrb.Spatial3DView(name=f"models in one frame ({frame})", origin="world"),
            rrb.Vertical(rrb.TextDocumentView(name="summary", origin="summary"),
                         rrb.TimeSeriesView(name="verified inliers per pair", origin="plots/verified_inliers"),
                         row_shares=[3, 2]),
            column_shares=[3, 2]), collapse_panels=False), make_active=True, make_default=True)
        ok = True
    finally:
        saved = logger.close(ok)
    return saved
