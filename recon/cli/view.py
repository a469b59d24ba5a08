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


WEB_PORT = 9090  # rerun's default web viewer port
GRPC_PORT = 9876  # rerun's default gRPC port (the web page streams the recording from it)


def has_display() -> bool:
    """Whether a native window can open: always on macOS and Windows; on Linux and other Unixes,
    when DISPLAY (X11) or WAYLAND_DISPLAY is set."""
    import os
    import sys

    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def web_command(exe: str, rrd: Path, port: int = WEB_PORT, grpc_port: int = GRPC_PORT,
                bind: str = "127.0.0.1") -> list[str]:
    """`rerun --serve-web` for one recording: the web viewer on http://BIND:PORT, the recording
    streamed to it from a gRPC server on GRPC_PORT (the browser needs both ports)."""
    return [exe, "--serve-web", "--bind", bind, "--web-viewer-port", str(port), "--port", str(grpc_port),
            str(rrd)]


def web_url(port: int = WEB_PORT, grpc_port: int = GRPC_PORT, host: str = "localhost") -> str:
    """The address to open: the web viewer, told where to read the recording from."""
    from urllib.parse import quote

    return f"http://{host}:{port}/?url={quote(f'rerun+http://{host}:{grpc_port}/proxy', safe='')}"


def register(app: typer.Typer) -> None:
    @app.command("view")
    def view(
        target: Annotated[Path, typer.Argument(help="A `recon run` or `recon compare` output folder, or a .rrd file.",
                                               metavar="TARGET")],
        web: Annotated[bool, typer.Option(
            "--web", metavar="", help="Serve Rerun's web viewer instead of opening a window (for a machine "
                                      "without a display; over ssh, forward --port and --grpc-port).")] = False,
        port: Annotated[int, typer.Option("--port", help="--web: the web viewer's HTTP port.")] = WEB_PORT,
        grpc_port: Annotated[int, typer.Option("--grpc-port", help="--web: the port the recording is "
                                                                   "streamed from.")] = GRPC_PORT,
        bind: Annotated[str, typer.Option("--bind", help="--web: address to listen on (0.0.0.0 = every "
                                                         "interface).")] = "127.0.0.1",
    ) -> None:
        """Open a Rerun recording (OUT_DIR/recording.rrd or compare.rrd) in the Rerun viewer."""
        import subprocess
        import sys

        from recon.errors import UserError
        from recon.viz.rerun_log import find_viewer

        rrd = resolve_recording(target)
        exe = find_viewer()
        if exe is None:
            raise UserError("the Rerun viewer (`rerun`) is not installed; `pip install rerun-sdk` "
                            f"or open {rrd} at https://rerun.io/viewer")
        check_recording(rrd)
        if not web and not has_display():
            raise UserError(f"no display here (DISPLAY and WAYLAND_DISPLAY are unset); use `recon view --web "
                            f"{target}` and open the address it prints in a browser")
        cmd = [exe, str(rrd)]
        if web:
            cmd = web_command(exe, rrd, port, grpc_port, bind)
            print(f"recon: serving {rrd} with Rerun's web viewer; open {web_url(port, grpc_port)} "
                  "(Ctrl-C to stop)", file=sys.stderr)
        from recon._signals import unblocked_for_children

        try:
            with unblocked_for_children():  # the viewer must answer Ctrl-C / SIGTERM itself
                code = subprocess.call(cmd)
        except KeyboardInterrupt:  # Ctrl-C ends the viewer (same process group) and this command
            return
        except OSError as e:
            raise UserError(f"cannot start the Rerun viewer {exe}: {e.strerror or e}") from None
        if code:
            raise SystemExit(code)
