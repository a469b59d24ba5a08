"""The `recon` command line: a thin typer layer over library functions.

Each command lives in its own module of this package exposing `register(app)` (modules whose
name starts with `_` are helpers). `main()` is the one place where exceptions become messages:
never a traceback, at most one `recon: error:` line, and a documented exit code.

Exit codes:

* 0: done.
* 1: the command ran but gave no result (`recon run` found no model), an unexpected internal
  error ("recon: internal error: <type>: <message> (rerun with -v for the traceback)"; with
  `-v` or `RECON_DEBUG=1` the traceback is printed; the hint names RECON_DEBUG=1 while the app
  has no -v option), or an environment failure the user cannot fix by changing the command (an
  I/O error, out of memory).
* 2: refused or stopped for a reason the user can fix, named on one line: a bad option or
  usage, an unusable input file or folder, an output folder that is not ours or is in use by
  another run, or a file-system problem with a path (permission denied, not a folder, no space
  left on device). Everything written so far is complete; rerunning resumes.
* 130: interrupted by Ctrl-C (SIGINT); 143: terminated (SIGTERM). Both print one line, run every
  cleanup (temporary files are removed, outputs stay consistent) and can be resumed by
  rerunning the same command. A second signal exits at once.

Signals are handled by `recon._signals`, installed by `recon/__init__.py` before anything heavy
is imported (so Ctrl-C in the first second gives no traceback either) and kept in place when
pycolmap is imported (its glog failure handler would answer SIGTERM with a C stack dump).
"""

from __future__ import annotations

import os
import signal
import sys
from typing import Annotated

import typer

from matching.errors import InputError
from recon import _signals
from recon.errors import UserError
from recon.version import DISTRIBUTION, version  # noqa: F401  (re-exported)

app = typer.Typer(
    name="recon",
    help="Extra-affine wide-viewpoint matching and COLMAP reconstruction.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # -h as well as --help on every command (click contexts inherit it from the group's)
    context_settings={"help_option_names": ["-h", "--help"]},
)

def _print_version(value: bool) -> None:
    if value:
        print(f"recon {version()}")
        raise typer.Exit()


@app.callback()
def _global_options(
    verbose: Annotated[bool, typer.Option(
        "-v", "--verbose", help="Debug logs and COLMAP's own log on stderr.", metavar="")] = False,
    show_version: Annotated[bool, typer.Option(
        "--version", help="Print the version and exit.", metavar="", is_eager=True,
        callback=_print_version)] = False,
) -> None:
    """Options before the command name (`recon -v run ...`): logging, set up once per command."""
    from recon.log import setup_logging

    setup_logging(verbose)


_registered = False


def _register_commands() -> None:
    """Import every command module of this package and let it add its command(s), once per process."""
    global _registered
    if _registered:
        return
    import importlib
    import pkgutil

    for mod in sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")):
        register = getattr(importlib.import_module(f"{__name__}.{mod}"), "register", None)
        if register is not None:  # helper modules (options) add no command
            register(app)
    _registered = True


# exceptions -> one line ----------------------------------------------------------------------------
def _click_exception_types(name: str) -> tuple[type, ...]:
    """`name` (e.g. "ClickException", "Abort") from every click in use: click itself and the copy
    typer vendors as `typer._click` (whose classes do not derive from click's). Missing ones are
    skipped: typer 0.29's `typer._click.exceptions` has no Abort (it is `typer.exceptions.Abort`)."""
    found: list[type] = []
    for modname in ("click.exceptions", "typer._click.exceptions", "typer.exceptions"):
        mod = sys.modules.get(modname)
        if mod is None:
            try:
                import importlib

                mod = importlib.import_module(modname)
            except Exception:
                continue
        t = getattr(mod, name, None)
        if isinstance(t, type) and t not in found:
            found.append(t)
    return tuple(found)


_FIXABLE_ERRNOS = {"ENOSPC", "EDQUOT", "EACCES", "EPERM", "EROFS", "EISDIR", "ENOTDIR", "ENOENT",
                   "ENAMETOOLONG", "EEXIST", "ENOTEMPTY", "ELOOP", "EFBIG", "EMFILE", "ENFILE"}


def _disk_full(e: BaseException) -> bool:
    import errno

    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    text = str(e).lower()
    return "no space left on device" in text or "database or disk is full" in text


def _os_error_line(e: OSError) -> tuple[int, str]:
    """(exit code, message) for a file-system error, naming the path."""
    import errno

    path = e.filename if e.filename is not None else None
    if e.filename2 is not None:
        path = f"{e.filename} -> {e.filename2}"
    where = f" {path}" if path else ""
    name = errno.errorcode.get(e.errno or 0, "")
    if _disk_full(e):
        return 2, f"no space left on device writing{where or ' (path unknown)'}; free some space and rerun to resume"
    messages = {
        "EACCES": f"permission denied:{where}", "EPERM": f"operation not permitted:{where}",
        "EROFS": f"read-only file system:{where}", "EISDIR": f"{path or 'the path'} is a folder, expected a file",
        "ENOTDIR": f"{path or 'the path'}: a part of this path is not a folder",
        "ENOENT": f"no such file or folder:{where}", "ENAMETOOLONG": f"file name too long:{where}",
        "EEXIST": f"already exists:{where}", "ELOOP": f"too many symbolic links:{where}",
    }
    if path and name in messages:
        msg = messages[name]
    elif path:
        msg = f"{e.strerror or type(e).__name__}:{where}"
    else:
        msg = str(e) or type(e).__name__
    return (2 if name in _FIXABLE_ERRNOS else 1), msg


