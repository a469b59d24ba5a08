"""Logging a run (or one pair) to Rerun: the 3D model, per-pair diagnostics, plots and a summary.

`RerunLogger` is a `recon.core.observer.RunObserver` (`run_scene(..., observer=logger)`):
it logs pairs, SfM steps and the final model as the run emits them, and never touches the
pipeline. Entity layout of a recording:

* `world/cameras/<image>`: `Transform3D` (COLMAP's `cam_from_world`, logged as
  ChildFromParent), its `image` child: `Pinhole` (intrinsics scaled to the thumbnail) and
  the image as a JPEG `EncodedImage` (longest side 320 px); `AnyValues` with the image name,
  COLMAP camera model and full-resolution parameters;
* `world/points`: `Points3D` with colours, plus `reprojection_error` and `track_length`
  per point (`AnyValues`);
* `pairs/<name0>__<name1>/matches` (both images side by side, inliers green, outliers red,
  JPEG), `.../info` (Markdown), `.../coarse` (PNG heat map of the coarse score of every simulated
  view: row = (tilt, scale), column = longitude index, chosen view(s) boxed in white) and
  `.../coarse_scores` (the raw grid as a `Tensor`, NaN where no view was simulated);
* `growth/...` on the `registration` timeline (sequence = registration step, 0 = the initial
  pair): the model as incremental mapping builds it, for replay image by image:
  `growth/cameras/<image>` (pose and intrinsics of every image registered so far, re-logged
  each step because bundle adjustment moves them; the image just registered in orange),
  `growth/points` (at most `GROWTH_POINTS` points, evenly subsampled, uniform colour: COLMAP
  extracts point colours only at the end) and `growth/info` (Markdown: step, image, counts).
  Only logged when the model is built in this run (a reused model has no replay);
* `plots/pair/*`: raw matches, matcher inliers, COLMAP-verified inliers and seconds per pair on
  the `pair` timeline; `plots/bars/verified_inliers` (`BarChart` over pair index);
  `plots/growth/registered_images` and `plots/growth/points3D` (`BarChart` over registration
  step, from the report so they exist for reused models too); `plots/model/points_per_image`
  (`BarChart`, registered images in image id order); `summary` (Markdown report headline numbers).

Per-pair entities and the final model are static, so they show on every timeline.

The sink is opened lazily on the first logged item, so nothing is created in the output folder
before the pipeline has checked and claimed it. A saved recording is written to a temporary
`.NAME.tmp-<pid>` file and renamed when complete, so a killed run never leaves half a file.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.types import PairResult
from recon.core.observer import BaseRunObserver

RECORDING_NAME = "recording.rrd"
SINK_KINDS = ("save", "spawn", "connect", "none")
THUMB_PX = 320  # longest side of the camera images in the 3D view
# Longest side of each image in a pair's side-by-side match picture, and JPEG quality: the
# recording's size is mostly these pictures (measured in docs/decisions.md, "Rerun recordings").
PAIR_PX = 512
JPEG_QUALITY = 80
GROWTH_POINTS = 20000  # points per step of the growth replay (keeps a 30-image recording small)
GROWTH_NEW = (255, 140, 0)  # the camera just registered
GROWTH_OLD = (150, 150, 150)  # cameras registered earlier
GROWTH_PTS = (90, 160, 230)
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sink:
    kind: str  # save | spawn | connect | none
    target: str | None = None  # file for save, URL for connect

    @property
    def enabled(self) -> bool:
        return self.kind != "none"


def parse_sink(spec: str, default_path: Path | None = None) -> Sink:
    """`save[:PATH]`, `spawn`, `connect[:URL]` or `none`; ValueError with a one-line message."""
    kind, _, arg = (spec or "").strip().partition(":")
    kind = kind.lower()
    if kind not in SINK_KINDS:
        raise ValueError(f"--rerun {spec!r}: choose save[:PATH], spawn, connect[:URL] or none")
    if kind == "save":
        path = arg or (str(default_path) if default_path is not None else "")
        if not path:
            raise ValueError("--rerun save needs a file: save:PATH")
        return Sink("save", path)
    if kind == "connect":
        return Sink("connect", arg or None)
    if arg:
        raise ValueError(f"--rerun {kind} takes no argument (got {spec!r})")
    return Sink(kind)


def find_viewer() -> str | None:
    """The Rerun viewer executable: on PATH or next to this Python (a venv's bin/), else None."""
    here = str(Path(sys.executable).parent)
    return shutil.which("rerun", path=os.pathsep.join([here, os.environ.get("PATH", "")]))


def _esc(part: str) -> str:
    import rerun as rr

    return rr.escape_entity_path_part(part)


def pair_entity(name0: str, name1: str) -> str:
    """`pairs/<name0>__<name1>` with both names escaped (spaces, slashes, dots are fine)."""
    return f"pairs/{_esc(f'{name0}__{name1}')}"


def camera_entity(name: str) -> str:
    return f"world/cameras/{_esc(name)}"


def _resize_longest(img: NDArray[np.uint8], px: int) -> tuple[NDArray[np.uint8], float]:
    h, w = img.shape[:2]
    s = min(1.0, px / max(h, w))
    if s >= 1.0:
        return img, 1.0
    out = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    return out, s


def _png(img_rgb: NDArray[np.uint8]) -> bytes:
    """PNG of an RGB picture: lossless, and tiny for flat-colour plots such as the coarse heat map
    (raw RGB images cost far more: docs/decisions.md, "Rerun recordings")."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(img_rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def _jpeg(img_bgr: NDArray[np.uint8]) -> bytes:
    ok, buf = cv2.imencode(".jpg", img_bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def log_camera(rec: Any, ent: str, cam_from_world: NDArray[np.float64], K: NDArray[np.float64],
               size: tuple[int, int], *, static: bool = True, color: tuple[int, int, int] | None = None,
               image_bgr: NDArray[np.uint8] | None = None, plane_distance: float = 0.5) -> None:
    """A camera as `ent` (`Transform3D` of COLMAP's cam_from_world (3x4), logged as
    ChildFromParent) and `ent/image` (`Pinhole` with K scaled to the picture, or to `THUMB_PX`
    without one, frustum drawn in `color`; `image_bgr` as a JPEG)."""
    import rerun as rr

    P = np.asarray(cam_from_world, np.float64)
    w, h = size
    if image_bgr is not None:
        sh, sw = image_bgr.shape[:2]
    else:
        f = THUMB_PX / max(w, h)
        sw, sh = max(1, round(w * f)), max(1, round(h * f))
    rec.log(ent, rr.Transform3D(translation=P[:, 3], mat3x3=P[:, :3], relation=rr.TransformRelation.ChildFromParent),
            static=static)
    rec.log(f"{ent}/image", rr.Pinhole(image_from_camera=np.diag([sw / w, sh / h, 1.0]) @ np.asarray(K, np.float64),
                                       resolution=[sw, sh], image_plane_distance=plane_distance, color=color),
            static=static)
    if image_bgr is not None:
        rec.log(f"{ent}/image", rr.EncodedImage(contents=_jpeg(image_bgr), media_type="image/jpeg"), static=static)


def coarse_grid(result: PairResult) -> tuple[NDArray[np.float32], list[str], list[tuple[int, int]]]:
    """(grid, row labels, chosen cells): coarse score per simulated view, NaN where none.

    Rows are the distinct (tilt, scale) pairs in increasing order; columns the longitudes of a
    row in increasing order (their number grows with the tilt, as in ASIFT). Chosen cells are
    the fine-stage views found in the grid.
    """
    rows: dict[tuple[float, float], list] = {}
    for c in result.coarse_scores:
        rows.setdefault((round(c.view.t, 6), round(c.view.s, 6)), []).append(c)
    keys = sorted(rows)
    ncol = max((len(v) for v in rows.values()), default=0)
    grid = np.full((len(keys), ncol), np.nan, np.float32)
    chosen_keys = {v.key for v in result.best_views}
    chosen: list[tuple[int, int]] = []
    for r, k in enumerate(keys):
        for c, cs in enumerate(sorted(rows[k], key=lambda x: x.view.phi)):
            grid[r, c] = cs.score
            if cs.view.key in chosen_keys:
                chosen.append((r, c))
    labels = [f"t={t:.2f}" + ("" if abs(s - 1.0) < 1e-9 else f" s={s:.2f}") for t, s in keys]
    return grid, labels, chosen


def heatmap_image(grid: NDArray[np.float32], chosen: list[tuple[int, int]], cell: int = 20) -> NDArray[np.uint8]:
    """An RGB picture of the grid (viridis, black where empty), chosen cells boxed in white."""
    h, w = grid.shape
    valid = np.isfinite(grid)
    lo = float(grid[valid].min()) if valid.any() else 0.0
    hi = float(grid[valid].max()) if valid.any() else 1.0
    norm = np.zeros(grid.shape, np.uint8)
    if valid.any():
        norm[valid] = np.clip((grid[valid] - lo) / max(hi - lo, 1e-9) * 255.0, 0, 255).astype(np.uint8)
    color = cv2.applyColorMap(norm, cv2.COLORMAP_VIRIDIS)
    color[~valid] = 0
    big = cv2.resize(color, (w * cell, h * cell), interpolation=cv2.INTER_NEAREST)
    for r, c in chosen:
        cv2.rectangle(big, (c * cell, r * cell), (c * cell + cell - 1, r * cell + cell - 1), (255, 255, 255), 2)
    return cv2.cvtColor(big, cv2.COLOR_BGR2RGB)


def pair_markdown(name0: str, name1: str, r: PairResult, cached: bool, verified: int | None = None) -> str:
    names = (name0, name1)
    lines = [f"## {name0} ↔ {name1}", "", "| | |", "|---|---|", f"| method | {r.method} |"]
    if r.reference is not None:
        lines.append(f"| reference | {names[r.reference]} ({r.reference_reason or '-'}) |")
    if r.f0 is not None and r.f1 is not None:
        lines.append(f"| Eq. 1 f0 / f1 | {r.f0:.1f} / {r.f1:.1f} |")
    if r.best_views:
        lines.append("| best (t, phi, s) | " + ", ".join(f"({v.t:.2f}, {v.phi:.1f}°, {v.s:.2f})" for v in r.best_views) + " |")
    if r.path:
        lines.append(f"| path | {r.path} ({r.path_reason or '-'}) |")
    if r.escalation:
        lines.append(f"| escalation | {r.escalation} |")
    lines.append(f"| raw matches | {r.num_matches} |")
    lines.append(f"| matcher inliers | {r.num_inliers} |")
    if verified is not None:
        lines.append(f"| COLMAP-verified inliers | {verified} |")
    lines.append(f"| simulated views scored | {len(r.coarse_scores)} |")
    lines.append(f"| from cache | {'yes' if cached else 'no'} |")
    if r.reason:
        lines.append(f"| note | {r.reason} |")
    stages = [(k, v) for k, v in r.timings.items() if isinstance(v, (int, float)) and k != "guided_rejected"]
    if stages:
        lines += ["", "### Time per stage", "", "| stage | s |", "|---|---:|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in stages]
    return "\n".join(lines) + "\n"


def summary_markdown(report: Any) -> str:
    err = report.mean_reprojection_error
    verified = sum(1 for p in report.pairs if p.verified_inliers > 0)
    lines = [f"# recon run: {Path(report.scene).name}", "",
             f"**status:** {report.status}" + (f" — {report.message}" if report.message else ""), "",
             "| metric | value |", "|---|---:|",
             f"| images (usable / skipped) | {report.num_images} / {len(report.skipped)} |",
             f"| registered images | {report.registered_images} / {report.num_images} |",
             f"| 3D points | {report.num_points3D} |",
             f"| mean track length (model) | {report.mean_track_length:.2f} |",
             f"| mean reprojection error (px) | {'-' if err is None else f'{err:.3f}'} |",
             f"| models (sizes) | {report.num_models} ({', '.join(map(str, report.model_sizes)) or '-'}) |",
             f"| pairs verified | {verified} / {len(report.pairs)} |",
             f"| pairs computed / cached | {report.pairs_computed} / {report.pairs_cached} |",
             f"| total (s) | {report.seconds_total:.1f} |",
             f"| peak memory (MB) | {report.peak_mb:.0f} |",
             "", "## Seconds per stage", "", "| stage | s |", "|---|---:|"]
    lines += [f"| {k} | {v:.2f} |" for k, v in report.stages.items()]
    lines += ["", "## Pairs", "", "| image 0 | image 1 | reference | best (t, phi, s) | raw | verified |",
              "|---|---|---|---|---:|---:|"]
    for p in report.pairs:
        bv = "-" if not p.best_view else f"({p.best_view['t']:.2f}, {p.best_view['phi']:.1f}°, {p.best_view['s']:.2f})"
        lines.append(f"| {p.image0} | {p.image1} | {p.reference or '-'} | {bv} | {p.raw_matches} | {p.verified_inliers} |")
    if report.warnings:
        lines += ["", "## Warnings", ""] + [f"* {w}" for w in report.warnings]
    if report.sfm_growth:
        lines += ["", "## Registration order", "", "| step | model | image | registered | 3D points |",
                  "|---:|---:|---|---:|---:|"]
        lines += [f"| {g['step']} | {g['model']} | {g['image']} | {g['registered_images']} | {g['num_points3D']} |"
                  for g in report.sfm_growth]
    if report.model_reused:
        lines += ["", "_The model was reused from an earlier run: the growth replay (timeline "
                      "`registration`) is only recorded when the model is built; use --overwrite._"]
    return "\n".join(lines) + "\n"


class RerunLogger(BaseRunObserver):
    """Logs a run to one Rerun sink: pass it as `run_scene(..., observer=logger)`, then `close()`."""

    def __init__(self, sink: Sink, image_path: Callable[[str], Path], *, application_id: str = "recon",
                 recording_id: str | None = None) -> None:
        self.sink = sink
        self.image_path = image_path
        self.application_id = application_id
        self.recording_id = recording_id
        self.rec = None  # rr.RecordingStream once opened
        self._tmp: Path | None = None
        self._thumbs: dict[str, tuple[NDArray[np.uint8], float] | None] = {}
        self._pairs: list[tuple[int, str, str]] = []
        self._growth_model: int | None = None  # model index of the last growth step logged
        self.seconds = 0.0  # wall-clock spent logging (overhead measurement)
        self.error: str | None = None  # the first logging failure (logging stops after it)

    # sink ---------------------------------------------------------------------------------------
    def open_sink(self):
        if self.rec is not None or not self.sink.enabled:
            return self.rec
        import rerun as rr

        rec = rr.RecordingStream(self.application_id, recording_id=self.recording_id)
        if self.sink.kind == "save":
            final = Path(self.sink.target).expanduser()  # type: ignore[arg-type]
            final.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
            rec.save(self._tmp)
        elif self.sink.kind == "spawn":
            exe = find_viewer()
            if exe is None:
                raise RuntimeError("the Rerun viewer (`rerun`) is not installed; use --rerun save instead")
            rr.spawn(executable_path=exe, recording=rec, connect=True)
        else:  # connect
            rec.connect_grpc(self.sink.target)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)  # COLMAP: y down, z forward
        self.rec = rec
        return rec

    def close(self, ok: bool = True) -> Path | None:
        """Flush and close the sink; a saved recording is moved into place (deleted when not ok)."""
        if self.rec is None:
            return None
        rec, self.rec = self.rec, None
        rec.flush()
        rec.disconnect()
        if self._tmp is None:
            return None
        tmp, self._tmp = self._tmp, None
        final = Path(self.sink.target).expanduser()  # type: ignore[arg-type]
        if ok and tmp.exists():
            os.replace(tmp, final)
            return final
        tmp.unlink(missing_ok=True)
        return None

    # images -------------------------------------------------------------------------------------
    def _thumb(self, name: str) -> tuple[NDArray[np.uint8], float] | None:
        """(BGR image with longest side <= PAIR_PX, scale from full resolution), cached."""
        if name not in self._thumbs:
            from matching.io import load_color

            try:
                self._thumbs[name] = _resize_longest(load_color(self.image_path(name)), PAIR_PX)
            except Exception:  # a diagnostic picture is never worth failing the run
                self._thumbs[name] = None
        return self._thumbs[name]

    # hooks --------------------------------------------------------------------------------------
    def _timed(self, fn: Callable[..., None], *args: Any) -> None:
        """Run one logging call, adding its wall time to `seconds` (the overhead measurement).

        A logging failure (a viewer closed under `connect`, a full disk) must not cost the
        reconstruction: the first one is logged once as a warning, kept in `error`, and logging
        stops; the run goes on.
        """
        if self.error is not None:
            return
        t0 = time.perf_counter()
        try:
            fn(*args)
        except Exception as e:
            self.error = f"{type(e).__name__}: {e}"
            log.warning("Rerun logging stopped (%s); the run goes on", self.error)
        finally:
            self.seconds += time.perf_counter() - t0

    def on_pair(self, i: int, name0: str, name1: str, result: PairResult, cached: bool) -> None:
        """RunObserver.on_pair: the pair's diagnostics (see module doc)."""
        self._timed(self._log_pair, i, name0, name1, result, cached)

    def _log_pair(self, i: int, name0: str, name1: str, r: PairResult, cached: bool) -> None:
        import rerun as rr

        rec = self.open_sink()
        if rec is None:
            return
        self._pairs.append((i, name0, name1))
        base = pair_entity(name0, name1)
        rec.set_time("pair", sequence=i)
        t0, t1 = self._thumb(name0), self._thumb(name1)
        if t0 is not None and t1 is not None:
            from recon.viz.vis import draw_matches

            (im0, s0), (im1, s1) = t0, t1
            small = dataclasses.replace(r, kpts0=(r.kpts0 * np.float32(s0)).astype(np.float32),
                                        kpts1=(r.kpts1 * np.float32(s1)).astype(np.float32))
            rec.log(f"{base}/matches", rr.EncodedImage(contents=_jpeg(draw_matches(im0, im1, small)),
                                                      media_type="image/jpeg"), static=True)
        rec.log(f"{base}/info", rr.TextDocument(pair_markdown(name0, name1, r, cached),
                                               media_type=rr.MediaType.MARKDOWN), static=True)
        rec.log(base, rr.AnyValues(image0=name0, image1=name1, raw_matches=r.num_matches,
                                   inliers=r.num_inliers, cached=bool(cached)), static=True)
        if r.coarse_scores:
            grid, labels, chosen = coarse_grid(r)
            rec.log(f"{base}/coarse", rr.EncodedImage(contents=_png(heatmap_image(grid, chosen)), media_type="image/png"),
                    static=True)
            rec.log(f"{base}/coarse_scores", rr.Tensor(grid, dim_names=("tilt", "longitude")),
                    rr.AnyValues(rows=labels), static=True)
        rec.log("plots/pair/raw_matches", rr.Scalars(float(r.num_matches)))
        rec.log("plots/pair/inliers", rr.Scalars(float(r.num_inliers)))
        rec.log("plots/pair/seconds", rr.Scalars(float(r.timings.get("total", 0.0))))

    def on_sfm_step(self, step: Any, live: Any) -> None:
        """RunObserver.on_sfm_step: one frame of the growth replay (see module doc)."""
        self._timed(self._log_growth_step, step, live)

    def _log_growth_step(self, step: Any, live: Any) -> None:
        import rerun as rr

        rec = self.open_sink()
        if rec is None:
            return
        rec.reset_time()
        rec.set_time("registration", sequence=int(step.step))
        if self._growth_model != step.model:  # a new model: forget the old cameras
            rec.log("growth", rr.Clear(recursive=True))
            self._growth_model = step.model
        for image_id in live.reg_image_ids():
            img = live.image(image_id)
            self._log_camera(rec, f"growth/cameras/{_esc(img.name)}", img, with_image=False, static=False,
                             color=GROWTH_NEW if img.name == step.image or step.registered_images == 2 else GROWTH_OLD)
        ids = sorted(live.point3D_ids())
        if len(ids) > GROWTH_POINTS:
            ids = [ids[i] for i in np.linspace(0, len(ids) - 1, GROWTH_POINTS).round().astype(int)]
        xyz = np.array([live.point3D(i).xyz for i in ids], np.float64).reshape(-1, 3)
        rec.log("growth/points", rr.Points3D(xyz, colors=GROWTH_PTS, radii=rr.Radius.ui_points(2.0)))
        rec.log("growth/info", rr.TextDocument(
            f"**step {step.step}** (model {step.model}): registered **{step.image}**\n\n"
            f"{step.registered_images} images, {step.num_points3D} points\n\n"
            f"order: {', '.join(step.images)}", media_type=rr.MediaType.MARKDOWN))
        rec.reset_time()

    def on_model(self, model: Any, report: Any) -> None:
        """RunObserver.on_model: verdicts, plots, the final model, summary, blueprint."""
        self._timed(self._log_model, model, report)

    def _log_model(self, model: Any, report: Any) -> None:
        import rerun as rr

        rec = self.open_sink()
        if rec is None:
            return
        for i, p in enumerate(report.pairs):  # COLMAP's verdict is known only now
            rec.set_time("pair", sequence=i)
            rec.log("plots/pair/verified_inliers", rr.Scalars(float(p.verified_inliers)))
            rec.log(f"{pair_entity(p.image0, p.image1)}/verified", rr.AnyValues(verified_inliers=int(p.verified_inliers),
                                                                              two_view_config=p.config))
        rec.reset_time()
        if report.pairs:
            rec.log("plots/bars/verified_inliers", rr.BarChart(np.array([p.verified_inliers for p in report.pairs],
                                                                         np.float64)),
                    rr.AnyValues(pairs=[f"{p.image0} | {p.image1}" for p in report.pairs]), static=True)
        if report.sfm_growth:
            rec.log("plots/growth/registered_images",
                    rr.BarChart(np.array([g["registered_images"] for g in report.sfm_growth], np.float64)),
                    rr.AnyValues(images=[g["image"] for g in report.sfm_growth],
                                 models=np.array([g["model"] for g in report.sfm_growth], np.int64)), static=True)
            rec.log("plots/growth/points3D",
                    rr.BarChart(np.array([g["num_points3D"] for g in report.sfm_growth], np.float64)), static=True)
        if model is not None:
            self._log_reconstruction(rec, model)
        rec.log("summary", rr.TextDocument(summary_markdown(report), media_type=rr.MediaType.MARKDOWN), static=True)
        rec.send_blueprint(self.blueprint(report), make_active=True, make_default=True)

    def _log_camera(self, rec: Any, ent: str, img: Any, *, with_image: bool, static: bool,
                    color: tuple[int, int, int] | None = None) -> None:
        """A registered pycolmap image as a camera (`log_camera`), with its JPEG thumbnail when
        `with_image`."""
        cam = img.camera
        pose = img.cam_from_world()
        P = np.hstack([np.asarray(pose.rotation.matrix(), np.float64),
                       np.asarray(pose.translation, np.float64).reshape(3, 1)])
        thumb = self._thumb(img.name) if with_image else None
        small = _resize_longest(thumb[0], THUMB_PX)[0] if thumb is not None else None
        log_camera(rec, ent, P, np.asarray(cam.calibration_matrix(), np.float64), (cam.width, cam.height),
                   static=static, color=color, image_bgr=small)

    def _log_reconstruction(self, rec: Any, model: Any) -> None:
        import rerun as rr

        names, counts = [], []
        for image_id in sorted(model.reg_image_ids()):
            img = model.image(image_id)
            ent = camera_entity(img.name)
            self._log_camera(rec, ent, img, with_image=True, static=True)
            rec.log(ent, rr.AnyValues(image_name=img.name, image_id=int(image_id), camera_model=img.camera.model_name,
                                      camera_params=np.asarray(img.camera.params, np.float64),
                                      full_resolution=np.array([img.camera.width, img.camera.height], np.int64),
                                      num_points3D=int(img.num_points3D)), static=True)
            names.append(img.name)
            counts.append(int(img.num_points3D))
        pts = model.points3D
        n = len(pts)
        xyz = np.empty((n, 3), np.float64)
        rgb = np.empty((n, 3), np.uint8)
        err = np.empty(n, np.float64)
        tl = np.empty(n, np.int64)
        for k, p in enumerate(pts.values()):
            xyz[k] = p.xyz
            rgb[k] = p.color
            err[k] = p.error
            tl[k] = p.track.length()
        rec.log("world/points", rr.Points3D(xyz, colors=rgb, radii=rr.Radius.ui_points(2.0)),
                rr.AnyValues(reprojection_error=err, track_length=tl), static=True)
        if counts:
            rec.log("plots/model/points_per_image", rr.BarChart(np.asarray(counts, np.float64)),
                    rr.AnyValues(image_names=names), static=True)

    # blueprint ----------------------------------------------------------------------------------
    def blueprint(self, report: Any = None):
        """3D view | (pair view of the best pair, per-pair plots, model plot, summary)."""
        import rerun.blueprint as rrb

        best = None
        if report is not None and report.pairs:
            p = max(report.pairs, key=lambda p: (p.verified_inliers, p.raw_matches))
            best = (p.image0, p.image1)
        elif self._pairs:
            best = self._pairs[0][1:]
        tabs: list = []
        if best is not None:
            base = pair_entity(*best)
            tabs.append(rrb.Horizontal(
                rrb.Spatial2DView(name=f"pair {best[0]} / {best[1]}", origin=f"{base}/matches"),
                rrb.Vertical(rrb.Spatial2DView(name="coarse scores (tilt × longitude)", origin=f"{base}/coarse"),
                             rrb.TextDocumentView(name="pair info", origin=f"{base}/info")),
                column_shares=[3, 2], name="pair"))
        tabs.append(rrb.TextDocumentView(name="summary", origin="summary"))
        plots = rrb.Tabs(
            rrb.TimeSeriesView(name="per pair", origin="plots/pair"),
            rrb.BarChartView(name="verified inliers per pair", origin="plots/bars/verified_inliers"),
            rrb.Horizontal(rrb.BarChartView(name="registered images per step", origin="plots/growth/registered_images"),
                           rrb.BarChartView(name="3D points per step", origin="plots/growth/points3D"),
                           name="growth"),
            rrb.BarChartView(name="points per registered image", origin="plots/model/points_per_image"),
            name="plots")
        world = rrb.Tabs(
            rrb.Spatial3DView(name="3D", origin="world"),
            rrb.Vertical(rrb.Spatial3DView(name="growth replay (timeline: registration)", origin="growth"),
                         rrb.TextDocumentView(name="step", origin="growth/info"), row_shares=[5, 1],
                         name="growth replay"))
        return rrb.Blueprint(
            rrb.Horizontal(world, rrb.Vertical(rrb.Tabs(*tabs), plots, row_shares=[3, 2]),
                           column_shares=[1, 1]),
            collapse_panels=False)


def log_single_pair(sink: Sink, path0: Path, path1: Path, result: PairResult) -> Path | None:
    """`recon match --rerun ...`: one pair's diagnostics; returns the saved file (save sink)."""
    import rerun.blueprint as rrb

    paths = {path0.name: path0, path1.name: path1} if path0.name != path1.name else {}
    n0, n1 = (path0.name, path1.name) if paths else (str(path0), str(path1))
    lookup = paths or {str(path0): path0, str(path1): path1}
    logger = RerunLogger(sink, lambda n: lookup[n], application_id="recon-match")
    ok = False
    try:
        logger.on_pair(0, n0, n1, result, False)
        if logger.rec is not None:
            base = pair_entity(n0, n1)
            logger.rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(
                rrb.Spatial2DView(name="matches", origin=f"{base}/matches"),
                rrb.Vertical(rrb.Spatial2DView(name="coarse scores", origin=f"{base}/coarse"),
                             rrb.TextDocumentView(name="info", origin=f"{base}/info")),
                column_shares=[3, 2])), make_active=True, make_default=True)
        ok = True
    finally:
        saved = logger.close(ok)
    return saved
