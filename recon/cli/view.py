"""`recon view OUT_DIR|FILE.rrd`: open a run's Rerun recording in the Rerun viewer."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def resolve_recording(target: Path) -> Path:
    """OUT_DIR -> OUT_DIR/recording.rrd (a `recon run` folder) or OUT_DIR/compare.rrd (a
    `recon compare` folder); a file is taken as is. UserError when there is none."""
    from recon.errors import UserError
    from recon.viz.compare_rerun import COMPARE_RECORDING
    from recon.viz.rerun_log import RECORDING_NAME

    p = target.expanduser()
    if p.is_dir():
        found = [p / n for n in (RECORDING_NAME, COMPARE_RECORDING) if (p / n).is_file()]
        if not found:
            raise UserError(f"{target}: no {RECORDING_NAME} or {COMPARE_RECORDING} here (run `recon run` or "
                            "`recon compare` without --rerun none)")
        p = found[0]
    elif not p.exists():
        raise UserError(f"{target}: no such recording or output folder")
    elif not p.is_file():
        raise UserError(f"{target}: not a file or folder")
    return p


RRD_MAGICS = (b"RRF0", b"RRF1", b"RRF2", b"RRIO")  # the first bytes of a Rerun recording file


def check_recording(path: Path) -> Path:
    """`path` when it holds a Rerun recording (by its first bytes, not its name); UserError
    otherwise, so that a text file or a photo is never handed to the viewer."""
    from recon.errors import UserError

    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise UserError(f"{path}: cannot read ({e.strerror or e})") from None
    if head[:4] not in RRD_MAGICS:
        what = "an empty file" if not head else "not a Rerun recording (.rrd)"
        raise UserError(f"{path}: {what}; give a `recon run` / `recon compare` output folder or its .rrd file")
    return path


def register(app: typer.Typer) -> None:
    @app.command("view")
    def view(
        target: Annotated[Path, typer.Argument(help="A `recon run` or `recon compare` output folder, or a .rrd file.")],
    ) -> None:
        """Open a Rerun recording (OUT_DIR/recording.rrd or compare.rrd) in the Rerun viewer."""
        import subprocess

        from recon.errors import UserError
        from recon.viz.rerun_log import find_viewer

        rrd = resolve_recording(target)
        exe = find_viewer()
        if exe is None:
            raise UserError("the Rerun viewer (`rerun`) is not installed; `pip install rerun-sdk` "
                            f"or open {rrd} at https://rerun.io/viewer")
        check_recording(rrd)
        from recon._signals import unblocked_for_children

        try:
            with unblocked_for_children():  # the viewer must answer Ctrl-C / SIGTERM itself
                code = subprocess.call([exe, str(rrd)])
        except OSError as e:
            raise UserError(f"cannot start the Rerun viewer {exe}: {e.strerror or e}") from None
        if code:
            raise SystemExit(code)
