"""`recon export OUT_DIR --format colmap-text|3dgs|nerfstudio`: the model for the next tool (see `recon.export`)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from recon.cli.options import flag, workers_option


class ExportFormat(str, Enum):
    """The formats of `recon.export.FORMATS` (an Enum so --help lists them)."""

    colmap_text = "colmap-text"
    gaussian_splatting = "3dgs"
    nerfstudio = "nerfstudio"


NEXT_STEP = {
    "colmap-text": "the text model is in {model}",
    "3dgs": "train Gaussian splatting with e.g. `python train.py -s {path}` (graphdeco gaussian-splatting) "
            "or gsplat's `simple_trainer.py default --data_dir {path} --data_factor 1`",
    "nerfstudio": "train with e.g. `ns-train splatfacto --data {path}` or `ns-train nerfacto --data {path}`",
}


def register(app: typer.Typer) -> None:
    @app.command("export")
    def export(
        out_dir: Annotated[Path, typer.Argument(help="A `recon run` output folder (holds sparse/0).",
                                                metavar="OUT_DIR")],
        format: Annotated[ExportFormat, typer.Option(
            "--format", "-f", help="colmap-text: the model as COLMAP text (sparse/0/*.txt); 3dgs: undistorted "
                                   "images/ + sparse/0 with PINHOLE cameras (Gaussian splatting); nerfstudio: "
                                   "transforms.json + images/ + sparse_pc.ply.")],
        to: Annotated[Optional[Path], typer.Option("--to", help="Destination folder (default: OUT_DIR/export/FORMAT).")] = None,
        overwrite: Annotated[bool, flag("--overwrite", help="Replace a previous export in --to.")] = False,
        keep_distortion: Annotated[bool, flag(
            "--keep-distortion", help="nerfstudio only: copy the original photos and write their distortion "
                                      "(OPENCV k1, k2, p1, p2) instead of undistorted PINHOLE images.")] = False,
        workers: Annotated[int, workers_option("Threads for undistortion (0 = all cores).")] = 0,
    ) -> None:
        """Export a reconstruction for Gaussian splatting, nerfstudio or COLMAP's text format."""
        import sys

        from recon.export import ExportConfig, export_run

        res = export_run(ExportConfig(out_dir=out_dir, format=format.value, to=to, overwrite=overwrite,
                                      keep_distortion=keep_distortion, workers=workers))
        for w in res.warnings:
            print(f"recon: warning: {w}", file=sys.stderr)
        print(f"recon: {res.format} export of {res.num_images} images ({', '.join(res.camera_models)} "
              f"cameras, {res.num_points3D} points) in {res.path}", file=sys.stderr)
        print("recon: " + NEXT_STEP[res.format].format(path=res.path, model=res.model_dir), file=sys.stderr)
