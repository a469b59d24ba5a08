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
    elif not p.is_file():
        raise UserError(f"{target}: no such recording or output folder")
    return p


def register(app: typer.Typer) -> None:
    @app.command("view")
    def view(
        target: Annotated[Path, typer.Argument(help="A `recon run` or `recon compare` output folder, or a .rrd file.", metavar="TARGET")],
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
        try:
            code = subprocess.call([exe, str(rrd)])
        except OSError as e:
            raise UserError(f"cannot start the Rerun viewer {exe}: {e.strerror or e}") from None
        if code:
            raise SystemExit(code)
