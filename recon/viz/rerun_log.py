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
* `pairs/<name0>__<name1>/matches`: the pair view, in the pixels of a side-by-side picture
  (image 0 left, image 1 right, each at most `PAIR_PX`): `.../matches/images` (the two images,
  JPEG, no lines burnt in), `.../matches/inliers` and `.../matches/outliers` (`LineStrips2D`,
  green and red, at most `MAX_STRIPS` each, a seeded sample; separate entities, so a user can
  hide either and hover a line to see its index); `.../info` (Markdown, with the counts),
  `.../coarse` (PNG heat map of the coarse score of every simulated view: rows = tilt (and
  scale), columns = longitude index, labelled axes and a colour scale; the chosen view(s) boxed
  in white) and `.../coarse_scores` (the raw grid as a `Tensor`, NaN where no view was simulated);
* `growth/...` on the `registration` timeline (sequence = registration step, 0 = the initial
  pair): the model as incremental mapping builds it, for replay image by image:
  `growth/cameras/<image>` (pose and intrinsics of every image registered so far, re-logged
  each step because bundle adjustment moves them; the image just registered in orange),
  `growth/points` (at most `GROWTH_POINTS` points, evenly subsampled, uniform colour: COLMAP
  extracts point colours only at the end) and `growth/info` (Markdown: step, image, counts).
  When the model is reused from an earlier run (no live steps), the replay is rebuilt from
  report.json's `sfm_growth` (the registration order) and the final model (`replay_steps`):
  each step shows the images registered so far at their *final* poses and the points seen by
  at least two of them (the intermediate bundle-adjusted poses of the first run are not kept);
* `plots/pair/*`: raw matches, matcher inliers and COLMAP-verified inliers per pair on the `pair`
  timeline; `plots/pair_seconds/seconds` (matching seconds per pair: its own plot, counts and
  seconds do not share an axis); `plots/bars/verified_inliers` (`BarChart` over pair index);
  `plots/growth/registered_images` and `plots/growth/points3D` (`BarChart` over registration
  step, from the report so they exist for reused models too); `plots/model/points_per_image`
  (`BarChart`, registered images in image id order); `summary` (Markdown report headline numbers).

Per-pair entities and the final model are static, so they show on every timeline.

The sink is opened lazily on the first logged item, so nothing is created in the output folder
before the pipeline has checked and claimed it. A saved recording is written to a temporary
`.NAME.tmp-<pid>` file and renamed when complete, so a killed run never leaves half a file.

