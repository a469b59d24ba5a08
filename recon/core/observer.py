"""One observer protocol for the events of a run: stages, pairs, SfM steps, the model, warnings.

`run_scene` / `run_stock` take `observer=` (one `RunObserver` or a sequence of them). Every
method is optional: subclass `BaseRunObserver` and override what you need (the Rerun logger,
`recon.viz.rerun_log.RerunLogger`, does so). Events arrive in this order, on the calling thread:

    on_stage_start(name) ... on_stage_end(name, seconds, reused)   for each stage in order,
        with on_pair(...) inside the match stage, once per pair (cached pairs first, in pair
        order, then computed ones as they finish; `index` is the pair's place in the pair list)
        and on_sfm_step(...) inside sfm, one per registration step;
    on_warning(message) whenever a warning is raised (also in the report and the log);
    on_model(reconstruction_or_None, report) once, last, after report.json is written.

An exception from `on_sfm_step` switches that hook off (one warning; mapping goes on); other
hooks are the observer's own responsibility (RerunLogger never raises).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from matching.types import PairResult
    from recon.core.report import RunReport
    from recon.core.sfm import GrowthStep


@runtime_checkable
class RunObserver(Protocol):
    def on_stage_start(self, stage: str) -> None:
        """A stage begins (`load`, `features`, `pairs`, `match`, `tracks`, `database`, ...)."""

    def on_stage_end(self, stage: str, seconds: float, reused: bool) -> None:
        """A stage ended after `seconds`; `reused`: skipped, its outputs reused from an earlier run."""

    def on_pair(self, index: int, name0: str, name1: str, result: PairResult, cached: bool) -> None:
        """Pair `index` (pair order) matched, or loaded from the pair cache (`cached`); keypoints
        in full-resolution pixels."""

    def on_sfm_step(self, step: GrowthStep, live: Any) -> None:
        """One registration step of incremental mapping; `live` is the model being built
        (read it now: it changes afterwards). Not called when an unchanged model is reused."""

    def on_model(self, model: Any, report: RunReport) -> None:
        """The end: the kept `pycolmap.Reconstruction` (or None) and the final report."""

    def on_warning(self, message: str) -> None:
        """A one-line warning (the user sees it as `recon: warning: ...`)."""


class BaseRunObserver:
    """Every RunObserver method as a no-op: subclass and override what you need."""

    def on_stage_start(self, stage: str) -> None:
        pass

    def on_stage_end(self, stage: str, seconds: float, reused: bool) -> None:
        pass

    def on_pair(self, index: int, name0: str, name1: str, result: PairResult, cached: bool) -> None:
        pass

    def on_sfm_step(self, step: GrowthStep, live: Any) -> None:
        pass

    def on_model(self, model: Any, report: RunReport) -> None:
        pass

    def on_warning(self, message: str) -> None:
        pass


class CompositeObserver(BaseRunObserver):
    """Several observers as one: each event goes to each, in order."""

    def __init__(self, observers: Sequence[RunObserver] = ()) -> None:
        self.observers = list(observers)

    def on_stage_start(self, stage: str) -> None:
        for o in self.observers:
            o.on_stage_start(stage)

    def on_stage_end(self, stage: str, seconds: float, reused: bool) -> None:
        for o in self.observers:
            o.on_stage_end(stage, seconds, reused)

    def on_pair(self, index: int, name0: str, name1: str, result: PairResult, cached: bool) -> None:
        for o in self.observers:
            o.on_pair(index, name0, name1, result, cached)

    def on_sfm_step(self, step: GrowthStep, live: Any) -> None:
        for o in self.observers:
            o.on_sfm_step(step, live)

    def on_model(self, model: Any, report: RunReport) -> None:
        for o in self.observers:
            o.on_model(model, report)

    def on_warning(self, message: str) -> None:
        for o in self.observers:
            o.on_warning(message)


def as_observer(observer: RunObserver | Sequence[RunObserver] | None) -> CompositeObserver:
    """None, one observer or several -> one CompositeObserver."""
    if observer is None:
        return CompositeObserver()
    if isinstance(observer, CompositeObserver):
        return observer
    if isinstance(observer, Sequence):
        return CompositeObserver(observer)
    return CompositeObserver([observer])
