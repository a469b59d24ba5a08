"""`export_run(ExportConfig)`: one entry point for every format (see `recon.export`)."""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import pycolmap

from recon.core.jsonio import write_json_atomic
from recon.errors import UserError
from recon.export.colmap import write_colmap_text, write_undistorted
from recon.export.nerfstudio import write_nerfstudio
from recon.export.source import check_photo_sizes, load_source
from recon.export.target import EXPORT_MARKER, check_target, staged

FORMATS: tuple[str, ...] = ("colmap-text", "3dgs", "nerfstudio")


@dataclass
class ExportConfig:
    """Options of `recon export` (the CLI flags one to one), validated on construction."""

    out_dir: Path
    """A `recon run` output folder (holds sparse/0 and .recon_scene.json)."""
    format: str
    """One of FORMATS."""
    to: Path | None = None
    """Destination folder; default OUT_DIR/export/<format>."""
    overwrite: bool = False
    """Replace a previous export in `to` (never a folder that is not an export)."""
    keep_distortion: bool = False
    """nerfstudio only: original photos + OPENCV distortion instead of undistorted PINHOLE."""
    workers: int = 0
    """Threads for undistortion (0 = all cores)."""

    def __post_init__(self) -> None:
        self.out_dir = Path(self.out_dir)
        if self.format not in FORMATS:
            raise UserError(f"--format {self.format!r}: choose one of {', '.join(FORMATS)}")
        if self.keep_distortion and self.format != "nerfstudio":
            raise UserError(f"--keep-distortion applies to --format nerfstudio only "
                            f"({_why_no_distortion(self.format)})")
        if self.workers < 0:
            raise UserError(f"--workers {self.workers}: must be >= 0 (0 = all cores)")
        if self.to is not None:
            self.to = Path(self.to)


@dataclass
class ExportResult:
    """What an export wrote."""

    format: str
    path: Path  # the export folder
    model_dir: Path  # the COLMAP model inside it
    num_images: int  # registered images exported
    camera_models: list[str] = field(default_factory=list)  # COLMAP models of the exported cameras
    num_points3D: int = 0
    warnings: list[str] = field(default_factory=list)  # one line each


def _copy_photos(names: list[str], image_dir: Path, dst: Path) -> None:
    for name in names:
        target = dst / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(image_dir / name, target)


def export_run(cfg: ExportConfig) -> ExportResult:
    """Write `cfg.format` for the run in `cfg.out_dir` (see `recon.export`); UserError for any
    problem a user can fix."""
    src = load_source(cfg.out_dir)
    to = cfg.to if cfg.to is not None else src.out_dir / "export" / cfg.format
    dst = check_target(to, src.out_dir, src.image_dir, cfg.overwrite)
    threads = cfg.workers or -1
    if cfg.format != "colmap-text":  # the formats that read the photos
        check_photo_sizes(src)
    with staged(dst) as stage:
        if cfg.format == "colmap-text":
            model_dir = write_colmap_text(src.rec, stage)
            rec = src.rec
        elif cfg.format == "3dgs":
            model_dir = write_undistorted(src.model_dir, src.image_dir, stage, threads)
            rec = pycolmap.Reconstruction(str(model_dir))
        else:  # nerfstudio, with its model where ns-process-data leaves it: colmap/sparse/0
            model_dir = stage / "colmap" / "sparse" / "0"
            if cfg.keep_distortion:
                _copy_photos(src.registered_names, src.image_dir, stage / "images")
                model_dir.mkdir(parents=True)
                src.rec.write(str(model_dir))
            else:
                undistorted = write_undistorted(src.model_dir, src.image_dir, stage, threads)
                model_dir.parent.mkdir(parents=True)
                os.replace(undistorted, model_dir)
                (stage / "sparse").rmdir()
            rec = pycolmap.Reconstruction(str(model_dir))
            write_nerfstudio(rec, stage)
        models = sorted({rec.camera(rec.image(i).camera_id).model.name for i in rec.reg_image_ids()})
        write_json_atomic(stage / EXPORT_MARKER, {
            "format": cfg.format, "run": str(src.out_dir), "image_dir": str(src.image_dir),
            "undistorted": cfg.format != "colmap-text" and not cfg.keep_distortion,
            "num_images": int(rec.num_reg_images()), "camera_models": models})
        rel_model = model_dir.relative_to(stage)
    warnings = []
    spaced = [n for n in src.registered_names if any(c.isspace() for c in n)]
    if cfg.format == "colmap-text" and spaced:
        warnings.append(f"COLMAP's text format ends an image name at its first space, so readers will cut "
                        f"{len(spaced)} name(s) such as {spaced[0]!r}; the binary model {src.model_dir} keeps them")
    return ExportResult(cfg.format, dst, dst / rel_model, int(rec.num_reg_images()), models,
                        int(rec.num_points3D()), warnings)


def _why_no_distortion(fmt: str) -> str:
    if fmt == "colmap-text":
        return "the model is written as it is"
    return "Gaussian-splatting trainers need undistorted PINHOLE images"
