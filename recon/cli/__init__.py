"""The `recon` command line: a thin typer layer over library functions.

Each command lives in its own module of this package exposing `register(app)`. `main()` turns
user errors (`InputError`, `UserError`) into one-line messages with a non-zero exit, never a
traceback; Ctrl-C exits 130 after whatever was written has been left consistent.
"""

from __future__ import annotations

import sys
from typing import Annotated

import typer

from matching.errors import InputError
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
    _registered = True
    import importlib
    import pkgutil

    for mod in sorted(m.name for m in pkgutil.iter_modules(__path__)):
        register = getattr(importlib.import_module(f"{__name__}.{mod}"), "register", None)
        if register is not None:  # helper modules (options) add no command
            register(app)


def main(argv: list[str] | None = None) -> int:
    from matching.memory import return_large_buffers_to_os

    return_large_buffers_to_os()
    _register_commands()
    try:
        # with standalone_mode=False click returns the code of `typer.Exit(n)` (and of an
        # interrupted prompt) instead of raising it
        rv = app(args=argv, standalone_mode=False)
        if isinstance(rv, int) and not isinstance(rv, bool):
            return rv
    except (InputError, UserError) as e:
        print(f"recon: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("recon: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except typer.Exit as e:
        return int(e.exit_code or 0)
    except SystemExit as e:
        return int(e.code or 0) if isinstance(e.code, int) else 1
    except Exception as e:  # click usage errors and friends
        import click

        # recent typer (0.29 here) vendors click as `typer._click`, whose exceptions do not derive
        # from click's: check both, or every usage error becomes a traceback with exit 1
        mods = [click.exceptions]
        try:
            from typer._click import exceptions as typer_click_exceptions

            mods.append(typer_click_exceptions)
        except ImportError:
            pass
        if any(isinstance(e, m.ClickException) for m in mods):
            e.show()
            return e.exit_code
        if any(isinstance(e, m.Abort) for m in mods):
            print("recon: aborted", file=sys.stderr)
            return 130
        raise
    return 0


