"""What a run's stages share: `Run` (options, folders, report, events, progress, executor) and
`RunData` (what each stage hands the next).

A stage reads its inputs from `run.data` and writes its outputs there; each `RunData` field
names the stage that makes it, and each stage lists what it `needs` and `makes` (the
orchestrator checks the latter), so the data flow is written down once, here and in the stages.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from recon.config import RunConfig
from recon.core.engine import make_executor
from recon.core.observer import CompositeObserver
from recon.core.progress import Progress
from recon.core.report import RunReport
from recon.core.state import StageState
from recon.log import console

log = logging.getLogger(__name__)


@dataclass
class RunData:
    """The stages' outputs. Keypoints are full-resolution pixels, OpenCV convention."""

    scene: Any = None  # load: recon.core.scene.Scene (usable images, skipped ones)
    grays: dict[str, NDArray[np.uint8]] | None = None  # load: working-resolution gray images (features frees them)
    store: Any = None  # features: matching.store.FeatureStore over every usable image
    pairs: list[tuple[str, str]] = field(default_factory=list)  # pairs: the image pairs, in order
    results: list[Any] = field(default_factory=list)  # match: one PairResult per pair (pair order)
    cached: list[bool] = field(default_factory=list)  # match: loaded from the pair cache
    merged: Any = None  # tracks: recon.core.tracks.MergedTracks (per-pair matches into merged keypoints)
    keypoints: dict[str, NDArray[np.float32]] = field(default_factory=dict)  # tracks: merged keypoints per image
    image_ids: dict[str, int] = field(default_factory=dict)  # database: COLMAP image id per name
    num_keypoints: dict[str, int] = field(default_factory=dict)  # database (stock: match): keypoints per image
    verified: dict[tuple[int, int], Any] = field(default_factory=dict)  # verify (stock: match): read_verified()
    reconstruction: Any = None  # sfm: the kept pycolmap.Reconstruction, or None


class Run:
    """One run: what every stage may use besides `data`."""

    def __init__(self, cfg: RunConfig, root: Path, out: Path, report: RunReport, observer: CompositeObserver,
                 state: StageState, matcher: Any = None) -> None:
        self.cfg = cfg
        self.root = root  # the scene folder
        self.out = out  # the output folder (checked and claimed before the run)
        self.report = report
        self.observer = observer
        self.state = state  # OUT/cache/state.json, or nothing (no resuming)
        self.matcher = matcher  # a caller's matcher in place of cfg.match (tests, comparisons)
        self.data = RunData()
        self.keys: dict[str, str] = {}  # stage name -> its key in this run (later keys include earlier ones)
        self.stage = ""  # the stage running now
        self.progress = Progress(cfg.output.progress)
        self._executor: Executor | None = None

    # folders ------------------------------------------------------------------------------------
    @property
    def db_path(self) -> Path:
        return self.out / "database.db"

    @property
    def cache(self) -> Path:
        return self.out / "cache"

    @property
    def image_dir(self) -> Path:
        return self.data.scene.image_dir

    # shared helpers -----------------------------------------------------------------------------
    def px_scale(self) -> float:
        """Working-to-full-resolution factor (mean over the images in the database, else all):
        pixel thresholds of COLMAP scale with it, since the matcher localises to a working px."""
        ims = [im for im in self.data.scene.images if not self.data.image_ids or im.name in self.data.image_ids]
        return float(np.mean([1.0 / min(im.scale_xy) for im in ims]))

    def warn(self, message: str) -> None:
        """A one-line warning: into the report, the log (`recon: warning: ...`) and the observers."""
        self.report.warnings.append(message)
        log.warning(message)
        self.observer.on_warning(message)

    def bar(self, total: int | None, part: str = "") -> Callable[..., None]:
        """A progress bar for the current stage (`part` names a part of it, e.g. a pass):
        `advance(n=1)`, `advance(done=True)`."""
        return self.progress.task(f"{self.stage} ({part})" if part else self.stage, total)

    @property
    def executor(self) -> Executor:
        """The pair tasks' executor (`cfg.match.engine`, `cfg.workers`), created on first use."""
        if self._executor is None:
            self._executor = make_executor(self.cfg.match.engine, self.cfg.num_workers)
            link = getattr(self._executor, "dashboard_link", None)
            if link:
                console().print(f"recon: Dask dashboard: {link}", markup=False, highlight=False)
        return self._executor

    def close_executor(self, cancel: bool) -> None:
        """Shut the executor down: waiting for its tasks, or not (`cancel`: after an error or
        Ctrl-C; the match stage has cancelled what had not started)."""
        ex, self._executor = self._executor, None
        if ex is not None:
            ex.shutdown(wait=not cancel)  # only the plain Executor API: any engine's executor fits
