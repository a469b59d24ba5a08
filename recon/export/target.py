"""The destination folder of an export: checked, built aside, renamed into place.

Rules (each refusal is a one-line `UserError`):

* `DIR` may not be, or contain, the run folder or the scene's image folder (replacing it would
  delete them), nor lie inside an `images/` folder (the next `recon run` would take the exported
  images for photos of the scene; photos directly in SCENE_DIR are listed from its top level
  only, so its subfolders, e.g. the default `SCENE_DIR/recon/export/...`, are allowed) or
  inside the run's `sparse/` or `cache/` (`recon run` rewrites those).
* An existing non-empty `DIR` is replaced only with `overwrite`, and only when it is a previous
  export (it holds `EXPORT_MARKER`), never somebody else's folder.

`staged(DIR)` yields a fresh temporary sibling folder `.DIR.export-tmp-<pid>`; when the block
ends without an error it is renamed to `DIR` (an old `DIR` is moved aside first and deleted
after), so `DIR` is at every moment absent, the old export or the complete new one. On an error
or Ctrl-C the temporary folder is removed.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from recon.core.scene import lists_subfolders
from recon.errors import UserError

EXPORT_MARKER = ".recon_export.json"


def _inside(p: Path, parent: Path) -> bool:
    """p == parent or p lies below parent (both resolved)."""
    return p == parent or parent in p.parents


def check_target(to: Path, out_dir: Path, image_dir: Path, overwrite: bool) -> Path:
    """The resolved destination, or UserError (see module doc)."""
    dst = to.expanduser().resolve()
    for protected, what in ((out_dir, "the run folder"), (image_dir, "the scene's image folder")):
        if _inside(protected, dst):
            raise UserError(f"export folder {dst} would replace {what} {protected}; choose another --to")
    if lists_subfolders(image_dir) and _inside(dst, image_dir):  # photos at SCENE_DIR's top level: a
        # subfolder of it (OUT/export/...) is never read as photos
        raise UserError(f"export folder {dst} is inside the scene's image folder {image_dir}; "
                        "choose another --to outside it")
    for sub in ("sparse", "cache"):
        if _inside(dst, out_dir / sub):
            raise UserError(f"export folder {dst} is inside {out_dir / sub}, which `recon run` rewrites; "
                            "choose another --to")
    if dst.exists() and not dst.is_dir():
        raise UserError(f"export folder {dst} exists and is not a folder; choose another --to")
    if dst.is_dir() and any(dst.iterdir()):
        if not overwrite:
            raise UserError(f"export folder {dst} is not empty; pass --overwrite to replace the previous export "
                            "or choose another --to")
        if not (dst / EXPORT_MARKER).is_file():
            raise UserError(f"export folder {dst} is not empty and holds no earlier export (no {EXPORT_MARKER}); "
                            "choose another --to")
    return dst


@contextmanager
def staged(dst: Path) -> Iterator[Path]:
    """Build in a temporary sibling of `dst`, then rename it into place (see module doc)."""
    made_parent = not dst.parent.exists()
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot create {dst.parent}: {e.strerror or e}") from None
    tmp = dst.with_name(f".{dst.name}.export-tmp-{os.getpid()}")
    old = dst.with_name(f".{dst.name}.export-old-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir()
    except OSError as e:
        raise UserError(f"cannot write to {dst.parent}: {e.strerror or e}; choose another --to") from None
    moved_aside = False
    try:
        yield tmp
        if dst.exists():
            os.replace(dst, old)
            moved_aside = True
        os.replace(tmp, dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if moved_aside and not dst.exists():  # the rename failed: put the previous export back
            os.replace(old, dst)
        if made_parent:  # e.g. OUT_DIR/export made for nothing
            with contextlib.suppress(OSError):
                dst.parent.rmdir()
        raise
    shutil.rmtree(old, ignore_errors=True)
