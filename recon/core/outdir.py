"""The output folder: created, checked writable, tied to its scene, and cleaned of our own files only.

The folder is tied to its scene by `OUT/.recon_scene.json` (scene path + image file names); a
different scene is refused. `--overwrite` deletes only the names in `OWN_OUTPUTS` (and the
temporary leftovers of killed runs), never other files; a non-empty folder that is not ours is
refused.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
from pathlib import Path

from recon.core.jsonio import write_json_atomic
from recon.core.scene import find_image_dir
from recon.errors import UserError

SCENE_MARKER = ".recon_scene.json"
OWN_OUTPUTS = ("cache", "recording.rrd", "database.db", "database.db.tmp", "database.db-journal", "database.db-wal",
               "database.db-shm", "sparse", "points.ply", "report.json", SCENE_MARKER)


def _no_write_bits(p: Path) -> bool:
    try:
        return not (p.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    except OSError:
        return False


def _check_writable(out: Path, default_out: bool) -> None:
    """UserError unless `out` can be created and written. A folder without any write permission
    bit counts as read-only even for root (who could write anyway): its owner made it so."""
    hint = ("pass --out DIR to write the reconstruction elsewhere" if default_out
            else "choose another --out DIR")
    probe = out
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and (not os.access(probe, os.W_OK | os.X_OK) or _no_write_bits(probe)):
        raise UserError(f"cannot write to {out}: {probe} is read-only; {hint}")
    try:
        out.mkdir(parents=True, exist_ok=True)
        t = out / f".write-test-{os.getpid()}"
        t.write_bytes(b"")
        t.unlink()
    except OSError as e:
        raise UserError(f"cannot write to {out}: {e.strerror or e}; {hint}") from None


def remove_outputs(out: Path, names: tuple[str, ...] = OWN_OUTPUTS) -> None:
    """Delete the named outputs in `out` and the temporary leftovers of killed runs, nothing else."""
    for name in names:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        elif p.exists() or p.is_symlink():
            p.unlink()
    for p in out.glob(".*tmp-*"):  # leftovers of a killed run: .sfm-tmp-<pid>, .report.json.tmp-<pid>, ...
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def prepare_out(out: Path, root: Path, candidates: list[str], overwrite: bool, default_out: bool) -> None:
    """Create/check the output folder and tie it to this scene (see module doc)."""
    marker = out / SCENE_MARKER
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is not a folder")
    if out.is_dir():
        if marker.is_file():
            try:
                rec = json.loads(marker.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                rec = {}
            if not overwrite and rec.get("scene") != str(root):
                raise UserError(f"{out} holds the reconstruction of another scene ({rec.get('scene', '?')}); "
                                f"pass --overwrite to replace it or choose another --out")
            if not overwrite and rec.get("images") != candidates:
                raise UserError(f"{out} was made from a different image list of this scene; "
                                f"pass --overwrite to start over or choose another --out")
        else:  # never write into (or, with --overwrite, delete from) somebody else's folder
            stray = sorted(p.name for p in out.iterdir() if p.name not in OWN_OUTPUTS and not p.name.startswith(".write-test"))
            if stray:
                raise UserError(f"{out} is not empty and is not a recon output folder "
                                f"(found {stray[0]}); choose another --out")
    _check_writable(out, default_out)
    if overwrite:
        remove_outputs(out)
    write_json_atomic(marker, {"scene": str(root), "image_dir": str(find_image_dir(root)), "images": candidates})
