"""`run_scene`: photos -> pair matches -> merged tracks -> COLMAP database -> SfM -> outputs.

Stages (each timed in `report.stages`, each with a progress bar on stderr):

1. `load`: find and decode the photos (`recon.core.scene`), skip bad ones, downscale to `max_size`.
2. `match`: every pair of `--pairs` (`recon.core.pairs`) is an independent task
   `match_pair_task(store, matcher, name0, name1) -> PairResult` over a shared, thread-safe
   per-image `FeatureStore` (features computed once per image and run, persisted under
   `OUT/cache/features`), run on a ThreadPoolExecutor (OpenCV releases the GIL). Each finished
   pair is converted to full-resolution pixels and written atomically to
   `OUT/cache/pairs/<hash>.npz` (hash of matcher config + both images' pixel digests + working
   sizes), so an interrupted run recomputes only the missing pairs. Results are collected in pair
   order, never completion order, so a fixed `--seed` gives the same output whatever the
   scheduling. The tasks only need (store, matcher, two names), so a later version can hand them
   to Dask or Ray.
3. `tracks`: per-image keypoint merging (`recon.core.tracks`, radius `--merge-px` in working-
   resolution pixels) so 3D points can be seen in more than two images.
4. `database` + `verify`: `recon.core.database` writes cameras (EXIF), images, keypoints (+0.5 for
   COLMAP's pixel centres) and *all* the matcher's matches (the pipeline asks the matcher for
   `final_homography=False`: a homography is the wrong model for a 3D scene; COLMAP's own F / E
   verification decides), into `database.db.tmp`, then renames it to `database.db`.
5. `sfm`: `pycolmap.incremental_mapping` with wide-baseline options (`recon.core.sfm`), the largest
   model written to `OUT/sparse/0` through a temporary folder.
6. `export`: `points.ply` (open3d; `--clean-points` drops statistical outliers) and
   `report.json` (temp + `os.replace`).

Resuming: features and pair results are cached; the database and the model are reused when
`OUT/cache/state.json` records that they were built from exactly the current inputs (a hash of
the merged keypoints, matches and options). `--overwrite` deletes everything the pipeline wrote
(never other files) and starts over. The output folder is tied to its scene by
`OUT/.recon_scene.json` (scene path + image file names); a different scene is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from matching.errors import InputError
from matching.memory import peak_rss_mb
from matching.registry import METHODS, PairMatcher, get_matcher
from matching.store import FeatureStore
from matching.types import PairResult

from recon.errors import UserError
from recon.core.database import CAMERA_MODES, build_database, read_verified, two_view_options
from recon.core.pairs import PairsSpec, make_pairs, parse_pairs_spec
from recon.core.outdir import prepare_out
from recon.core.paircache import load_pair_result, pair_cache_key, result_to_full_res, save_pair_result
from recon.core.progress import Progress, quiet_colmap
from recon.core.report import PairRow, RunReport, write_json_atomic, write_report
from recon.core.scene import Scene, find_image_dir, list_candidates, scan_scene
from recon.core.tracks import PairMatches, merge_tracks, track_stats

STATE_VERSION = "1"


# configuration ----------------------------------------------------------------------------------
@dataclass
class RunConfig:
    """Options of `recon run` (the CLI flags one to one), validated on construction."""

    out: Path | None = None  # default: SCENE_DIR/recon
    method: str = "extra-affine"
    pairs: str = "exhaustive"  # exhaustive | sequential:K | path to a pairs file
    max_size: int = 1600  # working resolution (longer side, px); 0 = full resolution
    camera_mode: str = "auto"  # auto | single | per-image
    merge_px: float = 2.0  # keypoint merge radius, working-resolution px; 0 = no merging
    seed: int = 0
    workers: int = 0  # parallel pair tasks; 0 = all cores
    overwrite: bool = False
    clean_points: bool = False
    progress: bool = True  # rich progress bars on stderr

    def __post_init__(self) -> None:
        if self.out is not None:
            self.out = Path(self.out).expanduser()
        if self.method not in METHODS:
            raise UserError(f"--method {self.method!r}: choose one of {', '.join(METHODS)}")
        try:
            self.pairs_spec  # noqa: B018  (validates)
        except ValueError as e:
            raise UserError(str(e)) from None
        if not isinstance(self.max_size, int) or (self.max_size != 0 and self.max_size < 64):
            raise UserError(f"--max-size {self.max_size}: use 0 (full resolution) or at least 64 px")
        if self.camera_mode not in CAMERA_MODES:
            raise UserError(f"--camera-mode {self.camera_mode!r}: choose one of {', '.join(CAMERA_MODES)}")
        if not (self.merge_px >= 0 and np.isfinite(self.merge_px)):
            raise UserError(f"--merge-px {self.merge_px}: must be >= 0 (0 disables merging)")
        if self.seed < 0:
            raise UserError(f"--seed {self.seed}: must be >= 0")
        if self.workers < 0:
            raise UserError(f"--workers {self.workers}: must be >= 0 (0 = all cores)")

    @property
    def pairs_spec(self) -> PairsSpec:
        return parse_pairs_spec(self.pairs)

    @property
    def num_workers(self) -> int:
        return self.workers or (os.cpu_count() or 1)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["out"] = None if self.out is None else str(self.out)
        return d


# matching tasks ---------------------------------------------------------------------------------
def match_pair_task(store: FeatureStore, matcher: PairMatcher, name0: str, name1: str) -> PairResult:
    """One pair: a pure function of the per-image store and the matcher (no pipeline state)."""
    return matcher.match(store, name0, name1)


def make_matcher(method: str, seed: int = 0, inner_workers: int = 1) -> PairMatcher:
    """The registry's matcher for multi-view use: no final homography filter, seeded, and (when
    pairs already run in parallel) single-threaded inside. Overrides go only to config fields the
    matcher has (the registry raises ValueError for unknown ones)."""
    try:
        probe = get_matcher(method)
    except (ValueError, ImportError) as e:
        raise UserError(f"--method {method}: {e}") from None
    cfg = getattr(probe, "cfg", None)
    known = {f.name for f in dataclasses.fields(cfg)} if dataclasses.is_dataclass(cfg) else set()
    wanted = {"final_homography": False, "seed": int(seed), "workers": int(inner_workers)}
    overrides = {k: v for k, v in wanted.items() if k in known}
    if method == "extra-affine":
        overrides["variant"] = "multiview"
    return get_matcher(method, **overrides)


def matcher_identity(matcher: PairMatcher) -> str:
    """A stable text naming the matcher and the config fields that change its output (part of
    the pair cache key; thread counts are left out)."""
    cfg = getattr(matcher, "cfg", None) or getattr(matcher, "config", None)
    kind = f"{type(matcher).__module__}.{type(matcher).__qualname__}"
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        if "workers" in {f.name for f in dataclasses.fields(cfg)}:
            cfg = dataclasses.replace(cfg, workers=0)
        return f"{kind}:{cfg!r}"
    return f"{kind}:{getattr(matcher, 'name', '')}"


def _fingerprint(*parts: Any) -> str:
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(str(p.shape).encode())
            h.update(np.ascontiguousarray(p).tobytes())
        else:
            h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()


# the run ----------------------------------------------------------------------------------------
@dataclass
class _Stages:
    times: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        try:
            yield
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t


def run_scene(scene_dir: str | Path, cfg: RunConfig | None = None, *,
              matcher: PairMatcher | None = None,
              on_pair: Callable[[int, str, str, PairResult, bool], None] | None = None,
              on_model: Callable[[Any, RunReport], None] | None = None,
              on_sfm_step: Callable[[Any, Any], None] | None = None,
              on_warning: Callable[[str], None] | None = None) -> RunReport:
    """Reconstruct a scene folder; returns the report (also written to OUT/report.json).

    `matcher` overrides `cfg.method` (tests, comparisons). Hooks for live logging (e.g. Rerun):
    `on_pair(index, name0, name1, full_res_result, cached)` after each pair is available,
    `on_sfm_step(sfm.GrowthStep, live_reconstruction)` after each registration step of
    incremental mapping (not called when an unchanged model is reused),
    `on_model(reconstruction_or_None, report)` at the end. `on_warning(msg)` receives one-line
    warnings (default: printed to stderr as "recon: warning: ...").
    Raises InputError / UserError for unusable input; a scene without a model is not an error
    here: the report has status "no_model" (the CLI exits 1).
    """
    cfg = cfg or RunConfig()
    t_start = time.perf_counter()
    stages = _Stages()
    root = Path(scene_dir).expanduser()
    image_dir = find_image_dir(root)  # InputError for a missing scene folder
    root = root.resolve()
    image_dir = image_dir.resolve()
    candidates, _ = list_candidates(image_dir)
    if not candidates:
        raise InputError(f"{image_dir}: no images found (expected .jpg, .jpeg, .png, .tif or .tiff files)")
    if len(candidates) < 2:
        raise UserError(f"{image_dir}: need at least 2 images to reconstruct, found 1 ({candidates[0]})")
    out = (cfg.out or root / "recon").resolve()
    prepare_out(out, root, candidates, cfg.overwrite, default_out=cfg.out is None)

    report = RunReport(scene=str(root), out=str(out), config=cfg.to_dict())
    progress = Progress(cfg.progress)

    def warn(msg: str) -> None:
        report.warnings.append(msg)
        if on_warning is not None:
            on_warning(msg)
        else:
            progress.print(f"recon: warning: {msg}")

    cache = out / "cache"
    state_path = cache / "state.json"
    try:
        state = json.loads(state_path.read_text(encoding="utf-8")) if state_path.is_file() else {}
    except (OSError, ValueError):
        state = {}
    if state.get("version") != STATE_VERSION:
        state = {"version": STATE_VERSION}

    with progress, quiet_colmap():
        # 1. load ------------------------------------------------------------------------------
        with stages("load"):
            adv = progress.task("load", len(candidates))
            scene, grays = scan_scene(root, max_size=cfg.max_size or None, workers=cfg.num_workers,
                                      on_image=lambda _n: adv())
            for w in scene.warnings:
                warn(w)
            report.skipped = [{"name": s.name, "reason": s.reason} for s in scene.skipped]
        if len(scene.images) < 2:
            raise UserError(f"{scene.image_dir}: need at least 2 usable images, found {len(scene.images)}"
                            + (f" ({len(scene.skipped)} skipped: see warnings)" if scene.skipped else ""))

        sizes = sorted({(im.width, im.height) for im in scene.images})
        if cfg.camera_mode == "single" and len(sizes) > 1:
            raise UserError(f"--camera-mode single needs images of one size, found "
                            f"{', '.join(f'{w}x{h}' for w, h in sizes[:4])}; use auto or per-image")

        # 2. pairs and matching ---------------------------------------------------------------
        pairs, pair_warnings = make_pairs(cfg.pairs_spec, scene.names)
        for w in pair_warnings:
            warn(w)
        if not pairs:
            raise UserError(f"--pairs {cfg.pairs}: no pair of usable images to match")
        matcher = matcher or make_matcher(cfg.method, cfg.seed,
                                          inner_workers=1 if len(pairs) >= cfg.num_workers else 0)
        mid = matcher_identity(matcher)
        store = FeatureStore(cache_dir=cache / "features")
        for name in scene.names:
            store.add_image(name, grays[name])
        del grays
        with stages("match"):
            results, cached_flags = _match_all(scene, pairs, matcher, mid, store, cache / "pairs",
                                               cfg.num_workers, progress, warn, on_pair)
        report.pairs_cached = int(sum(cached_flags))
        report.pairs_computed = len(pairs) - report.pairs_cached
        report.features_computed, report.features_reused = int(store.misses), int(store.hits)

        # 3. tracks ----------------------------------------------------------------------------
        with stages("tracks"):
            radius = {im.name: cfg.merge_px / min(im.scale_xy) for im in scene.images}
            merged = merge_tracks([PairMatches(a, b, r.kpts0, r.kpts1, r.matches, r.distances)
                                   for (a, b), r in zip(pairs, results)], radius)
            keypoints = {n: merged.keypoints.get(n, np.zeros((0, 2), np.float32)) for n in scene.names}
            report.merge = {**merged.stats.to_dict(), "merge_px": cfg.merge_px}

        # 4. database + verification ----------------------------------------------------------
        px_scale = float(np.mean([1.0 / min(im.scale_xy) for im in scene.images]))
        two_view = two_view_options(cfg.seed, max_error_px=4.0 * min(max(px_scale, 1.0), 3.0))
        db_path = out / "database.db"
        db_fp = _fingerprint("db", STATE_VERSION, cfg.camera_mode, [(im.name, im.digest) for im in scene.images],
                             *[keypoints[n] for n in scene.names], pairs, *merged.matches,
                             two_view.summary() if hasattr(two_view, "summary") else "")
        ids: dict[str, int]
        if state.get("db_fingerprint") == db_fp and db_path.is_file() and state.get("image_ids"):
            ids = {k: int(v) for k, v in state["image_ids"].items()}
            report.camera_mode_used = state.get("camera_mode_used", "")
            report.database_reused = True
            missing = list(state.get("missing", []))
            stages.times.setdefault("database", 0.0)
            stages.times.setdefault("verify", 0.0)
        else:
            state.pop("sfm_fingerprint", None)
            state.pop("db_fingerprint", None)
            write_json_atomic(state_path, state)
            adv_db = progress.task("database", len(scene.names) + len(pairs))
            adv_verify: list[Callable[..., None]] = []
            marks: dict[str, float] = {}

            def on_stage(s: str) -> None:
                marks[s] = time.perf_counter()
                if s == "verify":
                    adv_db(done=True)
                    adv_verify.append(progress.task("verify", None))

            ids, used_mode, missing = build_database(
                db_path, scene.image_dir, scene.names, cfg.camera_mode, keypoints, pairs, merged.matches,
                two_view, num_threads=cfg.num_workers, on_stage=on_stage, on_item=lambda: adv_db())
            t_end = time.perf_counter()
            if adv_verify:
                adv_verify[0](done=True)
            stages.times["database"] = marks.get("verify", t_end) - marks.get("import", t_end)
            stages.times["verify"] = t_end - marks.get("verify", t_end)
            report.camera_mode_used = used_mode
            state.update(db_fingerprint=db_fp, image_ids=ids, camera_mode_used=used_mode, missing=missing)
            write_json_atomic(state_path, state)
        for n in missing:
            reason = "COLMAP could not read the image"
            report.skipped.append({"name": n, "reason": reason})
            warn(f"skipped {n}: {reason}")
        verified = read_verified(db_path)

        # pair rows and track statistics of the verified graph
        rows, inliers = [], []
        for (a, b), r, mm, cached in zip(pairs, results, merged.matches, cached_flags):
            ia, ib = ids.get(a), ids.get(b)
            n_in, conf, inl = 0, "", np.zeros((0, 2), np.uint32)
            if ia is not None and ib is not None:
                key = (min(ia, ib), max(ia, ib))
                if key in verified:
                    n_in, conf, inl = verified[key]
                    if ia > ib:  # COLMAP stores the pair with the smaller id first
                        inl = inl[:, ::-1]
            inliers.append(inl)
            bv = r.best_view
            rows.append(PairRow(
                image0=a, image1=b,
                reference=None if r.reference is None else (a if r.reference == 0 else b),
                best_view=None if bv is None else {"t": bv.t, "phi": bv.phi, "s": bv.s},
                raw_matches=r.num_matches, merged_matches=int(len(mm)), verified_inliers=int(n_in),
                config=conf, cached=bool(cached), seconds=float(r.timings.get("total", 0.0)), reason=r.reason))
        report.pairs = rows
        nk = {n: len(keypoints[n]) for n in scene.names}
        report.tracks = {
            "merged": track_stats(nk, pairs, inliers),
            "unmerged": {"num_tracks": int(sum(len(m) for m in inliers)),
                         "mean_length": 2.0 if any(len(m) for m in inliers) else 0.0,
                         "max_length": 2 if any(len(m) for m in inliers) else 0},
            "raw_merged": track_stats(nk, pairs, merged.matches),
            "note": "connected components of the verified match graph before SfM; 'unmerged' = every "
                    "pair keeps its own keypoints (each match is its own track of length 2)",
        }
        if not any(len(m) for m in inliers):
            warn("no pair passed geometric verification (too few or inconsistent matches)")

        # 5. SfM -------------------------------------------------------------------------------
        from recon.core import sfm

        opts = sfm.mapping_options(cfg.seed, sfm.MAPPING_THREADS, px_scale)
        report.sfm_options = sfm.options_summary(opts)
        sfm_fp = _fingerprint("sfm", db_fp, report.sfm_options)
        model_dir = out / "sparse" / "0"
        rec = None
        with stages("sfm"):
            if state.get("sfm_fingerprint") == sfm_fp and model_dir.is_dir():
                rec = _read_model(model_dir)
                if rec is not None:
                    report.model_reused = True
                    report.num_models = int(state.get("num_models", 1))
                    report.model_sizes = list(state.get("model_sizes", [rec.num_reg_images()]))
                    report.sfm_growth = list(state.get("sfm_growth", []))
            if rec is None:
                adv_sfm = progress.task("sfm", len(scene.images))

                def sfm_step(step: Any, live: Any) -> None:
                    adv_sfm(2 if step.registered_images == 2 else 1)
                    if on_sfm_step is not None:
                        on_sfm_step(step, live)

                res = sfm.run_incremental(db_path, scene.image_dir, opts, on_step=sfm_step)
                adv_sfm(done=True)
                rec = res.reconstruction
                report.num_models, report.model_sizes = res.num_models, res.model_sizes
                report.sfm_growth = res.growth
                if res.hook_error:
                    warn(f"the SfM progress hook failed and was switched off: {res.hook_error}")
                if rec is not None:
                    sfm.write_model_atomic(rec, model_dir)
                    state.update(sfm_fingerprint=sfm_fp, num_models=res.num_models, model_sizes=res.model_sizes,
                                 sfm_growth=res.growth)
                else:
                    state.pop("sfm_fingerprint", None)
                write_json_atomic(state_path, state)

        # 6. export ----------------------------------------------------------------------------
        with stages("export"):
            report.set_model(sfm.model_stats(rec), sfm.registered_names(rec))
            report.num_images = len(scene.images)
            unregistered = [n for n in scene.names if n not in set(report.registered)]
            if rec is not None and unregistered:
                shown = ", ".join(unregistered[:5]) + (" ..." if len(unregistered) > 5 else "")
                warn(f"{len(unregistered)} of {len(scene.names)} images not registered: {shown}")
            ply = out / "points.ply"
            if rec is not None and rec.num_points3D() > 0:
                report.num_points_ply = sfm.write_points_ply(rec, ply, clean=cfg.clean_points)
            else:
                report.status = "no_model"
                n_ok = sum(1 for p in report.pairs if p.verified_inliers > 0)
                report.message = (f"SfM found no model ({n_ok} of {len(pairs)} pairs passed geometric "
                                  f"verification, and incremental mapping could not initialise a model from "
                                  f"them); the database and report are kept in {out}")
                for stale in (model_dir, ply):  # an old model would contradict this report
                    if stale.is_dir():
                        shutil.rmtree(stale, ignore_errors=True)
                    elif stale.exists():
                        stale.unlink()
        report.stages = {k: round(v, 3) for k, v in stages.times.items()}
        report.seconds_total = round(time.perf_counter() - t_start, 3)
        report.peak_mb = round(peak_rss_mb(), 1)
        write_report(report, out / "report.json")
    if on_model is not None:
        on_model(rec, report)
    return report


def _read_model(model_dir: Path):
    import pycolmap

    try:
        rec = pycolmap.Reconstruction()
        rec.read(str(model_dir))
        return rec if rec.num_reg_images() > 0 else None
    except Exception:
        return None


def _match_all(scene: Scene, pairs: list[tuple[str, str]], matcher: PairMatcher, mid: str,
               store: FeatureStore, pair_dir: Path, workers: int, progress: Progress,
               warn: Callable[[str], None],
               on_pair: Callable[[int, str, str, PairResult, bool], None] | None,
               ) -> tuple[list[PairResult], list[bool]]:
    """All pairs, from the cache or computed in parallel; results in pair order."""
    adv = progress.task("match", len(pairs))
    images = {im.name: im for im in scene.images}
    results: list[PairResult | None] = [None] * len(pairs)
    cached = [False] * len(pairs)
    todo: list[int] = []
    paths = [pair_dir / f"{pair_cache_key(mid, images[a], images[b])}.npz" for a, b in pairs]
    for i, (a, b) in enumerate(pairs):
        r = load_pair_result(paths[i])
        if r is not None:
            results[i], cached[i] = r, True
            adv()
            if on_pair is not None:
                on_pair(i, a, b, r, True)
        else:
            todo.append(i)
    if todo:
        pair_dir.mkdir(parents=True, exist_ok=True)
        ex = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="recon-pair")
        futures: dict[Future, int] = {}
        try:
            for i in todo:
                futures[ex.submit(match_pair_task, store, matcher, *pairs[i])] = i
            pending = set(futures)
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in sorted(done, key=lambda f: futures[f]):
                    i = futures[f]
                    a, b = pairs[i]
                    try:
                        raw = f.result()
                    except Exception as e:  # one bad pair must not end the run
                        warn(f"matching {a} / {b} failed: {type(e).__name__}: {e}")
                        results[i] = PairResult.empty(getattr(matcher, "name", "?"),
                                                      f"matcher error: {type(e).__name__}: {e}")
                        adv()
                        continue
                    full = result_to_full_res(raw, images[a], images[b])
                    save_pair_result(paths[i], full)
                    # use exactly what a resumed run would load, so both give identical output
                    results[i] = load_pair_result(paths[i]) or full
                    adv()
                    if on_pair is not None:
                        on_pair(i, a, b, results[i], False)
        except BaseException:
            ex.shutdown(wait=False, cancel_futures=True)
            raise
        ex.shutdown(wait=True)
    return results, cached  # type: ignore[return-value]  (every slot is filled above)
