"""`recon run SCENE_DIR`: photos to a COLMAP sparse model (see `recon.core.pipeline`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from matching.registry import METHODS
from recon.cli._options import SEED_MAX


def register(app: typer.Typer) -> None:
    @app.command("run")
    def run(
        scene_dir: Annotated[Path, typer.Argument(help="Scene folder: photos in SCENE_DIR/images/ or SCENE_DIR.")],
        out: Annotated[Optional[Path], typer.Option("--out", help="Output folder (default: SCENE_DIR/recon).")] = None,
        method: Annotated[str, typer.Option("--method", help=f"Pair matcher: {', '.join(METHODS)}.")] = "extra-affine",
        pairs: Annotated[str, typer.Option("--pairs", help="exhaustive, sequential:K, or a file of name pairs.")] = "exhaustive",
        max_size: Annotated[int, typer.Option("--max-size", help="Working resolution for matching (longer side, px; 0 = full).")] = 1600,
        camera_mode: Annotated[str, typer.Option("--camera-mode", help="auto, single or per-image.")] = "auto",
        merge_px: Annotated[float, typer.Option("--merge-px", help="Keypoint merge radius in working px (0 = no merging).")] = 2.0,
        seed: Annotated[int, typer.Option("--seed", min=0, max=SEED_MAX,
                                          help="Seed for the matcher and COLMAP's RANSAC.")] = 0,
        workers: Annotated[int, typer.Option("--workers", help="Parallel pair tasks (0 = all cores).")] = 0,
        overwrite: Annotated[bool, typer.Option("--overwrite", help="Delete this tool's outputs in --out and start over "
                                                                    "(the content-addressed match cache is kept).")] = False,
        clean_cache: Annotated[bool, typer.Option("--clean-cache", help="Also delete the cached features and pair "
                                                                        "matches in --out.")] = False,
        clean_points: Annotated[bool, typer.Option("--clean-points", help="Drop statistical outliers from points.ply.")] = False,
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bars on stderr.")] = True,
        rerun: Annotated[str, typer.Option(
            "--rerun", help="Rerun recording: save (OUT/recording.rrd, default), save:PATH, spawn (open the "
                            "viewer), connect[:URL] (stream to a running viewer) or none.")] = "save",
    ) -> None:
        """Match the photos of a scene, write a COLMAP database and reconstruct a sparse model."""
        import sys

        from rich.console import Console

        from recon.errors import UserError
        from recon.core.outdir import claim_output, clean_content_cache
        from recon.core.pairs import check_pairs_names
        from recon.core.pipeline import RunConfig, run_scene
        from recon.core.report import summary_table
        from recon.viz.rerun_log import RECORDING_NAME, RerunLogger, find_viewer, parse_sink
        from recon.core.scene import require_images

        cfg = RunConfig(out=out, method=method, pairs=pairs, max_size=max_size, camera_mode=camera_mode,
                        merge_px=merge_px, seed=seed, workers=workers, overwrite=overwrite,
                        clean_points=clean_points, progress=progress)
        # the same output folder run_scene uses; the logger opens its sink lazily, after
        # run_scene has checked and claimed the folder
        out_dir = (cfg.out or scene_dir.expanduser() / "recon").absolute()
        try:
            sink = parse_sink(rerun, out_dir / RECORDING_NAME)
        except ValueError as e:
            raise UserError(str(e)) from None
        if sink.kind == "spawn" and find_viewer() is None:
            raise UserError("--rerun spawn: the Rerun viewer (`rerun`) is not installed; "
                            "use --rerun save and open the file elsewhere")
        # the inputs first (no image decoded, nothing created): scene folder, image files, pairs file
        image_dir, candidates = require_images(scene_dir.expanduser())
        check_pairs_names(cfg.pairs_spec, candidates)
        image_dir = image_dir.resolve()
        logger = RerunLogger(sink, lambda name: image_dir / name) if sink.enabled else None
        ok = False
        # one run per output folder (OUT/.recon.lock); a foreign folder is refused before anything is written
        with claim_output(out_dir, "run", default_out=out is None, marker=False):
            if clean_cache:
                clean_content_cache(out_dir)
            try:
                report = run_scene(scene_dir, cfg,
                                   on_pair=logger.on_pair if logger else None,
                                   on_model=logger.on_model if logger else None,
                                   on_sfm_step=logger.on_sfm_step if logger else None,
                                   on_warning=lambda m: print(f"recon: warning: {m}", file=sys.stderr))
                ok = True
            finally:  # Ctrl-C too: `recon.cli.main` prints the one line and the exit code
                saved = logger.close(ok) if logger else None
        stale = out_dir / RECORDING_NAME
        if overwrite and saved != stale and stale.is_file():  # --overwrite: no recording of an older run
            stale.unlink()
        Console().print(summary_table(report))
        if saved is not None:
            print(f"recon: Rerun recording {saved} ({saved.stat().st_size / 1e6:.1f} MB); "
                  f"open it with: recon view {saved}", file=sys.stderr)
        if not report.ok:
            print(f"recon: error: {report.message}", file=sys.stderr)
            # SystemExit, not typer.Exit: click (standalone_mode=False) would turn Exit into a
            # return value that `recon.cli.main` does not look at
            raise SystemExit(1)
