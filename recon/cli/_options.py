"""Option checks shared by the commands, run by click while it parses (before any work).

A bad value raises `UserError`, which `recon.cli.main` prints on one line with exit 2. Used as
typer `callback=`s, so a reader sees the check next to the option.
"""

from __future__ import annotations

import os
from pathlib import Path

from recon.errors import UserError

SEED_MAX = 2**31 - 1  # COLMAP's and OpenCV's RANSAC seeds are 32-bit signed integers


def check_output_file(path: Path, option: str, *, image: bool = False) -> Path:
    """UserError unless `path` can be written as a regular file (parent folders may be created).

    Refused: an existing folder, a path through a file (`FILE/x.json`), a read-only folder, an
    existing special file (a device, a FIFO: an atomic rename would replace it), and with
    `image` an extension OpenCV cannot write (`.xyz`).
    """
    p = Path(path).expanduser()
    if p.is_dir():
        raise UserError(f"{option} {path}: is a folder, expected a file name")
    if p.exists() and not p.is_file():
        raise UserError(f"{option} {path}: exists and is not a regular file")
    probe = p.parent
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise UserError(f"{option} {path}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UserError(f"{option} {path}: {probe} is read-only")
    if image:
        import cv2

        ext = p.suffix.lower()
        if not ext or not cv2.haveImageWriter(f"x{ext}"):
            raise UserError(f"{option} {path}: OpenCV cannot write {ext or 'a file without extension'} images; "
                            f"use .png or .jpg")
    return path


def check_textures(paths: list[Path] | None) -> None:
    """A one-line UserError for the first `--texture` photo that is not a file."""
    for t in paths or []:
        if not t.expanduser().is_file():
            raise UserError(f"--texture {t}: no such file")


def json_file(value: Path | None) -> Path | None:
    """typer callback of `--json`."""
    return None if value is None else check_output_file(value, "--json")


def image_file(value: Path | None) -> Path | None:
    """typer callback of `--save-vis`."""
    return None if value is None else check_output_file(value, "--save-vis", image=True)
