"""`recon compare SCENE_DIR`: the extra-affine pipeline against COLMAP's stock matching (see
`recon.eval.compare`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from recon.cli.options import (
    deprecated_stock_preset_option,
    our_settings,
    progress_option,
    seed_option,
    set_option,
    simulate_option,
    stock_presets,
    stock_presets_option,
    workers_option,
)
from recon.config import DEFAULT_MAX_SIZE, build_run_config


def register(app: typer.Typer) -> None:
    @app.command("compare")
    def compare(
        scene_dir: Annotated[Path, typer.Argument(help="Scene folder: photos in SCENE_DIR/images/ or SCENE_DIR, "
                                                       "optional ground truth in SCENE_DIR/gt/.", metavar="SCENE_DIR")],
        out: Annotated[Optional[Path], typer.Option(
            "--out", help="Output folder (default: SCENE_DIR/compare): stock-<preset>/, extra_affine/, "
                          "compare.json.")] = None,
        stock_presets_: Annotated[str, stock_presets_option()] = "default",
        stock_preset: Annotated[Optional[str], deprecated_stock_preset_option()] = None,
        max_size: Annotated[int, typer.Option("--max-size", help="Working resolution of both pipelines "
                                                                 "(longer side, px; 0 = full).")] = DEFAULT_MAX_SIZE,
        pairs: Annotated[str, typer.Option("--pairs", help="exhaustive, sequential:K, or a file of name pairs.")]
            = "exhaustive",
        simulate: Annotated[str, simulate_option()] = "auto",
        settings: Annotated[Optional[list[str]], set_option()] = None,
        seed: Annotated[int, seed_option()] = 0,
        workers: Annotated[int, workers_option()] = 0,
        progress: Annotated[bool, progress_option()] = True,
        rerun: Annotated[str, typer.Option(
            "--rerun", help="Rerun sink for both models in one frame: save[:PATH] (default: OUT/compare.rrd), "
                            "spawn, connect[:URL] or none.")] = "save",
    ) -> None:
        """Run stock COLMAP and the extra-affine pipeline on the same images and pairs, and compare them."""
        import sys

        from rich.console import Console

        from recon.core.outdir import claim_output
        from recon.core.pipeline import RunConfig
        from recon.core.scene import require_images
        from recon.errors import UserError
        from recon.eval.compare import compare_scene, compare_table, load_gt
        from recon.viz.compare_rerun import COMPARE_RECORDING, log_comparison
        from recon.viz.rerun_log import find_viewer, parse_sink

        presets = stock_presets(stock_presets_, stock_preset)
        RunConfig.from_options(max_size=max_size, pairs=pairs, seed=seed)  # validates the shared options (UserError)
        ours = our_settings(simulate, settings)
        build_run_config(settings=ours)  # --simulate and --set checked before anything is created (UserError)
        require_images(scene_dir.expanduser())  # before anything is created
        out_dir = (out or scene_dir / "compare").expanduser().absolute()
        try:
            sink = parse_sink(rerun, out_dir / COMPARE_RECORDING)
        except ValueError as e:
            raise UserError(str(e)) from None
        if sink.kind == "spawn" and find_viewer() is None:
            raise UserError("--rerun spawn: the Rerun viewer (`rerun`) is not installed; use --rerun save")
        err = Console(stderr=True, highlight=False)
        with claim_output(out_dir, "compare", default_out=out is None, legacy=("compare.json",)) as out_dir:
            res = compare_scene(scene_dir, out_dir, presets=presets, max_size=max_size, pairs=pairs, seed=seed,
                                workers=workers, progress=progress, log=lambda m: err.print(f"recon: {m}", markup=False),
                                settings=ours,
                                on_warning=lambda m: print(f"recon: warning: {m}", file=sys.stderr))
            console = Console(width=None if sys.stdout.isatty() else 140)
            console.print(compare_table(res))
            console.print(f"JSON: {Path(res['out']) / 'compare.json'}")
            if sink.enabled:
                gt, _, _ = load_gt(Path(res["scene"]))
                try:
                    saved = log_comparison(sink, res, gt)
                except Exception as e:  # compare.json and both models are written: report, do not crash
                    print(f"recon: warning: the Rerun recording failed ({type(e).__name__}: {e}); "
                          f"the comparison is complete in {Path(res['out']) / 'compare.json'}", file=sys.stderr)
                    saved = None
                if saved is not None:
                    print(f"recon: Rerun recording {saved} ({saved.stat().st_size / 1e6:.1f} MB); "
                          f"open it with: recon view {saved}", file=sys.stderr)
