"""`recon run SCENE_DIR`: photos to a COLMAP sparse model (see `recon.pipeline`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from matching.registry import METHODS


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
        seed: Annotated[int, typer.Option("--seed", help="Seed for the matcher and COLMAP's RANSAC.")] = 0,
        workers: Annotated[int, typer.Option("--workers", help="Parallel pair tasks (0 = all cores).")] = 0,
        overwrite: Annotated[bool, typer.Option("--overwrite", help="Delete this tool's outputs in --out and start over.")] = False,
        clean_points: Annotated[bool, typer.Option("--clean-points", help="Drop statistical outliers from points.ply.")] = False,
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bars on stderr.")] = True,
    ) -> None:
        """Match the photos of a scene, write a COLMAP database and reconstruct a sparse model."""
        import sys

        from rich.console import Console

        from .pipeline import RunConfig, run_scene
        from .report import summary_table

        cfg = RunConfig(out=out, method=method, pairs=pairs, max_size=max_size, camera_mode=camera_mode,
                        merge_px=merge_px, seed=seed, workers=workers, overwrite=overwrite,
                        clean_points=clean_points, progress=progress)
        try:
            report = run_scene(scene_dir, cfg,
                               on_warning=lambda m: print(f"recon: warning: {m}", file=sys.stderr))
        except KeyboardInterrupt:
            # typer turns Ctrl-C into a *returned* exit code that `recon.cli.main` does not
            # look at; SystemExit reaches it. Everything written so far is complete (atomic).
            print("recon: interrupted; rerun the same command to resume", file=sys.stderr)
            raise SystemExit(130) from None
        Console().print(summary_table(report))
        if not report.ok:
            print(f"recon: error: {report.message}", file=sys.stderr)
            # SystemExit, not typer.Exit: click (standalone_mode=False) would turn Exit into a
            # return value that `recon.cli.main` does not look at
            raise SystemExit(1)