def _debug_wanted(argv: list[str] | None) -> bool:
    if os.environ.get("RECON_DEBUG", "").strip() not in ("", "0"):
        return True
    args = sys.argv[1:] if argv is None else list(argv)
    if "--" in args:
        args = args[: args.index("--")]
    return any(a in ("-v", "--verbose") for a in args)


def _quiet_opencv(argv: list[str] | None) -> None:
    """Keep OpenCV's own C++ log lines (a broken PNG's "[ WARN:0@0.8] global grfmt_png.cpp ..." and
    "[ERROR:0@0.8] ... IHDR chunk shall be first") off stderr: the CLI reports such inputs itself,
    on one line of its own, and OpenCV's failures that matter raise. `-v`, `RECON_DEBUG=1` or the
    user's own `OPENCV_LOG_LEVEL` keep OpenCV's default."""
    if _debug_wanted(argv) or os.environ.get("OPENCV_LOG_LEVEL"):
        return
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _exit_code_for(e: BaseException, argv: list[str] | None) -> int:
    """Print the one line for `e` on stderr and return the exit code (see module doc)."""

    def line(msg: str) -> None:
        text = " ".join(str(msg).split())  # one line, whatever the message held
        print(f"recon: error: {text}", file=sys.stderr)

    if isinstance(e, (InputError, UserError)):
        line(str(e))
        return 2
    if isinstance(e, _click_exception_types("NoArgsIsHelpError")):
        e.show()  # type: ignore[attr-defined]  # prints the help
        return 2
    if isinstance(e, _click_exception_types("ClickException")):
        msg = e.format_message()  # type: ignore[attr-defined]
        ctx = getattr(e, "ctx", None)
        hint = f" (see {ctx.command_path} --help)" if ctx is not None and isinstance(
            e, _click_exception_types("UsageError")) else ""
        line(f"{msg}{hint}")
        return 2
    if isinstance(e, _click_exception_types("Abort")):
        print("recon: aborted", file=sys.stderr)
        return 130
    if isinstance(e, OSError) or _disk_full(e):
        if isinstance(e, OSError):
            code, msg = _os_error_line(e)
        else:
            code, msg = 2, f"no space left on device ({' '.join(str(e).split())}); free some space and rerun to resume"
        line(msg)
        if code == 1 and _debug_wanted(argv):
            import traceback

            traceback.print_exception(e)
        return code
    if isinstance(e, MemoryError):
        line("out of memory; try a smaller --max-size or fewer --workers")
        return 1
    if _debug_wanted(argv):
        import traceback

        traceback.print_exception(e)
    how = "-v" if _has_verbose_option() else "RECON_DEBUG=1"
    print(f"recon: internal error: {type(e).__name__}: {' '.join(str(e).split())} "
          f"(rerun with {how} for the traceback)", file=sys.stderr)
    return 1


def _has_verbose_option() -> bool:
    """True when the app has a top-level -v/--verbose option (an `@app.callback()`)."""
    try:
        cmd = typer.main.get_command(app)
        return any(o in ("-v", "--verbose") for p in cmd.params for o in getattr(p, "opts", ()))
    except Exception:
        return False


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (see module doc). Never raises, never a traceback
    (except with -v / RECON_DEBUG=1 for an internal error)."""
    entry = _signals.is_program_entry()
    if not entry:
        _signals.reset()  # a library caller (tests) may call main several times
    _signals.install(raising=True)
    code = 1
    try:
        try:
            if _signals.received is not None:  # a signal while the modules were importing
                raise KeyboardInterrupt
            from matching.memory import return_large_buffers_to_os

            return_large_buffers_to_os()
            _quiet_opencv(argv)
            _register_commands()
            # with standalone_mode=False click returns the code of `typer.Exit(n)` (and typer
            # turns a KeyboardInterrupt inside a command into a returned 130) instead of raising
            rv = app(args=argv, prog_name="recon", standalone_mode=False)
            code = rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
        except KeyboardInterrupt:
            code = 130
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            if not isinstance(e.code, (int, type(None))):
                print(f"recon: error: {e.code}", file=sys.stderr)
        except BaseException as e:  # noqa: BLE001  (the one place that turns exceptions into lines)
            if _signals.received is not None:
                code = 130  # a consequence of the signal (e.g. a library half-imported): one line below
            elif isinstance(e, _click_exception_types("Exit")):
                code = int(getattr(e, "exit_code", 0) or 0)
            else:
                code = _exit_code_for(e, argv)
        if _signals.received is not None or code == 130:
            sig = _signals.received or signal.SIGINT
            print("recon: " + ("terminated" if sig == signal.SIGTERM else "interrupted")
                  + "; rerun the same command to resume", file=sys.stderr)
            code = 128 + sig
        try:
            sys.stdout.flush()
        except (BrokenPipeError, ValueError):  # `recon ... | head`: the reader left; not an error
            try:
                sys.stdout = open(os.devnull, "w")  # noqa: SIM115
            except OSError:
                pass
        return code
    except KeyboardInterrupt:  # a signal while printing the message above
        code = 128 + (_signals.received or signal.SIGINT)
        return code
    finally:
        if not entry:  # a library caller (tests) keeps its own handlers
            _signals.restore()
        else:
            _exit_now_if_rerun_abandoned(code)


def _exit_now_if_rerun_abandoned(code: int) -> None:
    """End the program at once when a Rerun stream was given up on (no viewer listening): every
    output is written and closed by now, and rerun's exit-time teardown would wait for the
    absent viewer again (several seconds). Only for the program itself, never a library caller."""
    mod = sys.modules.get("recon.viz.rerun_log")
    if mod is None or not getattr(mod, "abandoned_streams", lambda: 0)():
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    os._exit(code)
