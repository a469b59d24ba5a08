"""Stage `export`: the model's headline numbers, `points.ply`, and the run's status.

Needs: `scene`, `reconstruction`. Makes: nothing in `RunData`: the report's model numbers,
`OUT/points.ply` (open3d; `output.clean_points` drops statistical outliers) and the status. A
run without a model (or without 3D points) is not an error: status "no_model" with a message
saying how many pairs passed verification, and any older model and points.ply in OUT are
deleted so they cannot contradict the report. Key: none, it always runs.
"""

from __future__ import annotations

import shutil
from typing import Any

from recon.core import sfm
from recon.core.context import Run
from recon.core.stages.sfm import Sfm


class Export:
    name = "export"
    needs = ("scene", "reconstruction")
    makes: tuple[str, ...] = ()

    def __init__(self, ply: bool = True, who: str = "SfM") -> None:
        self.ply = ply  # write points.ply (the stock comparison does not)
        self.who = who  # names the pipeline in the no-model message

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        report, rec, names = run.report, run.data.reconstruction, run.data.scene.names
        report.set_model(sfm.model_stats(rec), sfm.registered_names(rec))
        report.set_pair_summary()
        unregistered = [n for n in names if n not in set(report.registered)]
        if rec is not None and unregistered:
            shown = ", ".join(unregistered[:5]) + (" ..." if len(unregistered) > 5 else "")
            run.warn(f"{len(unregistered)} of {len(names)} images not registered: {shown}")
        ply = run.out / "points.ply"
        if rec is not None and rec.num_points3D() > 0:
            if self.ply:
                report.num_points_ply = sfm.write_points_ply(rec, ply, clean=run.cfg.output.clean_points)
            return None
        report.status = "no_model"
        report.message = (f"{self.who} found no model ({report.verified_pairs} of {len(report.pairs)} pairs passed "
                          f"geometric verification, and incremental mapping could not initialise a model from "
                          f"them); the database and report are kept in {run.out}")
        for stale in (Sfm.model_dir(run), ply):  # an old model would contradict this report
            if stale.is_dir():
                shutil.rmtree(stale, ignore_errors=True)
            elif stale.exists():
                stale.unlink()
        return None
