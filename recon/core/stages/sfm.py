"""Stage `sfm`: incremental mapping of `OUT/database.db` into a sparse model (`recon.core.sfm`).

Needs: `scene`, `image_ids` (and `OUT/database.db`, verified). Makes: `reconstruction`, the
largest model (or None), adjusted once more under a robust loss (`final_bundle_adjustment`,
`report.final_ba`) and written to `OUT/sparse/0` through a temporary folder. Each
registration step is an `on_sfm_step` event (the live model) and a step of the progress bar.

Key: the verify stage's key, every mapper option (pycolmap's `todict()`, which holds the
seed) and the final adjustment's. Reused when unchanged and `sparse/0` can be read; the number
of models, their sizes, the registration order and the final adjustment's summary come back from
the state record (a reused model has no growth events). Options: `sfm.num_threads`,
`sfm.scale_thresholds`, `sfm.final_ba_loss`, `sfm.final_ba_scale_px`,
`sfm.final_ba_outlier_scales`, `sfm.final_ba_principal_point`, `seed`; the mapper's tuned
options are in `recon.core.sfm`.

Before the new model replaces an older one, `report.json` says "incomplete" and the older
`points.ply` goes (`replace_model`): a run stopped between here and the export stage leaves
outputs that agree with each other, not a new model beside the old run's report and points.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import pycolmap

from recon.config import RunConfig
from recon.core import sfm
from recon.core.context import Run
from recon.core.global_sfm import global_options, run_global
from recon.core.global_sfm import options_summary as global_options_summary
from recon.core.report import options_dict, write_report
from recon.core.state import fingerprint

log = logging.getLogger(__name__)


def mapping_options(cfg: RunConfig, px_scale: float, seed: int | None = None) -> pycolmap.IncrementalPipelineOptions:
    """`recon.core.sfm.mapping_options` for this run: seeded (`seed`, default the run's), pixel
    thresholds in full-resolution px, or scaled by the working-to-full-resolution factor
    `px_scale` with `sfm.scale_thresholds`."""
    return sfm.mapping_options(cfg.seed if seed is None else seed, cfg.sfm.num_threads,
                               px_scale if cfg.sfm.scale_thresholds else 1.0,
                               structure_less_fallback=cfg.sfm.structure_less_fallback)


def final_ba_config(cfg: RunConfig, px_scale: float) -> sfm.FinalBaConfig:
    """The final robust adjustment of this run: `sfm.final_ba_loss` / `final_ba_scale_px` /
    `final_ba_outlier_scales`, then the incremental mapper's own filter (its
    `filter_max_reproj_error`, `filter_min_tri_angle`)."""
    m = mapping_options(cfg, px_scale).mapper
    return sfm.FinalBaConfig(loss=cfg.sfm.final_ba_loss, scale_px=float(cfg.sfm.final_ba_scale_px),
                             max_reproj_error_px=float(m.filter_max_reproj_error),
                             min_tri_angle_deg=float(m.filter_min_tri_angle),
                             outlier_scales=float(cfg.sfm.final_ba_outlier_scales),
                             principal_point=cfg.sfm.final_ba_principal_point)


def read_model(model_dir: Path) -> pycolmap.Reconstruction | None:
    """The model in `model_dir`, or None when absent, unreadable or empty."""
    try:
        rec = pycolmap.Reconstruction()
        rec.read(str(model_dir))
        return rec if rec.num_reg_images() > 0 else None
    except Exception:
        return None


class Sfm:
    name = "sfm"
    needs = ("scene", "image_ids")
    makes = ("reconstruction",)

    @staticmethod
    def model_dir(run: Run) -> Path:
        return run.out / "sparse" / "0"

    def key(self, run: Run) -> str | None:
        if run.cfg.sfm.mapper == "global":
            run.report.sfm_options = {"mapper": "global", **global_options_summary(global_options(run.cfg.seed))}
        else:
            run.report.sfm_options = options_dict(mapping_options(run.cfg, run.px_scale()))
            run.report.sfm_options["retries"] = run.cfg.sfm.retries
        run.report.sfm_options["final_ba"] = dataclasses.asdict(final_ba_config(run.cfg, run.px_scale()))
        return fingerprint("sfm", run.keys.get("verify"), run.report.sfm_options)

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        rec = read_model(self.model_dir(run)) if self.model_dir(run).is_dir() else None
        if rec is None:
            return False
        report = run.report
        report.model_reused = True
        report.num_models = int(record.get("num_models", 1))
        report.model_sizes = list(record.get("model_sizes", [rec.num_reg_images()]))
        report.sfm_growth = list(record.get("sfm_growth", []))
        report.sfm_attempts = list(record.get("sfm_attempts", []))
        report.final_ba = dict(record.get("final_ba", {}))
        run.data.reconstruction = rec
        return True

    def run(self, run: Run) -> dict[str, Any] | None:
        advance = run.bar(len(run.data.scene.images))
        report = run.report

        def step(s: sfm.GrowthStep, live: pycolmap.Reconstruction) -> None:
            advance(2 if s.registered_images == 2 else 1)
            run.observer.on_sfm_step(s, live)

        if run.cfg.sfm.mapper == "global":  # GLOMAP: no registration steps to report
            res = run_global(run.db_path, run.image_dir, global_options(run.cfg.seed, run.cfg.sfm.num_threads))
        else:
            px = run.px_scale()
            res, attempts = sfm.map_with_retries(run.db_path, run.image_dir,
                                                 lambda seed: mapping_options(run.cfg, px, seed),
                                                 run.cfg.seed, run.cfg.sfm.retries, on_step=step)
            report.sfm_attempts = attempts
            if len(attempts) > 1:
                chosen = next(a for a in attempts if a["chosen"])
                log.info("mapping retried with seeds %s: kept seed %d (%d images)",
                         [a["seed"] for a in attempts[1:]], chosen["seed"], chosen["registered"])
        advance(done=True)
        rec = res.reconstruction
        report.num_models, report.model_sizes, report.sfm_growth = res.num_models, res.model_sizes, res.growth
        if res.hook_error:
            run.warn(f"the SfM progress hook failed and was switched off: {res.hook_error}")
        if rec is not None:
            fba = final_ba_config(run.cfg, run.px_scale())
            if fba.loss != "none":
                log.info("final bundle adjustment (%s loss) of %d images, %d points", fba.loss,
                         rec.num_reg_images(), rec.num_points3D())
            report.final_ba = sfm.final_bundle_adjustment(rec, fba, run.cfg.sfm.num_threads)
        run.data.reconstruction = rec
        if rec is None:
            return None  # nothing to reuse next time
        replace_model(run, rec, self.model_dir(run))
        return {"num_models": res.num_models, "model_sizes": res.model_sizes, "sfm_growth": res.growth,
                "sfm_attempts": report.sfm_attempts, "final_ba": report.final_ba}


INCOMPLETE_MESSAGE = ("the run stopped after writing the model to sparse/0 and before points.ply and this report; "
                      "run the same command again to finish (its stages are reused)")


def replace_model(run: Run, rec: pycolmap.Reconstruction, model_dir: Path) -> None:
    """Write `rec` to `model_dir` (atomically), first marking `OUT/report.json` "incomplete" and
    removing `OUT/points.ply`: both describe the model being replaced until the export stage
    writes them again, so a run stopped in between must not leave them claiming it."""
    report = run.report
    status, message = report.status, report.message
    report.status, report.message = "incomplete", INCOMPLETE_MESSAGE
    try:
        write_report(report, run.out / "report.json")
    finally:
        report.status, report.message = status, message
    (run.out / "points.ply").unlink(missing_ok=True)
    sfm.write_model_atomic(rec, model_dir)
