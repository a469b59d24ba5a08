"""The orchestrator: runs a list of stages in order and owns resume, timing, progress and events.

A stage (`Stage`) is a small object with a `name`, the `RunData` fields it `needs` and `makes`,
and three methods:

* `key(run) -> str | None`: a fingerprint of everything its output depends on (its options and
  its inputs, including the upstream stage's key); None for stages that always run (they are
  cheap, or resume item by item like the pair cache);
* `run(run) -> dict | None`: compute the outputs; the returned record (small JSON: what later
  stages need, e.g. image ids) is kept in `OUT/cache/state.json` with the key, None keeps nothing;
* `reuse(run, record) -> bool`: restore the outputs of an earlier run built with the same key
  (from disk and the record); False when they are gone, and the stage runs.

For each stage, `run_stages` emits `on_stage_start`, reuses or runs it, records its seconds in
`report.stages` (reused ones also in `report.stages_reused`) and emits `on_stage_end`. Around
all stages: the progress bars (`run.bar`), COLMAP's log level (`recon.log.quiet_colmap`), the
peak memory (`report.peak_mb`), the pair executor (shut down, cancelling on an error), and at
the end `OUT/report.json` and `on_model`. `recon run` and the stock comparison
(`recon.eval.stock.run_stock`) are this function with different stage lists.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any, Protocol

from matching.memory import RUN_INTERVAL_S, PeakRss, peak_rss_mb
from recon.core.context import Run
from recon.core.report import RunReport, write_report
from recon.log import quiet_colmap

log = logging.getLogger(__name__)


class Stage(Protocol):
    name: str
    needs: tuple[str, ...]  # RunData fields read
    makes: tuple[str, ...]  # RunData fields written

    def key(self, run: Run) -> str | None: ...

    def run(self, run: Run) -> dict[str, Any] | None: ...

    def reuse(self, run: Run, record: dict[str, Any]) -> bool: ...


def run_stages(run: Run, stages: Sequence[Stage]) -> RunReport:
    """Run `stages` in order (see module doc); returns the report, also written to OUT/report.json."""
    t_start = time.perf_counter()
    report = run.report
    failed = True
    with PeakRss(RUN_INTERVAL_S) as mem, run.progress, quiet_colmap():
        try:
            for stage in stages:
                _one(run, stage)
            failed = False
        finally:
            run.close_executor(cancel=failed)
        report.seconds_total = round(time.perf_counter() - t_start, 3)
        report.peak_mb = round(mem.total_mb or peak_rss_mb(), 1)
        report.peak_growth_mb = None if mem.peak_mb is None else round(mem.peak_mb, 1)
        write_report(report, run.out / "report.json")
    run.observer.on_model(run.data.reconstruction, report)
    return report


def _one(run: Run, stage: Stage) -> None:
    t0 = time.perf_counter()
    run.stage = stage.name
    run.observer.on_stage_start(stage.name)
    key = stage.key(run)
    record = None
    if key is not None:
        run.keys[stage.name] = key
        record = run.state.record(stage.name, key)
    reused = record is not None and stage.reuse(run, record)
    if not reused:
        if key is not None:
            run.state.forget(stage.name)
        record = stage.run(run)
        if key is not None and record is not None:
            run.state.put(stage.name, key, record)
    seconds = time.perf_counter() - t0
    run.report.stages[stage.name] = round(seconds, 3)
    if reused:
        run.report.stages_reused.append(stage.name)
    log.debug("stage %s: %.2f s%s", stage.name, seconds, " (reused)" if reused else "")
    run.observer.on_stage_end(stage.name, seconds, reused)
