"""`run_scene`: photos -> pair matches -> merged tracks -> COLMAP database -> SfM -> outputs.

The work is done by named stages (`recon.core.stages`: load, features, pairs, match, tracks,
database, verify, sfm, export), run in order by `recon.core.orchestrator.run_stages`, which
owns resuming, timing, progress and events. This module only checks the input and the output
folder before anything is written, and picks the stages.

Resuming: features and pair results are cached per item; the database, the verified database
and the model are reused when `OUT/cache/state.json` records that they were built with the same
key (a fingerprint of their inputs and options, see `recon.core.state`). `--overwrite` deletes
everything the pipeline wrote (never other files) and starts over. The output folder is tied
to its scene by `OUT/.recon_scene.json` (scene path + image file names); a different scene is
refused (`recon.core.outdir`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from matching.registry import PairMatcher
from recon.config import RunConfig
from recon.core.context import Run
from recon.core.observer import RunObserver, as_observer
from recon.core.orchestrator import run_stages
from recon.core.outdir import output_lock, prepare_out
from recon.core.pairs import check_pairs_names, parse_pairs_spec
from recon.core.report import RunReport
from recon.core.scene import require_images
from recon.core.stages import scene_stages
from recon.core.stages.match import make_matcher, match_pair_task, matcher_identity
from recon.core.state import StageState

__all__ = ["RunConfig", "make_matcher", "match_pair_task", "matcher_identity", "run_scene"]


def run_scene(scene_dir: str | Path, cfg: RunConfig | None = None, *, matcher: PairMatcher | None = None,
              observer: RunObserver | Sequence[RunObserver] | None = None) -> RunReport:
    """Reconstruct a scene folder; returns the report (also written to OUT/report.json).

    `matcher` replaces the one `cfg.match` describes (tests, comparisons). `observer` (one or
    several `recon.core.observer.RunObserver`s) receives the run's events: stages, pairs, SfM
    steps, warnings, the model. Raises InputError / UserError for unusable input or options; a
    scene without a model is not an error here: the report has status "no_model" (the CLI
    exits 1).
    """
    cfg = cfg or RunConfig()
    root = Path(scene_dir).expanduser()
    # the inputs first (no image decoded, nothing written): scene folder, image files, pairs file
    image_dir, candidates = require_images(root)  # InputError / UserError
    check_pairs_names(parse_pairs_spec(cfg.pairs.spec), candidates)
    root, image_dir = root.resolve(), image_dir.resolve()
    out = (cfg.output.out or root / "recon").resolve()
    notes = prepare_out(out, root, candidates, cfg.output.overwrite, default_out=cfg.output.out is None,
                        clean_cache=cfg.output.overwrite and not cfg.output.keep_cache)
    report = RunReport(scene=str(root), out=str(out), config=cfg.to_dict(),
                       method=getattr(matcher, "name", "") if matcher is not None else cfg.match.method)
    run = Run(cfg, root, out, report, as_observer(observer), StageState(out / "cache" / "state.json"), matcher)
    for note in notes:
        run.warn(note)
    with output_lock(out):  # one run per output folder (re-entrant inside the CLI's own lock)
        report = run_stages(run, scene_stages())
    if report.ok and not cfg.output.keep_cache:
        clean_cache(out)
    return report


def clean_cache(out: Path) -> None:
    """`--clean-cache`: delete OUT/cache after a successful run (the next run starts from scratch;
    the outputs, database.db, sparse/, points.ply and report.json, stay)."""
    import shutil

    shutil.rmtree(out / "cache", ignore_errors=True)