Closing never hangs: the final flush of a `connect` / `spawn` sink blocks for as long as no
viewer accepts the data (rerun-sdk 0.41 waits for ever by default), and disconnecting a file
sink whose writer died (a full disk) blocks for ever too, so `close` runs both in a daemon
thread (`finish_stream`) and gives up after `CLOSE_TIMEOUT_S` (`SAVE_CLOSE_TIMEOUT_S` for a
file's flush, `DISCONNECT_TIMEOUT_S` for the disconnect) with one warning, and the unfinished
file is deleted; Ctrl-C still works while it waits. The viewer can be chosen with
`RECON_RERUN_VIEWER=/path/to/rerun` (see `find_viewer`).

An absent viewer costs one warning and nothing else: `connect` checks that something listens at
the URL before streaming, and `spawn` starts the viewer itself (`spawn_viewer`) and stops at
once when it exits (a machine without a display) instead of buffering the recording for it.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from matching.types import PairResult
from recon.core.observer import BaseRunObserver
from recon.core.report import final_ba_row, principal_point_row

RECORDING_NAME = "recording.rrd"
SINK_KINDS = ("save", "spawn", "connect", "none")
THUMB_PX = 320  # longest side of the camera images in the 3D view
# Longest side of each image in a pair's side-by-side match picture, and JPEG quality: the
# recording's size is mostly these pictures (measured in docs/decisions.md, "Rerun recordings").
PAIR_PX = 512
JPEG_QUALITY = 80
MAX_STRIPS = 80  # match lines per class (inliers, outliers) in the Rerun pair view: legible at viewer size
STRIP_ALPHA = 170  # lines a little transparent, so the images show through a dense set
GROWTH_POINTS = 20000  # points per step of the growth replay (keeps a 30-image recording small)
GROWTH_NEW = (255, 140, 0)  # the camera just registered
GROWTH_OLD = (150, 150, 150)  # cameras registered earlier
GROWTH_PTS = (90, 160, 230)
CLOSE_TIMEOUT_S = 3.0  # connect / spawn: how long the final flush may wait for a viewer
SAVE_CLOSE_TIMEOUT_S = 120.0  # save: flushing a local file is only slow when it is huge
DISCONNECT_TIMEOUT_S = 3.0  # after a flush, disconnecting is immediate unless the sink is dead
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
    """The Rerun viewer executable: `RECON_RERUN_VIEWER` when set (an empty value means none),
    else `rerun` next to this Python (a venv's bin/) or on PATH; None when there is none."""
    chosen = os.environ.get("RECON_RERUN_VIEWER")
    if chosen is not None:
        return shutil.which(chosen) if chosen.strip() else None
    here = str(Path(sys.executable).parent)
    return shutil.which("rerun", path=os.pathsep.join([here, os.environ.get("PATH", "")]))


DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
SPAWN_TIMEOUT_S = 10.0  # how long a spawned viewer may take to listen


def viewer_address(url: str | None) -> tuple[str, int]:
    """(host, port) of a `connect` URL (rerun's default when None)."""
    from urllib.parse import urlsplit

    parts = urlsplit(url or DEFAULT_URL)
    return parts.hostname or "127.0.0.1", parts.port or 9876


def port_is_open(host: str, port: int, timeout_s: float = 1.0) -> bool:
    import socket

    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:
        return False


def spawn_viewer(exe: str, port: int = 9876) -> str:
    """Start the Rerun viewer listening on `port` (or reuse one already listening) and return its
    URL. RuntimeError (one line, with the viewer's last error line) when it exits before
    listening, e.g. on a machine without a display, or does not listen within
    `SPAWN_TIMEOUT_S`: then nothing is buffered for a viewer that will never come (rerun's own
    `spawn` waits, then buffers the whole recording for it)."""
    import subprocess
    import tempfile

    from recon._signals import unblocked_for_children

    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if port_is_open("127.0.0.1", port, 0.2):
        return url
    with tempfile.TemporaryFile() as err:
        with unblocked_for_children():  # the viewer process must be able to be terminated
            proc = subprocess.Popen([exe, f"--port={port}", "--memory-limit=75%", "--expect-data-soon"],
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                                    start_new_session=True, env={**os.environ, "RERUN_APP_ONLY": "true"})
        deadline = time.monotonic() + SPAWN_TIMEOUT_S
        while time.monotonic() < deadline:
            code = proc.poll()
            if code is not None:
                err.seek(0)
                lines = [ln.strip() for ln in err.read().decode(errors="replace").splitlines() if ln.strip()]
                why = f": {lines[-1][:200]}" if lines else ""
                raise RuntimeError(f"the Rerun viewer {exe} exited at once (code {code}{why})")
            if port_is_open("127.0.0.1", port, 0.2):
                return url
            time.sleep(0.1)
    raise RuntimeError(f"the Rerun viewer {exe} did not listen on port {port} within {SPAWN_TIMEOUT_S:.0f} s")


def finish_stream(rec: Any, flush_timeout_s: float, disconnect_timeout_s: float = DISCONNECT_TIMEOUT_S) -> str | None:
    """Flush, then disconnect, a RecordingStream, each bounded in time; None when both finished,
    else why not (one line).

    Runs in a daemon thread so a sink that never drains cannot hang the process: rerun-sdk
    0.41's flush waits for ever for an absent viewer, and its disconnect waits for ever after a
    file sink's writer died (a full disk). The waits themselves can be interrupted with Ctrl-C.
    """
    errors: list[str] = []
    flushed = threading.Event()

    def work() -> None:
        try:
            rec.flush(timeout_sec=flush_timeout_s)
        except Exception as e:  # rerun raises when its own timeout passes
            errors.append(f"{type(e).__name__}: {e}")
        flushed.set()
        if errors:
            return  # a sink that did not flush would block disconnect too
        try:
            rec.disconnect()
        except Exception as e:
            errors.append(f"{type(e).__name__}: {e}")

    t = threading.Thread(target=work, name="recon-rerun-close", daemon=True)
    t.start()
    for event_done, limit, what in ((flushed.is_set, flush_timeout_s + 1.0, "flush"),
                                    (lambda: not t.is_alive(), disconnect_timeout_s, "disconnect")):
        deadline = time.monotonic() + limit
        while not event_done() and time.monotonic() < deadline:
            t.join(0.05)
        if not event_done():
            return f"{what} gave up after {limit:.0f} s"
        if errors:
            return errors[0]
    return None


_abandoned: list[Any] = []  # streams whose flush was given up (kept alive: dropping one blocks too)


def abandoned_streams() -> int:
    """How many streams were given up on; the program may then end with `os._exit` once its
    outputs are written (rerun's exit-time teardown waits for the absent viewer again)."""
    return len(_abandoned)


def _forget_stream(rec: Any) -> None:
    """Keep an undrained stream referenced (dropping it would block in its destructor) and skip
    rerun's exit-time flush of every stream, which would wait for the absent viewer again."""
    _abandoned.append(rec)
    try:
        import rerun as rr

        rr.unregister_shutdown()
    except Exception:
        pass


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
        for col, cs in enumerate(sorted(rows[k], key=lambda x: x.view.phi)):
            grid[r, col] = cs.score
            if cs.view.key in chosen_keys:
                chosen.append((r, col))
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


def heatmap_figure(grid: NDArray[np.float32], labels: list[str], chosen: list[tuple[int, int]],
                   cell: int = 28) -> NDArray[np.uint8]:
    """`heatmap_image` with axes: row labels (tilt t, and scale s when not 1) on the left, the
    longitude index below, and a colour bar on the right from the lowest to the highest score.
    RGB, white background."""
    font, fs, th = cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1
    cells = heatmap_image(grid, chosen, cell)
    h, w = cells.shape[:2]
    left = 12 + max([cv2.getTextSize(t, font, fs, th)[0][0] for t in labels] + [40])
    top, bottom, bar_w, right = 26, 44, 16, 90
    fig = np.full((top + h + bottom, left + w + 20 + bar_w + right, 3), 255, np.uint8)
    fig[top:top + h, left:left + w] = cells
    black = (0, 0, 0)
    cv2.putText(fig, "coarse score per simulated view", (left, 18), font, fs, black, th, cv2.LINE_AA)
    for r, t in enumerate(labels):
        cv2.putText(fig, t, (4, top + r * cell + cell // 2 + 5), font, fs, black, th, cv2.LINE_AA)
    ncol = grid.shape[1]
    for c in range(ncol):
        if ncol <= 12 or c % max(1, ncol // 8) == 0:
            cv2.putText(fig, str(c), (left + c * cell + cell // 2 - 4, top + h + 16), font, fs, black, th, cv2.LINE_AA)
    cv2.putText(fig, "longitude index (phi increasing) ->", (left, top + h + 36), font, fs, black, th, cv2.LINE_AA)
    cv2.putText(fig, "tilt", (4, top - 8), font, fs, black, th, cv2.LINE_AA)
    # colour bar: viridis from the lowest (bottom) to the highest (top) score
    x0 = left + w + 20
    ramp = np.linspace(255, 0, max(h, 2)).astype(np.uint8).reshape(-1, 1)
    bar = cv2.cvtColor(cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)
    fig[top:top + h, x0:x0 + bar_w] = np.repeat(bar, bar_w, axis=1)[:h]
    valid = np.isfinite(grid)
    lo, hi = (float(grid[valid].min()), float(grid[valid].max())) if valid.any() else (0.0, 0.0)
    cv2.putText(fig, f"{hi:.3g}", (x0 + bar_w + 4, top + 10), font, fs, black, th, cv2.LINE_AA)
    cv2.putText(fig, f"{lo:.3g}", (x0 + bar_w + 4, top + h), font, fs, black, th, cv2.LINE_AA)
    cv2.putText(fig, "score", (x0 - 4, top + h + 16), font, fs, black, th, cv2.LINE_AA)
    return fig


def match_strips(result: PairResult, scale0: float, scale1: float, offset_x: float, max_lines: int = MAX_STRIPS,
                 seed: int = 0) -> dict[str, tuple[NDArray[np.float32], NDArray[np.int64]]]:
    """{"inliers": (strips (N, 2, 2), match indices), "outliers": ...}: each match as a line from
    its keypoint in image 0 (scaled by `scale0`) to its keypoint in image 1 (scaled by `scale1`,
    shifted right by `offset_x`), in the side-by-side picture's pixels; at most `max_lines` of
    each class, a seeded sample. OpenCV keypoints (pixel centres at integers) are moved by +0.5
    to Rerun's image coordinates (pixel centres at +0.5)."""
    from recon.viz.vis import sample_matches

    n = result.num_matches
    inl = result.inlier_mask if result.inlier_mask is not None else np.ones(n, bool)
    out = {}
    for name, mask in (("inliers", inl), ("outliers", ~inl)):
        idx = np.flatnonzero(mask[:n]) if n else np.zeros(0, np.int64)
        idx = idx[sample_matches(len(idx), max_lines, seed)]
        p0 = (result.kpts0[result.matches[idx, 0]].astype(np.float32) + 0.5) * np.float32(scale0)
        p1 = (result.kpts1[result.matches[idx, 1]].astype(np.float32) + 0.5) * np.float32(scale1)
        p1[:, 0] += np.float32(offset_x)
        out[name] = (np.stack([p0, p1], axis=1).astype(np.float32).reshape(-1, 2, 2), idx.astype(np.int64))
    return out


def side_by_side(im0: NDArray[np.uint8], im1: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Image 0 left, image 1 right, top-aligned, black below the shorter one (BGR)."""
    h = max(im0.shape[0], im1.shape[0])
    canvas = np.zeros((h, im0.shape[1] + im1.shape[1], 3), np.uint8)
    canvas[:im0.shape[0], :im0.shape[1]] = im0 if im0.ndim == 3 else cv2.cvtColor(im0, cv2.COLOR_GRAY2BGR)
    canvas[:im1.shape[0], im0.shape[1]:] = im1 if im1.ndim == 3 else cv2.cvtColor(im1, cv2.COLOR_GRAY2BGR)
    return canvas


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
    if r.finishing:
        lines.append(f"| finishing | {r.finishing} |")
    lines.append(f"| raw matches | {r.num_matches} |")
    lines.append(f"| matcher inliers | {r.num_inliers} |")
    if verified is not None:
        lines.append(f"| COLMAP-verified inliers | {verified} |")
    lines.append(f"| simulated views scored | {len(r.coarse_scores)} |")
    lines.append(f"| from cache | {'yes' if cached else 'no'} |")
    if r.reason:
        lines.append(f"| note | {r.reason} |")
    stages = [(k, v) for k, v in r.timings.items() if isinstance(v, (int, float))]
    if stages:
        lines += ["", "### Time per stage", "", "| stage | s |", "|---|---:|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in stages]
    return "\n".join(lines) + "\n"


def summary_markdown(report: Any) -> str:
    err = report.mean_reprojection_error
    verified = sum(1 for p in report.pairs if p.verified_inliers > 0)
    before_final_ba = final_ba_row(report)
    principal_point = principal_point_row(report)
    lines = [f"# recon run: {Path(report.scene).name}", "",
             f"**status:** {report.status}" + (f" — {report.message}" if report.message else ""), "",
             "| metric | value |", "|---|---:|",
             f"| images (usable / skipped) | {report.num_images} / {len(report.skipped)} |",
             f"| registered images | {report.registered_images} / {report.num_images} |",
             f"| 3D points | {report.num_points3D} |",
             f"| mean track length (model) | {report.mean_track_length:.2f} |",
             f"| mean reprojection error (px) | {'-' if err is None else f'{err:.3f}'} |",
             *([f"| {before_final_ba[0]} | {before_final_ba[1]} |"] if before_final_ba else []),
             *([f"| {principal_point[0]} | {principal_point[1]} |"] if principal_point else []),
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
        lines += ["", "_The model was reused from an earlier run: its growth replay (timeline `registration`) "
                      "is rebuilt from the registration order with the final poses._"]
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
        if sink.enabled and "rerun" not in sys.modules:
            # rerun's own log lines (an absent viewer, a full disk; it reads RUST_LOG once, at
            # import) would repeat our one warning several times; RUST_LOG=... still overrides
            os.environ.setdefault("RUST_LOG", "off")

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
            rec.connect_grpc(spawn_viewer(exe))
        else:  # connect
            host, port = viewer_address(self.sink.target)
            if not port_is_open(host, port):
                raise RuntimeError(f"no Rerun viewer is listening at {self.sink.target or DEFAULT_URL} (start one "
                                   f"with `rerun`, or use --rerun save)")
            rec.connect_grpc(self.sink.target)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)  # COLMAP: y down, z forward
        self.rec = rec
        return rec

    def close(self, ok: bool = True) -> Path | None:
        """Flush and close the sink, bounded in time (see module doc); a saved recording is moved
        into place (deleted when not ok). A sink that does not drain gives one warning."""
        if self.rec is None:
            return None
        rec, self.rec = self.rec, None
        timeout = SAVE_CLOSE_TIMEOUT_S if self.sink.kind == "save" else CLOSE_TIMEOUT_S
        problem = finish_stream(rec, timeout)
        if problem is not None:
            _forget_stream(rec)
            if ok:  # a failed run has its own error line; one is enough
                if self.sink.kind == "save":
                    print(f"recon: warning: the Rerun recording {self.sink.target} could not be completed "
                          f"({problem}); the run's outputs are complete", file=sys.stderr)
                else:
                    where = self.sink.target or DEFAULT_URL
                    print(f"recon: warning: the Rerun viewer at {where} did not take the recording ({problem}; "
                          f"was it closed?); the run's outputs are complete", file=sys.stderr)
        if self._tmp is None:
            return None
        tmp, self._tmp = self._tmp, None
        final = Path(self.sink.target).expanduser()  # type: ignore[arg-type]
        if ok and problem is None and tmp.exists():
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
            log_pair_view(rec, f"{base}/matches", t0, t1, r)
        rec.log(f"{base}/info", rr.TextDocument(pair_markdown(name0, name1, r, cached),
                                               media_type=rr.MediaType.MARKDOWN), static=True)
        rec.log(base, rr.AnyValues(image0=name0, image1=name1, raw_matches=r.num_matches,
                                   inliers=r.num_inliers, cached=bool(cached)), static=True)
        if r.coarse_scores:
            grid, labels, chosen = coarse_grid(r)
            rec.log(f"{base}/coarse", rr.EncodedImage(contents=_png(heatmap_figure(grid, labels, chosen)),
                                                      media_type="image/png"), static=True)
            rec.log(f"{base}/coarse_scores", rr.Tensor(grid, dim_names=("tilt", "longitude")),
                    rr.AnyValues(rows=labels), static=True)
        rec.log("plots/pair/raw_matches", rr.Scalars(float(r.num_matches)))
        rec.log("plots/pair/inliers", rr.Scalars(float(r.num_inliers)))
        rec.log("plots/pair_seconds/seconds", rr.Scalars(float(r.timings.get("total", 0.0))))

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
            rec.log(f"{pair_entity(p.image0, p.image1)}/verified",
                    rr.AnyValues(verified_inliers=int(p.verified_inliers), confirmed_inliers=int(p.confirmed_inliers),
                                 two_view_config=p.two_view_config))
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
            if self._growth_model is None and report.sfm_growth:  # reused model: no live steps
                self._replay_growth(rec, model, report.sfm_growth)
        rec.log("summary", rr.TextDocument(summary_markdown(report), media_type=rr.MediaType.MARKDOWN), static=True)
        rec.send_blueprint(self.blueprint(report), make_active=True, make_default=True)

    def _replay_growth(self, rec: Any, model: Any, growth: list[dict[str, Any]]) -> None:
        """The growth replay of a reused model, rebuilt from `sfm_growth` (see module doc)."""
        import rerun as rr

        steps = replay_steps(model, growth)
        if not steps:
            return
        ids = {model.image(i).name: int(i) for i in model.reg_image_ids()}
        pts = model.points3D
        xyz = np.array([p.xyz for p in pts.values()], np.float64).reshape(-1, 3)
        obs_point = np.concatenate([np.full(p.track.length(), k, np.int64) for k, p in enumerate(pts.values())]
                                   or [np.zeros(0, np.int64)])
        obs_image = np.concatenate([np.array([e.image_id for e in p.track.elements], np.int64) for p in pts.values()]
                                   or [np.zeros(0, np.int64)])
        rec.reset_time()
        for n, (step, names, image) in enumerate(steps):
            rec.set_time("registration", sequence=int(step))
            if n == 0:
                rec.log("growth", rr.Clear(recursive=True))
            for name in names:
                self._log_camera(rec, f"growth/cameras/{_esc(name)}", model.image(ids[name]), with_image=False,
                                 static=False, color=GROWTH_NEW if name == image or n == 0 else GROWTH_OLD)
            seen = np.bincount(obs_point[np.isin(obs_image, [ids[m] for m in names])], minlength=len(xyz))
            sel = np.flatnonzero(seen >= 2)
            if len(sel) > GROWTH_POINTS:
                sel = sel[np.linspace(0, len(sel) - 1, GROWTH_POINTS).round().astype(int)]
            rec.log("growth/points", rr.Points3D(xyz[sel], colors=GROWTH_PTS, radii=rr.Radius.ui_points(2.0)))
            rec.log("growth/info", rr.TextDocument(
                f"**step {step}**: registered **{image}**\n\n{len(names)} images, {len(sel)} points seen by two "
                f"of them\n\norder: {', '.join(names)}\n\n_rebuilt from report.json (final poses)_",
                media_type=rr.MediaType.MARKDOWN))
        rec.reset_time()
        self._growth_model = -1

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
                rrb.Vertical(rrb.Spatial2DView(name="coarse scores (tilt x longitude)", origin=f"{base}/coarse"),
                             rrb.TextDocumentView(name="pair info", origin=f"{base}/info")),
                column_shares=[3, 2], name="pair"))
        tabs.append(rrb.TextDocumentView(name="summary", origin="summary"))
        plots = rrb.Tabs(
            rrb.TimeSeriesView(name="matches per pair", origin="plots/pair"),
            rrb.TimeSeriesView(name="seconds per pair", origin="plots/pair_seconds"),
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


def log_pair_view(rec: Any, ent: str, thumb0: tuple[NDArray[np.uint8], float],
                  thumb1: tuple[NDArray[np.uint8], float], r: PairResult) -> None:
    """The pair view under `ent` (see module doc): the two images side by side, then inliers and
    outliers as line strips over them (drawn above the images, inliers above outliers)."""
    import rerun as rr

    (im0, s0), (im1, s1) = thumb0, thumb1
    rec.log(f"{ent}/images", rr.EncodedImage(contents=_jpeg(side_by_side(im0, im1)), media_type="image/jpeg",
                                             draw_order=-10.0), static=True)
    from recon.viz.vis import INLIER_BGR, OUTLIER_BGR

    strips = match_strips(r, s0, s1, float(im0.shape[1]))
    for (name, (lines, idx)), bgr, order in zip(strips.items(), (INLIER_BGR, OUTLIER_BGR), (30.0, 25.0)):
        rec.log(f"{ent}/{name}", rr.LineStrips2D(lines, colors=(*bgr[::-1], STRIP_ALPHA),
                                                 radii=rr.Radius.ui_points(0.75),
                                                 labels=[f"match {i}" for i in idx], show_labels=False,
                                                 draw_order=order), static=True)


def replay_steps(model: Any, growth: list[dict[str, Any]]) -> list[tuple[int, list[str], str]]:
    """[(step, images registered so far, image just registered)] of the growth rows of `model`
    (the kept model: the rows' model index whose images it holds most of), images no longer in
    the model dropped. The first row's two images come from its `initial_pair` (report schema 2);
    a version-1 row names only the second, and the first is the one image of the model that no
    row names."""
    in_model = {model.image(i).name for i in model.reg_image_ids()}
    by_model: dict[int, list[dict[str, Any]]] = {}
    for g in growth:
        by_model.setdefault(int(g["model"]), []).append(g)
    if not by_model:
        return []
    rows = max(by_model.values(), key=lambda rs: (sum(g["image"] in in_model for g in rs), len(rs)))
    first = rows[0]
    pair = first.get("initial_pair")
    if pair:
        order = [n for n in pair if n != first["image"]] + [first["image"]]
    else:
        named = {g["image"] for g in rows}
        order = sorted(in_model - named)[:1] + [first["image"]]
    steps = [(int(first["step"]), [n for n in order if n in in_model], first["image"])]
    for g in rows[1:]:
        order.append(g["image"])
        steps.append((int(g["step"]), [n for n in order if n in in_model], g["image"]))
    return steps


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
                rrb.Spatial2DView(name="matches (toggle inliers / outliers in the panel)", origin=f"{base}/matches"),
                rrb.Vertical(rrb.Spatial2DView(name="coarse scores", origin=f"{base}/coarse"),
                             rrb.TextDocumentView(name="info", origin=f"{base}/info")),
                column_shares=[3, 2])), make_active=True, make_default=True)
        ok = True
    finally:
        saved = logger.close(ok)
    return saved
