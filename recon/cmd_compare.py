"""`recon compare SCENE_DIR`: the extra-affine pipeline against COLMAP's stock matching (see
`recon.compare`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("compare")
    def compare(
        scene_dir: Annotated[Path, typer.Argument(help="Scene folder: photos in SCENE_DIR/images/ or SCENE_DIR, "
                                                       "optional ground truth in SCENE_DIR/gt/.")],
        out: Annotated[Optional[Path], typer.Option(
            "--out", help="Output folder (default: SCENE_DIR/compare): stock-<preset>/, extra_affine/, "
                          "compare.json.")] = None,
        stock_preset: Annotated[str, typer.Option(
            "--stock-preset", help="Stock COLMAP preset: default or high (comma-separated for several).")] = "default",
        max_size: Annotated[int, typer.Option("--max-size", help="Working resolution of both pipelines "
                                                                 "(longer side, px; 0 = full).")] = 1600,
        pairs: Annotated[str, typer.Option("--pairs", help="exhaustive, sequential:K, or a file of name pairs.")]
            = "exhaustive",
        seed: Annotated[int, typer.Option("--seed", help="Seed for the matcher and COLMAP's RANSAC.")] = 0,
        progress: Annotated[bool, typer.Option("--progress/--no-progress",
                                               help="recon run's progress bars on stderr.")] = False,
    ) -> None:
        """Run stock COLMAP and the extra-affine pipeline on the same images and pairs, and compare them."""
        import sys

        from rich.console import Console

        from .compare import compare_scene, compare_table

        presets = [p.strip() for p in stock_preset.split(",") if p.strip()]
        err = Console(stderr=True, highlight=False)
        res = compare_scene(scene_dir, out, presets=presets, max_size=max_size, pairs=pairs, seed=seed,
                            progress=progress, log=lambda m: err.print(f"recon: {m}", markup=False),
                            on_warning=lambda m: print(f"recon: warning: {m}", file=sys.stderr))
        console = Console(width=None if sys.stdout.isatty() else 140)
        console.print(compare_table(res))
        console.print(f"JSON: {Path(res['out']) / 'compare.json'}")
